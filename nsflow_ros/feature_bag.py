"""Track a recorded sequence offline and write a VINS feature bag: features plus IMU, no images.

The bag holds ``/feature_tracker/feature`` (sensor_msgs/PointCloud in the VINS-Fusion layout of
:func:`nsflow_ros.vins.messages.encode_fusion`: points (x, y, 1) undistorted, channels id, camera_id, u, v,
velocity_x, velocity_y, 0, 0, 0; header stamp = image stamp) and the IMU messages, so ``rosbag play`` (ROS 1)
or ``ros2 bag play`` feeds a stock VINS-Fusion estimator without running any front-end live. Every image is
tracked (no frame is dropped, whatever the machine's speed) and the result depends only on the data, the
config, the method and the perturbation seed.

The bag is built under a hidden name beside the output and renamed when complete; when the source is
damaged part-way, the frames before the damage are still written and the error is raised afterwards.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

from nsflow_ros.core.tracker import FeatureTracker
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.records import ImageRecord, ImuRecord
from nsflow_ros.data.replay import ReplayOptions, replay_records
from nsflow_ros.data.writers import BagWriter, temp_sibling
from nsflow_ros.errors import NSFlowError
from nsflow_ros.vins.messages import encode_fusion

__all__ = ["FEATURE_TOPIC", "BagFormat", "FeatureBagSummary", "bag_format", "write_feature_bag"]

FEATURE_TOPIC = "/feature_tracker/feature"
"""The topic the VINS-Fusion estimator subscribes to for features."""

BagFormat = Literal["ros1", "ros2"]


@dataclass(frozen=True)
class FeatureBagSummary:
    """What :func:`write_feature_bag` wrote.

    Attributes:
        path: the bag written.
        format: ``ros1`` or ``ros2``.
        frames: feature messages written (one per tracked image stamp).
        features: features written, summed over frames.
        imu: IMU messages written.
        unpaired: stereo images dropped because the other camera has no image of the same stamp.
    """

    path: Path
    format: BagFormat
    frames: int
    features: int
    imu: int
    unpaired: int = 0

    def text(self) -> str:
        """One line for the command line."""
        per = self.features / max(self.frames, 1)
        extra = f", {self.unpaired} stereo image(s) without a partner skipped" if self.unpaired else ""
        return (f"wrote {self.path} ({self.format}): {self.frames} feature messages on {FEATURE_TOPIC} "
                f"({per:.1f} features/frame), {self.imu} IMU messages{extra}")


def bag_format(path: str | Path, requested: str | None = None) -> BagFormat:
    """The format to write: ``requested`` if given, else ROS 1 for a ``.bag`` path and ROS 2 otherwise.

    Raises:
        DataError: for an unknown format, or ROS 1 asked for a path without ``.bag``.
    """
    suffix_ros1 = Path(path).suffix == ".bag"
    if requested is None:
        return "ros1" if suffix_ros1 else "ros2"
    if requested not in ("ros1", "ros2"):
        raise DataError(f"unknown bag format {requested!r}; expected ros1 or ros2")
    if requested == "ros1" and not suffix_ros1:
        raise DataError(f"a ROS 1 bag is a file ending in .bag; got {path}")
    return requested  # type: ignore[return-value]


def write_feature_bag(
    opts: ReplayOptions,
    out: str | Path,
    *,
    config: str | Path | None = None,
    method: str = "nsflow",
    fmt: str | None = None,
    overrides: dict[str, Any] | None = None,
    progress: bool = True,
) -> FeatureBagSummary:
    """Track every image of a bag or ASL folder and write the features and IMU as a new bag.

    Args:
        opts: what to read (path, window, perturbation and seed, remaps of the IMU topic); ``opts.topics``
            is replaced by the config's camera and IMU topics.
        out: the bag to create (must not exist): a ``.bag`` file for ROS 1, a folder for ROS 2 (mcap).
        config: VINS config (cameras, topics, max_cnt, min_dist, ...; stereo when ``num_of_cam: 2``);
            default: the shipped EuRoC mono config.
        method: tracker method, ``nsflow``, ``classical`` or ``klt``.
        fmt: ``ros1`` or ``ros2``; None = from the suffix of ``out``.
        overrides: further tracker settings.
        progress: show a progress bar.

    Returns:
        what was written.

    Raises:
        NSFlowError: an existing output, a bad source (DataError), config (ConfigError) or model
            (EncoderError). When the source is damaged part-way, the bag with the frames before the
            damage is written first.
    """
    from tqdm import tqdm

    from nsflow_ros.resources import share_file
    from nsflow_ros.vins.config import load_vins_config

    path = Path(out)
    kind = bag_format(path, fmt)
    if path.exists():
        raise DataError(f"bag {path} exists already; not overwriting")
    cfg = load_vins_config(config or share_file("config/euroc/euroc_mono_imu_config.yaml"))
    tracker = FeatureTracker.from_vins_config(cfg, {"method": method, **(overrides or {})})
    cams = list(cfg.image_topics)
    topics = cams + ([cfg.imu_topic] if cfg.use_imu and cfg.imu_topic else [])
    records = replay_records(replace(opts, topics=topics))

    tmp = temp_sibling(path)
    try:
        tmp.mkdir(parents=True)
    except OSError as err:
        raise DataError(f"cannot create {path}: {err.strerror}") from None
    frames = features = imu = unpaired = 0
    error: NSFlowError | None = None
    pending: dict[str, ImageRecord] = {}
    bar = tqdm(desc=f"feature bag {method}", unit="frame", disable=not progress)
    try:
        with BagWriter(tmp / path.name, ros1=kind == "ros1") as bag:
            try:
                for rec in records:
                    if isinstance(rec, ImuRecord):
                        bag.write_record(rec)
                        imu += 1
                        continue
                    if not isinstance(rec, ImageRecord):
                        continue
                    # Stereo: a camera's older image whose partner never came cannot be tracked.
                    unpaired += sum(1 for r in pending.values() if r.stamp_ns != rec.stamp_ns)
                    pending = {t: r for t, r in pending.items() if r.stamp_ns == rec.stamp_ns}
                    pending[rec.topic] = rec
                    if len(pending) < len(cams):
                        continue
                    left, right = pending[cams[0]], pending.get(cams[1]) if len(cams) > 1 else None
                    pending = {}
                    frame = tracker.process(left.stamp_ns * 1e-9, left.gray(),
                                            None if right is None else right.gray())
                    cloud = encode_fusion(frame)
                    bag.write_point_cloud(FEATURE_TOPIC, left.stamp_ns, cloud.points, cloud.channels,
                                          cloud.names, frame_id=left.frame_id or "world")
                    frames += 1
                    features += len(cloud)
                    bar.update(1)
            except NSFlowError as err:
                error = err  # keep what was tracked; report after the bag is complete
        unpaired += len(pending)
        try:
            (tmp / path.name).rename(path)
        except OSError as err:
            raise DataError(f"cannot write {path}: {err.strerror}") from None
    finally:
        bar.close()
        shutil.rmtree(tmp, ignore_errors=True)
    if error is not None:
        raise NSFlowError(f"{error} (the {frames} frames before it were tracked and written to {path})")
    return FeatureBagSummary(path, kind, frames, features, imu, unpaired)
