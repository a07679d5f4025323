"""``nsflow-config``: options, output, and one error line with exit 1 (2 for a bad option)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from calibration_files import SHIPPED, camera_info, shipped_camchain

from nsflow_ros.core.opencv_yaml import read_opencv_yaml
from nsflow_ros.vins.cli import main
from nsflow_ros.vins.config import load_vins_config


def _run(args: list[str], capsys) -> tuple[int, str, list[str]]:
    try:
        code = main(args)
    except SystemExit as exc:  # argparse
        code = exc.code
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return code, out.out, out.err.strip().splitlines()


def test_kalibr_to_a_config_folder(tmp_path, capsys):
    camchain, imu = shipped_camchain(tmp_path)
    out = tmp_path / "robot"
    code, text, err = _run(["--kalibr-camchain", str(camchain), "--kalibr-imu", str(imu), "--out", str(out)],
                           capsys)
    assert code == 0, err
    assert text.splitlines()[0] == f"{out / 'vins_config.yaml'}: 2 camera(s) (PINHOLE + PINHOLE), IMU"
    cfg, shipped = load_vins_config(out / "vins_config.yaml"), load_vins_config(SHIPPED)
    assert cfg.image_topics == shipped.image_topics and cfg.imu_topic == shipped.imu_topic
    # mono from the same chain, IMU noise inflated, topics renamed
    code, text, err = _run(["--kalibr-camchain", str(camchain), "--kalibr-imu", str(imu), "--out", str(out),
                            "--name", "mono.yaml", "--num-of-cam", "1", "--imu-noise-scale", "10",
                            "--image-topics", "/camera/infra1/image_rect_raw", "--imu-topic", "/camera/imu"],
                           capsys)
    assert code == 1 and err == [f"nsflow-config: error: {out / 'cam0_pinhole.yaml'} exists (overwrite to "
                                 "replace it)"]
    code, text, err = _run(["--kalibr-camchain", str(camchain), "--kalibr-imu", str(imu), "--out", str(out),
                            "--name", "mono.yaml", "--num-of-cam", "1", "--imu-noise-scale", "10",
                            "--image-topics", "/camera/infra1/image_rect_raw", "--imu-topic", "/camera/imu",
                            "--overwrite"], capsys)
    assert code == 0, err
    mono = load_vins_config(out / "mono.yaml")
    assert mono.num_of_cam == 1 and mono.image_topics == ("/camera/infra1/image_rect_raw",)
    assert mono.imu_topic == "/camera/imu"
    written, ref = read_opencv_yaml(out / "mono.yaml"), read_opencv_yaml(SHIPPED)
    assert written["acc_n"] == pytest.approx(10 * ref["acc_n"], rel=1e-15)


def test_camera_info_with_extrinsics_from_files_and_numbers(tmp_path, capsys):
    shipped = load_vins_config(SHIPPED)
    left = camera_info(tmp_path / "left.yaml", "plumb_bob", [-0.2, 0.04, 0.0, 0.0, 0.0])
    right = camera_info(tmp_path / "right.yaml", "plumb_bob", [-0.2, 0.04, 0.0, 0.0, 0.0])
    sensor = tmp_path / "cam0_sensor.yaml"
    sensor.write_text("T_BS:\n  cols: 4\n  rows: 4\n  data: " + str(shipped.body_T_cam[0].ravel().tolist()))
    numbers = ",".join(repr(float(v)) for v in shipped.body_T_cam[1].ravel())
    out = tmp_path / "out"
    code, _, err = _run(["--camera-info", str(left), str(right), "--body-T-cam0", str(sensor),
                        "--body-T-cam1", numbers, "--out", str(out)], capsys)
    assert code == 0, err
    cfg = load_vins_config(out / "vins_config.yaml")
    assert cfg.stereo and not cfg.use_imu and cfg.image_topics == ("/cam0/image_raw", "/cam1/image_raw")
    for mine, ref in zip(cfg.body_T_cam, shipped.body_T_cam, strict=True):
        np.testing.assert_array_equal(mine, ref)


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (lambda t, c, i: ["--camera-info", str(t / "left.yaml"), "--out", str(t / "o")], 1,
         "nsflow-config: error: camera_info has no extrinsics: give --body-T-cam0"),
        (lambda t, c, i: ["--camera-info", str(t / "left.yaml"), "--body-T-cam0", "1 2 3",
                          "--out", str(t / "o")], 1,
         "nsflow-config: error: --body-T-cam0: expected 16 finite numbers (a row-major 4x4), got 3"),
        (lambda t, c, i: ["--kalibr-camchain", str(c), "--out", str(t / "o"), "--num-of-cam", "1"], 1,
         "nsflow-config: error: one camera without an IMU: VINS-Fusion needs stereo or an IMU (give the IMU "
         "file)"),
        (lambda t, c, i: ["--kalibr-camchain", str(c), "--imu-topic", "/imu", "--out", str(t / "o")], 1,
         "nsflow-config: error: --imu-topic needs --kalibr-imu (the IMU noise comes from it)"),
        (lambda t, c, i: ["--kalibr-camchain", str(t / "nothing.yaml"), "--out", str(t / "o")], 1,
         "does not exist"),
        (lambda t, c, i: ["--kalibr-camchain", str(c), "--kalibr-imu", str(c), "--out", str(t / "o")], 1,
         "camchain-imucam.yaml: missing key 'accelerometer_noise_density'"),
        (lambda t, c, i: ["--kalibr-camchain", str(c), "--camera-info", str(i), "--out", str(t / "o")], 2,
         "argument --camera-info: not allowed with argument --kalibr-camchain"),
        (lambda t, c, i: ["--kalibr-camchain", str(c), "--num-of-cam", "3", "--out", str(t / "o")], 2,
         "argument --num-of-cam: invalid choice: 3"),
        (lambda t, c, i: ["--kalibr-camchain", str(c)], 2, "the following arguments are required: --out"),
    ],
    ids=["no extrinsics", "short transform", "mono without imu", "imu topic alone", "missing camchain",
         "imu file missing key", "two sources", "three cameras", "no out"],
)
def test_errors_are_one_line(tmp_path, capsys, args, code, message):
    camchain, imu = shipped_camchain(tmp_path)
    camera_info(tmp_path / "left.yaml", "plumb_bob", [-0.2, 0.04, 0.0, 0.0])
    got, _, err = _run(args(tmp_path, camchain, imu), capsys)
    assert got == code
    assert message in err[-1] and (code == 2 or len(err) == 1), err
    assert not (tmp_path / "o").exists()


def test_camchain_keys_broken_give_exit_1(tmp_path, capsys):
    camchain, imu = shipped_camchain(tmp_path)
    data = yaml.safe_load(Path(camchain).read_text())
    data["cam1"]["camera_model"] = "eucm"
    Path(camchain).write_text(yaml.safe_dump(data))
    code, _, err = _run(["--kalibr-camchain", str(camchain), "--kalibr-imu", str(imu), "--out",
                         str(tmp_path / "o")], capsys)
    assert code == 1 and len(err) == 1
    assert err[0].startswith(f"nsflow-config: error: {camchain}: key 'cam1/camera_model' eucm-radtan has no "
                             "camodocal model (supported: pinhole-radtan, pinhole-equidistant, omni-radtan)")
