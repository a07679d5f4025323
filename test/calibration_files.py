"""Calibration files as Kalibr and ROS write them, made from the shipped EuRoC config (for the vins tests)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from nsflow_ros.core.opencv_yaml import read_opencv_yaml
from nsflow_ros.vins.config import load_vins_config

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "config" / "euroc" / "euroc_stereo_imu_config.yaml"

K = {"fu": 380.5, "fv": 381.25, "pu": 318.2, "pv": 241.7}
EQUI = [-0.012, 0.0035, -0.0021, 0.0004]
RADTAN = [-0.21, 0.045, 0.0007, -0.0003]


def dump(path: Path, data: dict) -> Path:
    """Write ``data`` as plain YAML, as Kalibr and ROS write it."""
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def shipped_camchain(tmp_path: Path) -> tuple[Path, Path]:
    """A Kalibr camchain and imu.yaml written from the shipped EuRoC config (what Kalibr would say)."""
    cfg = load_vins_config(SHIPPED)
    chain = {}
    for i, (cam, body_T_cam) in enumerate(zip(cfg.cameras, cfg.body_T_cam, strict=True)):
        chain[f"cam{i}"] = {
            "T_cam_imu": np.linalg.inv(body_T_cam).tolist(),
            "camera_model": "pinhole",
            "distortion_coeffs": [cam.k1, cam.k2, cam.p1, cam.p2],
            "distortion_model": "radtan",
            "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
            "resolution": [cam.width, cam.height],
            "rostopic": cfg.image_topics[i],
            "timeshift_cam_imu": 0.0,
        }
    raw = read_opencv_yaml(SHIPPED)
    imu = {"imu0": {"accelerometer_noise_density": raw["acc_n"], "accelerometer_random_walk": raw["acc_w"],
                    "gyroscope_noise_density": raw["gyr_n"], "gyroscope_random_walk": raw["gyr_w"],
                    "rostopic": cfg.imu_topic, "update_rate": 200.0}}
    return dump(tmp_path / "camchain-imucam.yaml", chain), dump(tmp_path / "imu.yaml", imu)


def camera_info(path: Path, model: str, coeffs: list[float], name: str = "narrow_stereo/left") -> Path:
    """A ROS camera_info YAML (camera_calibration_parsers' layout) with the intrinsics K."""
    return dump(path, {
        "image_width": 640, "image_height": 480, "camera_name": name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [K["fu"], 0.0, K["pu"], 0.0, K["fv"], K["pv"],
                                                          0.0, 0.0, 1.0]},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": len(coeffs), "data": coeffs},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [0.0] * 12},
    })
