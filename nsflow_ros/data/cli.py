"""``nsflow-make-sample``: make the built-in synthetic EuRoC-like sample sequence."""

from __future__ import annotations

import argparse
import sys
import time

from nsflow_ros.argtypes import names, non_negative_float, positive_float, program_name
from nsflow_ros.data.sample import FORMATS, make_sample_sequence
from nsflow_ros.errors import NSFlowError

__all__ = ["build_parser", "main"]


def _formats(text: str) -> tuple[str, ...]:
    items = tuple(names(text))
    bad = [f for f in items if f not in FORMATS]
    if bad or not items:
        raise argparse.ArgumentTypeError(
            f"expected a comma-separated subset of {','.join(FORMATS)}, got {text!r}")
    return items


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser."""
    p = argparse.ArgumentParser(
        prog=program_name("nsflow-make-sample"),
        description="Render a synthetic EuRoC-like stereo-inertial sequence (textured room, 752x480 "
                    "pinhole-radtan cameras, 200 Hz IMU) as an ASL folder, a ROS 2 bag (mcap) and a ROS 1 "
                    "bag, with ground truth. Reuses an identical sequence that already exists.",
    )
    p.add_argument("--out", default="data/sample", help="output folder (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed of scene, flight and noise (default: 0)")
    p.add_argument("--duration", type=positive_float, default=10.0,
                   help="seconds of images (default: %(default)s)")
    p.add_argument("--rate", type=positive_float, default=20.0,
                   help="camera rate in Hz (default: %(default)s)")
    p.add_argument("--rest", type=non_negative_float, default=0.0,
                   help="seconds the body holds its first pose before it flies, as EuRoC's flights start "
                        "(default: 0, in flight from the first frame)")
    p.add_argument("--mono", action="store_true", help="cam0 only (default: stereo)")
    p.add_argument("--formats", type=_formats, default=FORMATS,
                   help=f"comma-separated subset of {','.join(FORMATS)} (default: all)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing folder that is not a sample")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(args: list[str] | None = None) -> int:
    """Run the command.

    Returns:
        0 on success, 1 on a known error (message on stderr), 2 on bad arguments (argparse).
    """
    opts = build_parser().parse_args(args)
    t0 = time.perf_counter()
    try:
        seq = make_sample_sequence(
            opts.out, seed=opts.seed, duration=opts.duration, rate_hz=opts.rate, stereo=not opts.mono,
            formats=opts.formats, progress=False if opts.no_progress else None, overwrite=opts.overwrite,
            rest=opts.rest,
        )
    except NSFlowError as err:  # a DataError, or the eval extra missing (the textures are its photos)
        print(f"nsflow-make-sample: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # disk full, permissions changed while writing
        print(f"nsflow-make-sample: error: cannot write {err.filename or opts.out}: {err.strerror}",
              file=sys.stderr)
        return 1
    print(f"{seq.root}: {len(seq)} frames x {len(seq.cameras)} camera(s), formats {', '.join(seq.formats)} "
          f"({time.perf_counter() - t0:.1f} s)")
    for fmt in seq.formats:
        print(f"  {fmt:5s} {seq.path(fmt)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
