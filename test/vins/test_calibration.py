"""Kalibr and camera_info calibrations -> VINS-Fusion config folders."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from calibration_files import EQUI, RADTAN, SHIPPED, K, camera_info, dump, shipped_camchain

from nsflow_ros.core.camera import KannalaBrandtCamera, MeiCamera, PinholeCamera
from nsflow_ros.core.opencv_yaml import read_opencv_yaml
from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.vins.calibration import (
    Calibration,
    CameraCalibration,
    ImuCalibration,
    parse_transform,
    read_camera_info,
    read_camera_infos,
    read_kalibr_camchain,
    read_kalibr_imu,
    render_vins_config,
    write_vins_config,
)
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.errors import ConfigError


def _from_kalibr(camchain: Path, imu: Path | None, out: Path, **kwargs) -> Path:
    cameras, td = read_kalibr_camchain(camchain, **kwargs)
    imu_cal = read_kalibr_imu(imu) if imu is not None else None
    return write_vins_config(out, Calibration(cameras, imu_cal, td))[0]


def _points(n: int = 200, seed: int = 0, half_angle: float = 0.6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-np.tan(half_angle), np.tan(half_angle), (n, 2))
    return np.c_[xy, np.ones(n)] * rng.uniform(0.5, 20.0, (n, 1))


# ----------------------------------------------------------------------------------------------------------
# Kalibr -> the shipped EuRoC config


def test_camchain_of_the_shipped_calibration_gives_the_shipped_config(tmp_path):
    camchain, imu = shipped_camchain(tmp_path)
    path = _from_kalibr(camchain, imu, tmp_path / "out")
    assert sorted(p.name for p in path.parent.iterdir()) == ["cam0_pinhole.yaml", "cam1_pinhole.yaml",
                                                            "vins_config.yaml"]
    made, shipped = load_vins_config(path), load_vins_config(SHIPPED)
    pixels = np.stack(np.meshgrid(np.linspace(0, 751, 24), np.linspace(0, 479, 16)), -1).reshape(-1, 2)
    for mine, ref in zip(made.cameras, shipped.cameras, strict=True):
        assert type(mine) is PinholeCamera and mine.parameters == ref.parameters
        np.testing.assert_allclose(mine.project(_points()), ref.project(_points()), rtol=0, atol=1e-6)
        np.testing.assert_allclose(mine.lift(pixels) * ref.fx, ref.lift(pixels) * ref.fx, rtol=0, atol=1e-6)
    for mine, ref in zip(made.body_T_cam, shipped.body_T_cam, strict=True):
        np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-12)
    # every key of the shipped config, with its value (the files named differ only in case of the model)
    written, expected = read_opencv_yaml(path), read_opencv_yaml(SHIPPED)
    for key, value in expected.items():
        if key.startswith("body_T_cam"):
            continue
        assert written[key] == value, key


def test_tracker_on_the_generated_config_gives_the_shipped_features(tmp_path):
    camchain, imu = shipped_camchain(tmp_path)
    made = load_vins_config(_from_kalibr(camchain, imu, tmp_path / "out"))
    shipped = load_vins_config(SHIPPED)
    seq = make_sample_sequence(tmp_path / "seq", seed=0, duration=0.5, stereo=True, formats=("asl",),
                               progress=False)
    trackers = [FeatureTracker(list(c.cameras), TrackerSettings(method="klt", stereo=True))
                for c in (made, shipped)]
    total = 0
    for i in range(len(seq)):
        images = seq.image(i, 0), seq.image(i, 1)
        mine, ref = (t.process(seq.time(i), *images) for t in trackers)
        for a, b in zip(mine.cameras, ref.cameras, strict=True):
            assert np.array_equal(a.ids, b.ids)
            assert np.array_equal(a.pixels, b.pixels) and np.array_equal(a.undistorted, b.undistorted)
            assert np.array_equal(a.velocities, b.velocities)
            total += len(a)
    assert total > 1000


def test_camchain_without_imu_chains_cam1_from_cam0(tmp_path):
    camchain, _ = shipped_camchain(tmp_path)
    data = yaml.safe_load(camchain.read_text())
    t0, t1 = (np.array(data[f"cam{i}"].pop("T_cam_imu")) for i in (0, 1))
    data["cam1"]["T_cn_cnm1"] = (t1 @ np.linalg.inv(t0)).tolist()
    dump(camchain, data)
    with pytest.raises(ConfigError, match=r"missing key 'cam0/T_cam_imu' \(or give the cam0 -> body "
                                          r"transform with --body-T-cam0\)"):
        read_kalibr_camchain(camchain)
    shipped = load_vins_config(SHIPPED)
    del data["cam1"]["T_cn_cnm1"]
    dump(camchain, data)
    with pytest.raises(ConfigError, match=r"missing key 'cam1/T_cn_cnm1' \(the transform from cam0; nor is "
                                          r"there 'cam1/T_cam_imu'\), or give .* with --body-T-cam1$"):
        read_kalibr_camchain(camchain, [shipped.body_T_cam[0]])
    data["cam1"]["T_cn_cnm1"] = (t1 @ np.linalg.inv(t0)).tolist()
    dump(camchain, data)
    shipped = load_vins_config(SHIPPED)
    cameras, _ = read_kalibr_camchain(camchain, [shipped.body_T_cam[0]])
    np.testing.assert_allclose(cameras[1].body_T_cam, shipped.body_T_cam[1], rtol=0, atol=1e-9)
    mono, _ = read_kalibr_camchain(camchain, [shipped.body_T_cam[0]], num_of_cam=1)
    assert len(mono) == 1


# ----------------------------------------------------------------------------------------------------------
# Fisheye and omnidirectional Kalibr models

def _chain(tmp_path: Path, model: str, distortion: str, intrinsics: list[float], coeffs: list[float]) -> Path:
    cam = {"camera_model": model, "distortion_model": distortion, "intrinsics": intrinsics,
           "distortion_coeffs": coeffs, "resolution": [640, 480], "rostopic": "/fisheye/image_raw",
           "T_cam_imu": np.eye(4).tolist(), "timeshift_cam_imu": -0.0042}
    return dump(tmp_path / "camchain.yaml", {"cam0": cam})


def test_pinhole_equidistant_becomes_kannala_brandt_projecting_as_opencv_fisheye(tmp_path):
    chain = _chain(tmp_path, "pinhole", "equidistant", list(K.values()), EQUI)
    (cal,), td = read_kalibr_camchain(chain)
    assert td == -0.0042 and cal.topic == "/fisheye/image_raw"
    cam = cal.camera
    assert isinstance(cam, KannalaBrandtCamera) and (cam.k2, cam.k3, cam.k4, cam.k5) == tuple(EQUI)
    pts = _points(half_angle=1.2)
    matrix = np.array([[K["fu"], 0, K["pu"]], [0, K["fv"], K["pv"]], [0, 0, 1]])
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), matrix, np.array(EQUI))
    np.testing.assert_allclose(cam.project(pts), ref[:, 0], rtol=0, atol=1e-6)
    # written and read back: same parameters, model named in the file
    imu = ImuCalibration(0.1, 0.01, 0.001, 0.0001, "/imu")
    path = write_vins_config(tmp_path / "out", Calibration((cal,), imu, td))[0]
    loaded = load_vins_config(path)
    assert read_opencv_yaml(path)["cam0_calib"] == "cam0_kannala_brandt.yaml"
    assert loaded.cameras[0].parameters == cam.parameters and not loaded.stereo
    np.testing.assert_allclose(loaded.cameras[0].project(pts), ref[:, 0], rtol=0, atol=1e-6)


def _mei_reference(pts: np.ndarray, xi: float, fu: float, fv: float, pu: float, pv: float,
                   coeffs: list[float]) -> np.ndarray:
    """Kalibr's omni-radtan projection, written out from its definition."""
    k1, k2, p1, p2 = coeffs
    z = pts[:, 2] + xi * np.linalg.norm(pts, axis=1)
    x, y = pts[:, 0] / z, pts[:, 1] / z
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.c_[fu * xd + pu, fv * yd + pv]


