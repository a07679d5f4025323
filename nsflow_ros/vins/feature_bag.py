"""A VINS feature bag from a recorded stream: ``/feature_tracker/feature`` (VINS-Fusion layout) plus the IMU.

``rosbag play`` or ``ros2 bag play`` then feeds a stock VINS-Fusion estimator without a live front-end.
Frames go through the node's frame policy and stereo pairing but none is dropped for speed, so the result
depends only on the data, the config, the settings, the method and the perturbation seed. With a
``publish_rate`` every frame is tracked and only the frames the rate lets through are written, as the node
publishes them.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nsflow_ros import threads as process_threads
from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.records import ImageRecord, ImuRecord, Record
from nsflow_ros.data.writers import BagWriter, temp_sibling
from nsflow_ros.errors import NSFlowError
from nsflow_ros.vins.config import VinsConfig
from nsflow_ros.vins.health import HealthMonitor, HealthReport, State, usable_share
from nsflow_ros.vins.messages import encode_fusion
from nsflow_ros.vins.pairing import StereoPairer
from nsflow_ros.vins.session import FrontEndSession, Skip
from nsflow_ros.vins.settings import setting

__all__ = [
    "FEATURE_TOPIC",
    "BagFormat",
    "FeatureBagSummary",
    "bag_format",
    "feature_bag_topics",
    "write_feature_bag",
]

FEATURE_TOPIC = "/feature_tracker/feature"
"""The topic the VINS-Fusion estimator subscribes to for features."""

BagFormat = Literal["ros1", "ros2"]


@dataclass(frozen=True)
class FeatureBagSummary:
    """What :func:`write_feature_bag` wrote.

    Attributes:
        frames: feature messages written.
        unpaired: stereo images dropped because the other camera had no image within the tolerance.
        tracked: frames tracked (more than ``frames`` with a ``publish_rate``).
        health: the run's tracking state (:class:`~nsflow_ros.vins.health.HealthMonitor`), None if unjudged.
    """

    path: Path
    format: BagFormat
    frames: int
    features: int
    imu: int
    unpaired: int = 0
    tracked: int = 0
    health: HealthReport | None = None

    def text(self) -> str:
        """One line for the command line."""
        per = self.features / max(self.frames, 1)
        extra = f", {self.unpaired} stereo image(s) without a partner skipped" if self.unpaired else ""
        if self.tracked > self.frames:
            extra += f"; {self.tracked} frames tracked, {self.frames} published (publish_rate)"
        if self.health is not None and self.health.state is not State.OK:  # what the estimator will get
            extra += f"; tracking {self.health.text}"
        return (f"wrote {self.path} ({self.format}): {self.frames} feature messages on {FEATURE_TOPIC} "
                f"({per:.1f} features/frame), {self.imu} IMU messages{extra}")


def bag_format(path: str | Path, requested: str | None = None) -> BagFormat:
    """``requested``, else ROS 1 for a ``.bag`` path and ROS 2 otherwise.

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


def feature_bag_topics(config: VinsConfig) -> list[str]:
    """The topics a feature bag reads: the config's cameras, then its IMU when it uses one."""
    return list(config.image_topics) + ([config.imu_topic] if config.use_imu and config.imu_topic else [])


