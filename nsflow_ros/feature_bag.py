"""Track a recorded sequence offline and write a VINS feature bag: the command-line side.

The bag's contents and the frame policy are :mod:`nsflow_ros.vins.feature_bag`'s; this module only reads
the source (:func:`nsflow_ros.data.replay.replay_records`: window, perturbation, remaps) for it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from nsflow_ros.data.replay import ReplayOptions, replay_records
from nsflow_ros.vins.feature_bag import FEATURE_TOPIC, FeatureBagSummary, bag_format, feature_bag_topics
from nsflow_ros.vins.feature_bag import write_feature_bag as write_records

__all__ = ["FEATURE_TOPIC", "bag_format", "write_feature_bag"]


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
        config: VINS config file; default: :data:`nsflow_ros.resources.DEFAULT_CONFIG`.
        method: tracker method, e.g. ``nsflow`` or ``klt``.
        fmt: ``ros1`` or ``ros2``; None = from the suffix of ``out``.
        overrides: further tracker settings.
        progress: show a progress bar.

    Returns:
        what was written.

    Raises:
        NSFlowError: as :func:`nsflow_ros.vins.feature_bag.write_feature_bag`.
    """
    from nsflow_ros.resources import DEFAULT_CONFIG, share_file
    from nsflow_ros.vins.config import load_vins_config

    cfg = load_vins_config(config or share_file(DEFAULT_CONFIG))
    records = replay_records(replace(opts, topics=feature_bag_topics(cfg)))
    return write_records(records, out, cfg, method=method, fmt=fmt, overrides=overrides, progress=progress)