def test_omni_radtan_becomes_mei(tmp_path):
    xi = 0.92
    chain = _chain(tmp_path, "omni", "radtan", [xi, *K.values()], RADTAN)
    (cal,), _ = read_kalibr_camchain(chain)
    cam = cal.camera
    assert isinstance(cam, MeiCamera) and cam.xi == xi and (cam.gamma1, cam.u0) == (K["fu"], K["pu"])
    pts = _points(half_angle=0.9)
    np.testing.assert_allclose(cam.project(pts), _mei_reference(pts, xi, *K.values(), RADTAN), atol=1e-6)
    rays = cam.lift(cam.project(pts))
    np.testing.assert_allclose(rays, pts[:, :2] / pts[:, 2:], atol=1e-4)  # 8 camodocal iterations


# ----------------------------------------------------------------------------------------------------------
# camera_info


def test_camera_info_plumb_bob_and_equidistant(tmp_path):
    matrix = np.array([[K["fu"], 0, K["pu"]], [0, K["fv"], K["pv"]], [0, 0, 1]])
    pts = _points()
    pinhole = read_camera_info(camera_info(tmp_path / "left.yaml", "plumb_bob", [*RADTAN, 0.0]))
    assert isinstance(pinhole, PinholeCamera) and pinhole.name == "narrow_stereo/left"
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), matrix, np.array(RADTAN))
    np.testing.assert_allclose(pinhole.project(pts), ref[:, 0], rtol=0, atol=1e-6)
    fisheye = read_camera_info(camera_info(tmp_path / "fish.yaml", "equidistant", EQUI))
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), matrix, np.array(EQUI))
    assert isinstance(fisheye, KannalaBrandtCamera)
    np.testing.assert_allclose(fisheye.project(pts), ref[:, 0], rtol=0, atol=1e-6)


