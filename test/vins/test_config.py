"""VINS-Fusion / VINS-Mono config reading, tracker overrides, and errors that name the file and the key."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.core.camera import PinholeCamera, load_camera
from nsflow_ros.errors import NSFlowError
from nsflow_ros.vins import (
    DEFAULT_FREQ,
    OVERRIDABLE_KEYS,
    ConfigError,
    VinsConfig,
    apply_overrides,
    load_vins_config,
)

EUROC = Path(__file__).resolve().parents[2] / "config" / "euroc"
STEREO = EUROC / "euroc_stereo_imu_config.yaml"
MONO = EUROC / "euroc_mono_imu_config.yaml"

# EuRoC T_BS (sensor -> body) of cam0 and cam1.
T_BS_CAM0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
T_BS_CAM1 = np.array(
    [
        [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
        [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
        [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

# Modelled on VINS-Mono's config/euroc/euroc_config.yaml: intrinsics inline, extrinsics as R and t.
VINS_MONO_EUROC = """%YAML:1.0

#common parameters
imu_topic: "/imu0"
image_topic: "/cam0/image_raw"
output_path: "/tmp/vins_mono_output/"

#camera calibration
model_type: PINHOLE
camera_name: camera
image_width: 752
image_height: 480
distortion_parameters:
   k1: -2.917e-01
   k2: 8.228e-02
   p1: 5.333e-05
   p2: -1.578e-04
projection_parameters:
   fx: 4.616e+02
   fy: 4.603e+02
   cx: 3.630e+02
   cy: 2.481e+02

# camera-to-IMU extrinsics: 0 trusted, 1 refined, 2 unknown
estimate_extrinsic: 0
extrinsicRotation: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [0.0148655429818, -0.999880929698, 0.00414029679422,
           0.999557249008, 0.0149672133247, 0.025715529948,
           -0.0257744366974, 0.00375618835797, 0.999660727178]
extrinsicTranslation: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [-0.0216401454975,-0.064676986768, 0.00981073058949]

#feature tracker parameters
max_cnt: 150
min_dist: 30
freq: 10
F_threshold: 1.0
show_track: 1
equalize: 1
fisheye: 0

#optimization parameters
max_solver_time: 0.04
max_num_iterations: 8
keyframe_parallax: 10.0

#imu parameters
acc_n: 0.08
gyr_n: 0.004
acc_w: 0.00004
gyr_w: 2.0e-6
g_norm: 9.81007

#loop closure parameters
loop_closure: 1
load_previous_pose_graph: 0
fast_relocalization: 0
pose_graph_save_path: "/tmp/vins_mono_output/pose_graph/"

#unsynchronization parameters
estimate_td: 0
td: 0.0

#rolling shutter parameters
rolling_shutter: 0
rolling_shutter_tr: 0