def write_feature_bag(
    records: Iterable[Record],
    out: str | Path,
    config: VinsConfig,
    *,
    method: str = "nsflow",
    fmt: str | None = None,
    overrides: dict[str, Any] | None = None,
    settings: dict[str, Any] | None = None,
    masks: tuple[np.ndarray | None, ...] | None = None,
    progress: bool = True,
    opencv_threads: int | None = None,
    observe: Callable[[FrameFeatures], None] | None = None,
) -> FeatureBagSummary:
    """Track every image of a stream and write the features and IMU as a new bag.

    The bag is built under a hidden name beside ``out`` and renamed when complete.

    Args:
        records: the stream in time order (see :func:`feature_bag_topics`).
        out: the bag to create: a ``.bag`` file for ROS 1, a folder for ROS 2 (mcap).
        fmt: ``ros1`` or ``ros2``; None = from the suffix of ``out``.
        overrides: further TrackerSettings fields, fixed for the run (e.g. ``downsample``).
        settings: front-end settings of the session (the node's parameters, e.g. ``publish_rate``).
        masks: static masks per camera (:func:`~nsflow_ros.vins.tracker.load_static_masks`); None = the
            config's mask0 / mask1 keys, if any.
        opencv_threads: OpenCV's threads while tracking; None = the node's ``opencv_threads`` default.
        observe: called with every frame written, e.g. to score what the estimator will get.

    Raises:
        NSFlowError: an existing output, a bad source, config or model, or a frame the tracker refuses.
            When the source is damaged part-way, the bag with the frames before the damage is written first.
    """
    from nsflow_ros.progress import progress_bar

    path = Path(out)
    kind = bag_format(path, fmt)
    if path.exists():
        raise DataError(f"bag {path} exists already; not overwriting")
    session = FrontEndSession(config, {"method": method, **(settings or {})}, layout="fusion", masks=masks,
                              tracker_overrides=overrides)
    cams = list(config.image_topics)
    pairer: StereoPairer[ImageRecord] = StereoPairer(len(cams))

    tmp = temp_sibling(path)
    try:
        tmp.mkdir(parents=True)
    except OSError as err:
        raise DataError(f"cannot create {path}: {err.strerror}") from None
    frames = features = imu = 0
    health = HealthMonitor()  # the node's default thresholds: the bag is judged as the node judges
    error: NSFlowError | None = None
    bar = progress_bar(desc=f"feature bag {method}", unit="frame", enabled=progress)
    try:
        cv = int(setting("opencv_threads").default) if opencv_threads is None else opencv_threads
        with BagWriter(tmp / path.name, ros1=kind == "ros1") as bag, process_threads.opencv_threads(cv):
            try:
                for rec in records:
                    if isinstance(rec, ImuRecord):
                        bag.write_record(rec)
                        imu += 1
                        continue
                    if not isinstance(rec, ImageRecord) or rec.topic not in cams:
                        continue
                    pair = pairer.add(cams.index(rec.topic), rec.stamp_ns, rec)
                    if pair is None:
                        continue
                    left, right = pair
                    image0 = left.for_tracker()
                    outcome = session.process(left.stamp_ns * 1e-9, image0,
                                              None if right is None else right.for_tracker())
                    if outcome.skipped is Skip.TRACKER:
                        raise NSFlowError(f"frame at {left.stamp_ns} ns: {outcome.note}")
                    if outcome.features is None:
                        continue
                    if observe is not None:
                        observe(outcome.features)
                    cloud = encode_fusion(outcome.features)
                    bag.write_point_cloud(FEATURE_TOPIC, left.stamp_ns, cloud.points, cloud.channels,
                                          cloud.names, frame_id=left.frame_id or "world")
                    frames += 1
                    features += len(cloud)
                    health.add_frame(outcome.features.cameras[0].ids, image=image0,
                                     usable=usable_share(session.tracker.mask))
                    bar.update(1)
            except NSFlowError as err:
                error = err  # keep what was tracked; report after the bag is complete
        pairer.flush()
        try:
            (tmp / path.name).rename(path)
        except OSError as err:
            raise DataError(f"cannot write {path}: {err.strerror}") from None
    finally:
        bar.close()
        shutil.rmtree(tmp, ignore_errors=True)
    if error is not None:
        raise NSFlowError(f"{error} (the {frames} frames before it were tracked and written to {path})")
    report = health.run_report(max_cnt=session.tracker.settings.max_cnt, gated=session.counters.gated)
    return FeatureBagSummary(path, kind, frames, features, imu, pairer.unpaired, session.counters.tracked,
                             report)