def test_camera_info_stereo_with_separate_extrinsics(tmp_path):
    shipped = load_vins_config(SHIPPED)
    paths = [camera_info(tmp_path / f"{side}.yaml", "plumb_bob", RADTAN, "") for side in ("l", "r")]
    cameras = read_camera_infos(paths, shipped.body_T_cam, ["/left", "/right"])
    path = write_vins_config(tmp_path / "out", Calibration(cameras))[0]  # stereo: no IMU needed
    cfg = load_vins_config(path)
    assert cfg.image_topics == ("/left", "/right") and not cfg.use_imu and cfg.stereo
    assert [c.name for c in cfg.cameras] == ["cam0", "cam1"]
    for mine, ref in zip(cfg.body_T_cam, shipped.body_T_cam, strict=True):
        np.testing.assert_array_equal(mine, ref)  # written with 17 digits: read back bit for bit
    assert read_camera_infos(paths[:1], [None])[0].topic == "/cam0/image_raw"


# ----------------------------------------------------------------------------------------------------------
# Transforms given separately


def test_parse_transform_numbers_and_files(tmp_path):
    shipped = load_vins_config(SHIPPED).body_T_cam[0]
    text = " ".join(repr(float(v)) for v in shipped.ravel())
    np.testing.assert_array_equal(parse_transform(text), shipped)
    np.testing.assert_array_equal(parse_transform(text.replace(" ", ",")), shipped)
    sensor = tmp_path / "sensor.yaml"  # EuRoC's sensor.yaml layout
    sensor.write_text("sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [" + ", ".join(
        repr(float(v)) for v in shipped.ravel()) + "]\nrate_hz: 20\n")
    np.testing.assert_array_equal(parse_transform(str(sensor)), shipped)
    with pytest.raises(ConfigError, match=r"--body-T-cam0: expected 16 finite numbers .*got 15"):
        parse_transform(" ".join(text.split()[:15]), "--body-T-cam0")
    with pytest.raises(ConfigError, match="not a rigid transform"):
        parse_transform(" ".join(["2"] * 16))
    with pytest.raises(ConfigError, match="neither 16 numbers nor an existing file"):
        parse_transform(str(tmp_path / "missing.yaml"))
    with pytest.raises(ConfigError, match="'x1 2' is neither"):
        parse_transform("x1 2")


# ----------------------------------------------------------------------------------------------------------
# Errors: one line naming the file and the key


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: c["cam0"].pop("intrinsics"), "missing key 'cam0/intrinsics'"),
        (lambda c: c["cam0"].update(camera_model="ds"), "key 'cam0/camera_model' ds-radtan has no camodocal"),
        (lambda c: c["cam1"].update(distortion_model="fov"), "key 'cam1/distortion_model' pinhole-fov"),
        (lambda c: c["cam1"].update(resolution=[640, 480]), "cam1 is 640x480 but cam0 is 752x480"),
        (lambda c: c["cam0"].update(intrinsics=[1.0, 2.0, 3.0]), "key 'cam0/intrinsics' must hold 4 numbers"),
        (lambda c: c["cam0"].update(intrinsics=[-458.0, 457.0, 367.0, 248.0]), "'cam0/intrinsics' gives an "
                                                                               "invalid camera"),
        (lambda c: c["cam1"].pop("T_cam_imu"), "missing key 'cam1/T_cn_cnm1' (the transform from cam0; nor "
                                               "is there 'cam1/T_cam_imu'), or give the cam1 -> body "
                                               "transform with --body-T-cam1"),
        (lambda c: c["cam0"]["T_cam_imu"][0].__setitem__(0, 3.0), "'cam0/T_cam_imu' is not a rigid"),
        (lambda c: c["cam0"].update(rostopic="/cam 0"), "'cam0/rostopic' is not a ROS topic name"),
        (lambda c: c.update(cam2=c["cam1"]), "has 3 camera(s); a VINS-Fusion config takes 1 or 2"),
    ],
)
def test_kalibr_errors_name_the_key(tmp_path, edit, message):
    camchain, imu = shipped_camchain(tmp_path)
    data = yaml.safe_load(camchain.read_text())
    edit(data)
    dump(camchain, data)
    with pytest.raises(ConfigError) as err:
        _from_kalibr(camchain, imu, tmp_path / "out")
    text = str(err.value)
    assert message in text and "\n" not in text
    assert text.startswith(str(camchain)) or "cam0 is" in text
    assert not (tmp_path / "out" / "vins_config.yaml").exists()


