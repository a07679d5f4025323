"""``nsflow-config``: write a VINS-Fusion config folder from a Kalibr calibration or ROS camera_info files."""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from nsflow_ros.argtypes import finite_float, positive_float, program_name
from nsflow_ros.vins.calibration import (
    Calibration,
    CameraCalibration,
    parse_transform,
    read_camera_infos,
    read_kalibr_camchain,
    read_kalibr_imu,
    write_vins_config,
)
from nsflow_ros.vins.errors import ConfigError

__all__ = ["build_parser", "main"]

_NAME = "nsflow-config"


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser."""
    p = argparse.ArgumentParser(
        prog=program_name(_NAME),
        description="Write a VINS-Fusion config folder (the config YAML and one camodocal camera file per "
                    "camera, laid out as config/euroc/) from a Kalibr calibration or from ROS camera_info "
                    "files. The tracker node and the stock VINS-Fusion estimator both read it.",
        epilog="Transforms (--body-T-cam0/1) are 16 numbers of a row-major 4x4 camera-to-body (IMU) matrix, "
               "separated by commas or spaces, or a file holding them (text before a 'data:' key is "
               "skipped, so a VINS config's body_T_cam0 block or a EuRoC sensor.yaml's T_BS can be pasted "
               "as it is). Kalibr's T_cam_imu is the inverse of body_T_cam and is inverted for you.",
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--kalibr-camchain", metavar="FILE",
                        help="Kalibr camchain-imucam.yaml (or camchain.yaml with --body-T-cam0)")
    source.add_argument("--camera-info", nargs="+", metavar="FILE",
                        help="ROS camera_info YAML of cam0, then of cam1 for stereo (plumb_bob or "
                             "equidistant); needs --body-T-cam0 (and --body-T-cam1)")
    p.add_argument("--kalibr-imu", metavar="FILE",
                   help="Kalibr imu.yaml: noise densities and random walks, rostopic (without it: no IMU, "
                        "which VINS-Fusion allows for stereo only)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write (created when missing)")
    p.add_argument("--name", default="vins_config.yaml",
                   help="file name of the config in DIR (default: %(default)s)")
    p.add_argument("--body-T-cam0", metavar="T", help="cam0 -> body transform; replaces Kalibr's T_cam_imu")
    p.add_argument("--body-T-cam1", metavar="T", help="cam1 -> body transform; replaces Kalibr's T_cam_imu")
    p.add_argument("--num-of-cam", type=int, choices=(1, 2),
                   help="use cam0 only (1) or cam0 and cam1 (2) of the camchain (default: every camera)")
    p.add_argument("--image-topics", nargs="+", metavar="TOPIC",
                   help="image topic of cam0 (then cam1); default: Kalibr's rostopic, /cam<i>/image_raw "
                        "for camera_info")
    p.add_argument("--imu-topic", metavar="TOPIC", help="IMU topic (default: the IMU file's rostopic)")
    p.add_argument("--imu-noise-scale", type=positive_float, default=1.0, metavar="FACTOR",
                   help="multiply acc_n, gyr_n, acc_w, gyr_w by this: VINS configs often inflate the "
                        "calibrated values, e.g. by 10 (default: %(default)s)")
    p.add_argument("--estimate-extrinsic", type=int, choices=(0, 1, 2), default=0,
                   help="VINS's estimate_extrinsic: 0 trust, 1 refine, 2 no prior (default: %(default)s)")
    p.add_argument("--td", type=finite_float, metavar="SECONDS",
                   help="camera-IMU time offset in seconds (default: Kalibr's timeshift_cam_imu, else 0)")
    p.add_argument("--output-path", default="/tmp/vins_output/", metavar="DIR",
                   help="VINS-Fusion's output_path, where it writes vio.csv (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace config and camera files that exist")
    return p


def _calibration(opts: argparse.Namespace) -> Calibration:
    transforms: list[np.ndarray | None] = [
        None if text is None else parse_transform(text, f"--body-T-cam{i}")
        for i, text in enumerate((opts.body_T_cam0, opts.body_T_cam1))
    ]
    td = 0.0
    if opts.kalibr_camchain:
        cameras, td = read_kalibr_camchain(opts.kalibr_camchain, transforms, num_of_cam=opts.num_of_cam)
        topics = opts.image_topics or []
        cameras = tuple(
            CameraCalibration(c.camera, topics[i] if i < len(topics) else c.topic, c.body_T_cam)
            for i, c in enumerate(cameras)
        )
    else:
        if opts.num_of_cam is not None and opts.num_of_cam != len(opts.camera_info):
            count = len(opts.camera_info)
            raise ConfigError(f"--num-of-cam {opts.num_of_cam} but {count} camera_info file(s)")
        cameras = read_camera_infos(opts.camera_info, transforms, opts.image_topics or ())
        for i, cam in enumerate(cameras):
            if cam.body_T_cam is None and (i > 0 or opts.estimate_extrinsic != 2):
                raise ConfigError(f"camera_info has no extrinsics: give --body-T-cam{i}")
    imu = None
    if opts.kalibr_imu:
        imu = read_kalibr_imu(opts.kalibr_imu).scaled(opts.imu_noise_scale)
        if opts.imu_topic is not None:
            imu = dataclasses.replace(imu, topic=opts.imu_topic)
    elif opts.imu_topic is not None:
        raise ConfigError("--imu-topic needs --kalibr-imu (the IMU noise comes from it)")
    return Calibration(cameras, imu, td if opts.td is None else opts.td, opts.estimate_extrinsic)


def main(args: list[str] | None = None) -> int:
    """Run the command.

    Returns:
        0 on success, 1 on a known error (one line on stderr), 2 on bad arguments (argparse).
    """
    opts = build_parser().parse_args(args)
    try:
        calibration = _calibration(opts)
        files = write_vins_config(opts.out, calibration, name=opts.name, output_path=opts.output_path,
                                  overwrite=opts.overwrite)
    except ConfigError as err:
        print(f"{_NAME}: error: {err}", file=sys.stderr)
        return 1
    models = " + ".join(c.camera.model_type for c in calibration.cameras)
    imu = "IMU" if calibration.imu is not None else "no IMU"
    print(f"{files[0]}: {len(calibration.cameras)} camera(s) ({models}), {imu}")
    for path in files[1:]:
        print(f"  {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
