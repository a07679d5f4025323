"""``nsflow-replay --offline`` and ``--features-bag``: the recorded stream tracked in this process.

:func:`run_tracked` is the part of :func:`nsflow_ros.ros.replay_node.main` that tracks: the camera topics
and the static masks checked as the node checks them (a warning for little usable image, one error line
for none), then the feature bag or the offline outputs written, and exit code 1 with one line naming the
likely cause when no feature was tracked at all.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from nsflow_ros.argtypes import program_name
from nsflow_ros.data.replay import ReplayOptions
from nsflow_ros.errors import NSFlowError

__all__ = ["run_tracked"]


def run_tracked(opts: argparse.Namespace, ropts: ReplayOptions, prog: str) -> int:
    """Track the stream of ``ropts`` into ``--features-bag`` or ``--offline`` as ``opts`` say.

    Returns:
        0, or 1 when no feature was tracked at all (the outputs are written all the same).

    Raises:
        NSFlowError: a bad source, config, model or mask, or an output that cannot be written.
    """
    from nsflow_ros.allocator import keep_large_buffers
    from nsflow_ros.data.sources import SensorSource
    from nsflow_ros.resources import DEFAULT_CONFIG, share_file
    from nsflow_ros.vins.config import load_vins_config

    cfg = load_vins_config(opts.config or share_file(DEFAULT_CONFIG))
    _check_tracked_topics(opts, cfg)
    # a file that is no bag at all fails here, before an output exists
    next(iter(SensorSource(opts.path, topics=opts.topics).raw_messages()), None)
    keep_large_buffers()  # the tracker runs in this process
    overrides = {"providers": opts.providers, "model_path": opts.model or None, "downsample": opts.downsample}
    if opts.features_bag is not None:
        from dataclasses import replace

        from nsflow_ros.data.replay import replay_records
        from nsflow_ros.vins.feature_bag import feature_bag_topics, write_feature_bag

        asked = {"publish_rate": opts.publish_rate, "max_sigma": opts.max_sigma}
        bag = write_feature_bag(
            replay_records(replace(ropts, topics=feature_bag_topics(cfg))),
            opts.features_bag,
            cfg,
            method=opts.method,
            fmt=opts.features_bag_format,
            overrides=overrides,
            settings={k: v for k, v in asked.items() if v is not None} or None,
            masks=_static_masks(opts, cfg),
            progress=not opts.no_progress,
        )
        print(bag.text())
        features, frames, cause = bag.features, bag.frames, bag.health.cause if bag.health is not None else ""
    else:  # --offline
        from nsflow_ros.vins.offline import run_offline

        masks = _static_masks(opts, cfg)
        try:
            opts.offline.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise NSFlowError(f"cannot create output folder {opts.offline}: {err.strerror}") from None
        summary = run_offline(ropts, opts.offline, config=opts.config, method=opts.method,
                              overrides=overrides, masks=masks, progress=not opts.no_progress)
        print(summary.text())
        features, frames = summary.figures["features_per_frame"], summary.figures["frames"]
        cause = summary.tracking_cause
    if not features:  # outputs the estimator can do nothing with are a failure
        print(f"{prog}: no feature was tracked in {frames} frames" + (f": {cause}" if cause else ""),
              file=sys.stderr)
        return 1
    return 0


def _check_tracked_topics(opts: argparse.Namespace, cfg: Any) -> None:
    """--topics with --offline / --features-bag: they must hold the config's camera topics."""
    if opts.topics is None:
        return
    cams = list(cfg.image_topics) if opts.features_bag is not None else [cfg.image0_topic]
    missing = [t for t in cams if t not in opts.topics]
    if missing:
        raise NSFlowError(
            f"--topics {' '.join(opts.topics)} leaves out the camera topic(s) {', '.join(missing)} that "
            f"the config {cfg.path} tracks"
        )


def _static_masks(opts: argparse.Namespace, cfg: Any) -> tuple[Any, Any]:
    """The static masks of --mask0 / --mask1 (else the config's keys) in --mask-convention, checked as the
    node checks them: a warning for little usable image, an error (ConfigError) for none."""
    from nsflow_ros.vins.health import check_static_masks
    from nsflow_ros.vins.settings import setting
    from nsflow_ros.vins.tracker import load_static_masks

    masks = load_static_masks(cfg, opts.mask0, opts.mask1, opts.mask_convention)
    given = (opts.mask0, opts.mask1)
    names = [f"mask{i} {path or getattr(cfg, f'mask{i}')}" for i, path in enumerate(given)]
    least = float(setting("mask_min_usable").default)  # the node's default: the tools have no option
    for warning in check_static_masks(dict(zip(names, masks, strict=True)), least):
        print(f"{program_name('nsflow-replay')}: warning: {warning}", file=sys.stderr)
    return masks
