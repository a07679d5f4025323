"""A synthetic CPU load beside the tracker, standing in for the VINS estimator on the same cores.

The load is spread over whole-core processes (1.5 cores: one busy all the time, one half of it), each
spinning for its share of every short period and sleeping the rest, so that it arrives in bursts as an
estimator's per-frame work does. Every process ends by itself when its parent goes away or after
``max_seconds``, so a crashed benchmark leaves nothing spinning.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager

from nsflow_ros.errors import NSFlowError

__all__ = ["PERIOD_S", "LoadError", "background_load", "load_shares"]

PERIOD_S = 0.02
"""The load's period: one 20 Hz camera frame."""

_MAX_CORES = 64


class LoadError(NSFlowError):
    """A background load that cannot be made (a share out of range)."""


def load_shares(cores: float) -> list[float]:
    """Split ``cores`` into per-process busy shares in (0, 1]: whole cores first, the rest last.

    Raises:
        LoadError: ``cores`` negative, not finite or more than 64.
    """
    if not (math.isfinite(cores) and 0 <= cores <= _MAX_CORES):
        raise LoadError(f"background load must be between 0 and {_MAX_CORES} cores, got {cores}")
    whole = int(cores)
    shares = [1.0] * whole
    rest = round(cores - whole, 6)
    if rest > 0:
        shares.append(rest)
    return shares


def _spin(share: float, period: float, max_seconds: float, parent: int, nice: int) -> None:
    if nice:
        os.nice(nice)
    end = time.monotonic() + max_seconds
    busy = share * period
    nxt = time.monotonic()
    while time.monotonic() < end and os.getppid() == parent:
        start = time.monotonic()
        while time.monotonic() - start < busy:
            pass
        nxt += period
        pause = nxt - time.monotonic()
        if pause > 0:
            time.sleep(pause)
        else:  # fell behind (an overloaded machine): start the next period now
            nxt = time.monotonic()


@contextmanager
def background_load(
    cores: float, *, period: float = PERIOD_S, max_seconds: float = 3600.0, nice: int = 0
) -> Iterator[list[mp.Process]]:
    """Run a load of ``cores`` CPU cores in other processes while the ``with`` block runs.

    Args:
        cores: total load in cores (0 = none).
        period: seconds of one busy-then-idle cycle.
        max_seconds: each process stops by itself after this long.
        nice: the load's niceness increment (0-19): > 0 runs it at a lower priority than the tracker, as
            an estimator started with ``nice -n`` would.

    Yields:
        the load processes (empty for 0 cores).

    Raises:
        LoadError: ``cores`` out of range, ``period`` not positive or ``nice`` outside 0-19.
    """
    shares = load_shares(cores)
    if not period > 0:
        raise LoadError(f"load period must be > 0 s, got {period}")
    if not 0 <= nice <= 19:
        raise LoadError(f"load niceness must be 0-19, got {nice}")
    ctx = mp.get_context("spawn")  # no copy of the tracker's threads or onnxruntime sessions
    procs = [
        ctx.Process(
            target=_spin, args=(s, period, max_seconds, os.getpid(), nice), daemon=True, name=f"load{i}"
        )
        for i, s in enumerate(shares)
    ]
    for p in procs:
        p.start()
    try:
        yield procs
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.join(timeout=5)