def test_imu_and_camera_info_errors_name_the_key(tmp_path):
    _, imu = shipped_camchain(tmp_path)
    data = yaml.safe_load(imu.read_text())
    del data["imu0"]["gyroscope_random_walk"]
    dump(imu, data)
    with pytest.raises(ConfigError, match=r"imu\.yaml: missing key 'imu0/gyroscope_random_walk'$"):
        read_kalibr_imu(imu)
    flat = dump(tmp_path / "flat.yaml", {
        "accelerometer_noise_density": 0.01, "accelerometer_random_walk": 0.0,
        "gyroscope_noise_density": 0.001, "gyroscope_random_walk": 1e-5,
    })
    with pytest.raises(ConfigError, match="'accelerometer_random_walk' must be > 0"):
        read_kalibr_imu(flat)
    with pytest.raises(ConfigError, match=r"k3 = 0\.01; camodocal's PINHOLE has no k3"):
        read_camera_info(camera_info(tmp_path / "k3.yaml", "plumb_bob", [*RADTAN, 0.01]))
    with pytest.raises(ConfigError, match="'distortion_model' 'rational_polynomial' is not supported"):
        read_camera_info(camera_info(tmp_path / "rp.yaml", "rational_polynomial", [0.0] * 8))
    with pytest.raises(ConfigError, match="'distortion_coefficients' must hold 4 numbers, got 5"):
        read_camera_info(camera_info(tmp_path / "eq.yaml", "equidistant", [*EQUI, 0.0]))
    info = yaml.safe_load(camera_info(tmp_path / "skew.yaml", "plumb_bob", RADTAN).read_text())
    info["camera_matrix"]["data"][1] = 0.5
    with pytest.raises(ConfigError, match=r"'camera_matrix' must be .*no skew"):
        read_camera_info(dump(tmp_path / "skew.yaml", info))
    del info["camera_matrix"]
    with pytest.raises(ConfigError, match="missing key 'camera_matrix'"):
        read_camera_info(dump(tmp_path / "skew.yaml", info))
    with pytest.raises(ConfigError, match="does not exist"):
        read_camera_info(tmp_path / "nothing.yaml")
    (tmp_path / "bad.yaml").write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: Kalibr camchain is not valid YAML"):
        read_kalibr_camchain(tmp_path / "bad.yaml")


def test_writer_refuses_what_vins_fusion_cannot_run(tmp_path):
    cam = PinholeCamera(width=640, height=480, fx=400.0, fy=400.0, cx=320.0, cy=240.0)
    mono = CameraCalibration(cam, "/cam0/image_raw", np.eye(4))
    with pytest.raises(ConfigError, match="one camera without an IMU"):
        render_vins_config(Calibration((mono,)))
    with pytest.raises(ConfigError, match="cam1 has no extrinsics"):
        render_vins_config(Calibration((mono, CameraCalibration(cam, "/cam1/image_raw"))))
    with pytest.raises(ConfigError, match="imu_topic is empty"):
        render_vins_config(Calibration((mono,), ImuCalibration(0.1, 0.01, 0.001, 0.0001)))
    imu = ImuCalibration(0.1, 0.01, 0.001, 0.0001, "/imu0")
    no_prior = Calibration((CameraCalibration(cam, "/cam0/image_raw"),), imu, estimate_extrinsic=2)
    path = write_vins_config(tmp_path, no_prior)[0]
    assert load_vins_config(path).body_T_cam[0].tolist() == np.eye(4).tolist()
    with pytest.raises(ConfigError, match=r"vins_config\.yaml exists"):
        write_vins_config(tmp_path, no_prior)
    write_vins_config(tmp_path, Calibration((mono,), imu.scaled(10.0), settings={"max_cnt": 200}),
                      overwrite=True)
    written = read_opencv_yaml(path)
    assert written["max_cnt"] == 200 and written["acc_n"] == 1.0 and written["estimate_extrinsic"] == 0