#visualization parameters
save_image: 1
visualize_imu_forward: 0
visualize_camera_size: 0.4
"""


@pytest.fixture
def euroc_copy(tmp_path: Path) -> Path:
    """A private copy of config/euroc to damage."""
    folder = tmp_path / "euroc"
    shutil.copytree(EUROC, folder)
    return folder


def edited(folder: Path, old: str, new: str, name: str = "euroc_stereo_imu_config.yaml") -> Path:
    path = folder / name
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))
    return path


# ------------------------------------------------------------------------------------------ shipped files


def test_shipped_stereo_config() -> None:
    config = load_vins_config(STEREO)
    assert isinstance(config, VinsConfig)
    assert config.path == STEREO and config.path.is_absolute()
    assert config.dialect == "fusion"
    assert (config.image0_topic, config.image1_topic, config.imu_topic) == (
        "/cam0/image_raw",
        "/cam1/image_raw",
        "/imu0",
    )
    assert config.use_imu and config.stereo and config.num_of_cam == 2
    assert config.image_topics == ("/cam0/image_raw", "/cam1/image_raw")
    assert (config.image_width, config.image_height) == (752, 480)
    assert config.tracker_settings() == {
        "max_cnt": 150,
        "min_dist": 30,
        "F_threshold": 1.0,
        "flow_back": True,
        "show_track": True,
        "freq": 10,
        "equalize": False,
    }
    assert not config.fisheye
    assert config.output_path == "/tmp/vins_output/"
    assert config.cameras == (
        load_camera(EUROC / "cam0_pinhole.yaml"),
        load_camera(EUROC / "cam1_pinhole.yaml"),
    )
    assert all(isinstance(c, PinholeCamera) for c in config.cameras)
    assert [c.name for c in config.cameras] == ["cam0", "cam1"]
    np.testing.assert_array_equal(config.body_T_cam[0], T_BS_CAM0)
    np.testing.assert_array_equal(config.body_T_cam[1], T_BS_CAM1)
    assert all(t.dtype == np.float64 and not t.flags.writeable for t in config.body_T_cam)


def test_tracker_fields_are_the_vins_keyed_tracker_settings_in_the_trackers_types() -> None:
    fields = load_vins_config(STEREO).tracker_fields()
    # show_track and freq have VINS keys but are the session's, not the tracker's
    assert fields == {
        "max_cnt": 150, "min_dist": 30.0, "F_threshold": 1.0, "flow_back": True, "equalize": False,
        "stereo": True,
    }
    assert isinstance(fields["min_dist"], float) and fields["flow_back"] is True
    assert load_vins_config(MONO).tracker_fields()["stereo"] is False


def test_shipped_mono_config() -> None:
    config = load_vins_config(MONO)
    assert config.dialect == "fusion" and config.num_of_cam == 1 and not config.stereo
    assert config.image_topics == ("/cam0/image_raw",)
    assert len(config.cameras) == 1 and len(config.body_T_cam) == 1
    assert config.cameras[0] == load_camera(EUROC / "cam0_pinhole.yaml")
    np.testing.assert_array_equal(config.body_T_cam[0], T_BS_CAM0)
    assert (config.max_cnt, config.min_dist, config.F_threshold, config.freq) == (150, 30, 1.0, 10)


def test_camera_files_are_relative_to_the_config(euroc_copy: Path, tmp_path: Path, monkeypatch) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    config = load_vins_config(euroc_copy / "euroc_stereo_imu_config.yaml")
    assert config.cameras[1].name == "cam1"


# ------------------------------------------------------------------------------------------------ VINS-Mono


def test_vins_mono_config(tmp_path: Path) -> None:
    path = tmp_path / "euroc_config.yaml"
    path.write_text(VINS_MONO_EUROC)
    config = load_vins_config(path)
    assert config.dialect == "mono"
    assert (config.image0_topic, config.image1_topic, config.imu_topic) == ("/cam0/image_raw", "", "/imu0")
    assert config.use_imu and config.num_of_cam == 1
    assert config.cameras == (
        PinholeCamera(
            fx=461.6,
            fy=460.3,
            cx=363.0,
            cy=248.1,
            k1=-0.2917,
            k2=0.08228,
            p1=5.333e-05,
            p2=-1.578e-04,
            width=752,
            height=480,
            name="camera",
        ),
    )
    np.testing.assert_array_equal(config.body_T_cam[0], T_BS_CAM0)
    assert config.tracker_settings() == {
        "max_cnt": 150,
        "min_dist": 30,
        "F_threshold": 1.0,
        "flow_back": False,  # VINS-Mono has no back-tracking
        "show_track": True,
        "freq": 10,
        "equalize": True,
    }
    assert not config.fisheye
    assert config.output_path == "/tmp/vins_mono_output/"


def test_vins_mono_freq_zero_and_unknown_extrinsics(tmp_path: Path) -> None:
    text = VINS_MONO_EUROC.replace("freq: 10", "freq: 0").replace(
        "estimate_extrinsic: 0", "estimate_extrinsic: 2"
    )
    start = text.index("extrinsicRotation")
    text = text[:start] + text[text.index("#feature tracker") :]  # no extrinsics at all
    path = tmp_path / "vins_mono.yaml"
    path.write_text(text)
    config = load_vins_config(path)
    assert config.freq == DEFAULT_FREQ == 100
    np.testing.assert_array_equal(config.body_T_cam[0], np.eye(4))


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("   fx: 4.616e+02\n", "", "projection_parameters/fx"),
        ('image_topic: "/cam0/image_raw"', "image_topic: 5", "image_topic"),
        ('imu_topic: "/imu0"\n', "", "imu_topic"),
        ("model_type: PINHOLE", "model_type: FOO", "model_type"),
        ("extrinsicTranslation", "extrinsicTranslationX", "extrinsicTranslation"),
        ("rows: 3\n   cols: 3", "rows: 1\n   cols: 9", "extrinsicRotation"),
        ("equalize: 1", "equalize: yes", "equalize"),
    ],
)
def test_vins_mono_errors_name_file_and_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    path = tmp_path / "vins_mono.yaml"
    assert old in VINS_MONO_EUROC
    path.write_text(VINS_MONO_EUROC.replace(old, new, 1))
    with pytest.raises(ConfigError, match=re.escape(f"'{key}'")) as info:
        load_vins_config(path)
    assert str(path) in str(info.value)


# ------------------------------------------------------------------------------------------------ overrides


def test_overrides() -> None:
    config = load_vins_config(STEREO)
    changed = apply_overrides(
        config,
        {
            "max_cnt": 200,
            "min_dist": 0,
            "F_threshold": 2,
            "flow_back": 0,
            "show_track": False,
            "equalize": True,
        },
    )
    assert changed.tracker_settings() == {
        "max_cnt": 200,
        "min_dist": 0,
        "F_threshold": 2.0,
        "flow_back": False,
        "show_track": False,
        "freq": 10,
        "equalize": True,
    }
    assert isinstance(changed.F_threshold, float)
    assert config.max_cnt == 150 and config.flow_back  # the original is untouched
    assert changed.cameras == config.cameras and changed.path == config.path
    assert apply_overrides(config, {"freq": 0}).freq == DEFAULT_FREQ
    assert apply_overrides(config, {"freq": 30}).freq == 30


def test_overrides_keep_sentinels() -> None:
    # ROS parameters say "from the VINS config" with -1 (-1.0 for F_threshold); None works too.
    config = load_vins_config(STEREO)
    keep = {key: -1 for key in OVERRIDABLE_KEYS} | {"F_threshold": -1.0, "max_cnt": None}
    assert apply_overrides(config, keep).tracker_settings() == config.tracker_settings()
    assert apply_overrides(config, {}) is config


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"max_features": 10}, "unknown tracker setting 'max_features'"),
        ({"image0_topic": "/x"}, "unknown tracker setting 'image0_topic'"),
        ({"max_cnt": 0}, "'max_cnt' must be >= 1"),
        ({"max_cnt": "150"}, "'max_cnt' must be an integer, got str '150'"),
        ({"max_cnt": 150.0}, "'max_cnt' must be an integer"),
        ({"max_cnt": True}, "'max_cnt' must be an integer"),
        ({"min_dist": -2}, "'min_dist' must be >= 0"),
        ({"freq": -5}, "'freq' must be >= 0"),
        ({"F_threshold": 0.0}, "'F_threshold' must be a finite number > 0"),
        ({"F_threshold": float("inf")}, "'F_threshold' must be a finite number > 0"),
        ({"F_threshold": "1.0"}, "'F_threshold' must be a number"),
        ({"flow_back": 2}, "'flow_back' must be true/false or 0/1"),
        ({"show_track": "yes"}, "'show_track' must be true/false or 0/1"),
    ],
)
def test_override_errors_name_the_key(overrides: dict, message: str) -> None:
    config = load_vins_config(STEREO)
    with pytest.raises(ConfigError, match=re.escape(message)):
        apply_overrides(config, overrides)


# ------------------------------------------------------------------------------------- VINS-Fusion errors


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('image0_topic: "/cam0/image_raw"\n', "", "missing required key 'image0_topic'"),
        ('image1_topic: "/cam1/image_raw"\n', "", "missing required key 'image1_topic'"),
        ('imu_topic: "/imu0"\n', "", "missing required key 'imu_topic'"),
        ("num_of_cam: 2 ", "num_of_cam: 3 ", "key 'num_of_cam' must be 1 or 2, got 3"),
        ("num_of_cam: 2 ", 'num_of_cam: "two" ', "key 'num_of_cam' must be an integer, got str 'two'"),
        ('cam0_calib: "cam0_pinhole.yaml" ', "", "missing required key 'cam0_calib'"),
        ("image_width: 752", "image_width: 0", "key 'image_width' must be >= 1, got 0"),
        ("image_height: 480\n", "", "missing required key 'image_height'"),
        ("max_cnt: 150 ", "max_cnt: 0 ", "key 'max_cnt' must be >= 1, got 0"),
        ("max_cnt: 150 ", "max_cnt: 1.5 ", "key 'max_cnt' must be an integer, got float 1.5"),
        ("min_dist: 30 ", "min_dist: -1 ", "key 'min_dist' must be >= 0"),
        ("F_threshold: 1.0", "F_threshold: fast", "key 'F_threshold' must be a number, got str 'fast"),
        ("F_threshold: 1.0", "F_threshold: 0", "key 'F_threshold' must be > 0"),
        ("freq: 10 ", "freq: -1 ", "key 'freq' must be >= 0"),
        ("flow_back: 1 ", "flow_back: [1] ", "key 'flow_back' must be an integer, got a sequence"),
        ("estimate_extrinsic: 0", "estimate_extrinsic: 3", "key 'estimate_extrinsic' must be 0, 1 or 2"),
        ('output_path: "/tmp/vins_output/"', "output_path: 3", "key 'output_path' must be a string"),
        (
            "body_T_cam0: !!opencv-matrix",
            "body_T_cam0_: !!opencv-matrix",
            "missing required key 'body_T_cam0'",
        ),
        (
            "body_T_cam1: !!opencv-matrix",
            "body_T_cam1_: !!opencv-matrix",
            "missing required key 'body_T_cam1'",
        ),
        (
            "   rows: 4\n   cols: 4",
            "   rows: 2\n   cols: 8",
            "key 'body_T_cam0' must be a 4x4 !!opencv-matrix",
        ),
        (" 0.0148655429818,", " 0.5,", "key 'body_T_cam0' is not a rigid transform"),
        (
            "0.0, 0.0, 0.0, 1.0 ]",
            "0.0, 0.0, 0.5, 1.0 ]",
            "key 'body_T_cam0' is not a rigid transform: last row",
        ),
        (
            'image0_topic: "/cam0/image_raw"',
            "image0_topic: 7",
            "key 'image0_topic' must be a string, got int 7",
        ),
    ],
)
def test_fusion_errors_name_file_and_key(euroc_copy: Path, old: str, new: str, message: str) -> None:
    path = edited(euroc_copy, old, new)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        load_vins_config(path)
    assert str(info.value).startswith(f"{path}: ")
    assert isinstance(info.value, NSFlowError)


def test_mono_camera_fusion_config_needs_no_cam1(euroc_copy: Path) -> None:
    # With num_of_cam 1 the cam1 keys are not needed (and a broken cam1 file is not read).
    path = edited(euroc_copy, 'cam1_calib: "cam1_pinhole.yaml"', 'cam1_calib: "nope.yaml"', MONO.name)
    path = edited(euroc_copy, 'image1_topic: "/cam1/image_raw"', "#", MONO.name)
    config = load_vins_config(path)
    assert config.image1_topic == "" and config.num_of_cam == 1


def test_imu_off_needs_no_imu_topic(euroc_copy: Path) -> None:
    path = edited(euroc_copy, "imu: 1 ", "imu: 0 ")
    path = edited(euroc_copy, 'imu_topic: "/imu0"\n', "")
    config = load_vins_config(path)
    assert not config.use_imu and config.imu_topic == ""


def test_unknown_extrinsics_start_from_identity(euroc_copy: Path) -> None:
    path = edited(euroc_copy, "estimate_extrinsic: 0", "estimate_extrinsic: 2")
    path = edited(euroc_copy, "body_T_cam0: !!opencv-matrix", "unused_T: !!opencv-matrix")
    config = load_vins_config(path)
    np.testing.assert_array_equal(config.body_T_cam[0], np.eye(4))
    np.testing.assert_array_equal(config.body_T_cam[1], T_BS_CAM1)  # VINS-Fusion still reads body_T_cam1


def test_missing_camera_file_names_its_path(euroc_copy: Path) -> None:
    (euroc_copy / "cam1_pinhole.yaml").unlink()
    path = euroc_copy / "euroc_stereo_imu_config.yaml"
    with pytest.raises(ConfigError) as info:
        load_vins_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: key 'cam1_calib'")
    assert f"{euroc_copy / 'cam1_pinhole.yaml'}, which does not exist" in message


def test_broken_camera_file_names_config_camera_file_and_key(euroc_copy: Path) -> None:
    camera = euroc_copy / "cam0_pinhole.yaml"
    camera.write_text(camera.read_text().replace("   fy: 457.296\n", ""))
    path = euroc_copy / "euroc_stereo_imu_config.yaml"
    with pytest.raises(ConfigError) as info:
        load_vins_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: key 'cam0_calib'")
    assert f"{camera}: missing key 'projection_parameters/fy'" in message


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR", "binary data"),
        (b"", "file is empty"),
        (b"image0_topic: /cam0\n", "first line must be '%YAML:1.0'"),
        (b"%YAML:1.0\nimage0_topic: [\n  - {\n", "cannot parse"),
        (b"%YAML:1.0\n", "not a VINS config"),
        (b"%YAML:1.0\nfoo: 1\nbar: baz\n", "not a VINS config"),
        (b"%YAML:1.0\n- 1\n", "top level must be a mapping"),
    ],
)
def test_unreadable_or_garbage_file(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "config.yaml"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        load_vins_config(path)
    assert str(path) in str(info.value)


def test_missing_config_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=re.escape(f"{path}: file does not exist")):
        load_vins_config(path)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_vins_config(tmp_path)


# ------------------------------------------------------------------------------------ ROS parameters file


def test_tracker_params_file() -> None:
    yaml = pytest.importorskip("yaml")
    params_path = EUROC.parent / "tracker_params.yaml"
    params = yaml.safe_load(params_path.read_text())["nsflow_tracker"]["ros__parameters"]
    assert set(params) >= {
        "config_file",
        "method",
        "model_path",
        *OVERRIDABLE_KEYS,
        "output_layout",
        "feature_topic",
        "use_imu_prediction",
        "num_threads",
        "fisheye_mask",
    }
    assert (EUROC.parents[1] / params["config_file"]).is_file()  # relative to the share directory
    assert params["method"] in ("nsflow", "classical")
    assert params["output_layout"] in ("", "fusion", "mono")
    assert params["feature_topic"] == "/feature_tracker/feature"
    # Every tracker setting defaults to "from the VINS config", and is typed so ROS declares the right type.
    config = load_vins_config(EUROC.parents[1] / params["config_file"])
    overrides = {key: params[key] for key in OVERRIDABLE_KEYS}
    assert apply_overrides(config, overrides).tracker_settings() == config.tracker_settings()
    assert isinstance(params["F_threshold"], float)
    assert all(type(params[key]) is int for key in OVERRIDABLE_KEYS if key != "F_threshold")


def test_no_ros_or_torch_import() -> None:
    import subprocess
    import sys

    code = (
        "import sys, nsflow_ros.vins, nsflow_ros.core.camera; "
        "bad = sorted(m for m in ('rclpy', 'torch') if m in sys.modules); "
        "sys.exit(f'imported {bad}' if bad else 0)"
    )
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr
