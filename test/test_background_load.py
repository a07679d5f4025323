"""The synthetic background load: shares, and processes that really use the CPU they are asked for."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from nsflow_ros.background_load import LoadError, background_load, load_shares


def test_shares_split_whole_cores_first() -> None:
    assert load_shares(0) == []
    assert load_shares(0.7) == [0.7]
    assert load_shares(1.0) == [1.0]
    assert load_shares(1.5) == [1.0, 0.5]


@pytest.mark.parametrize("cores", [-0.1, float("nan"), float("inf"), 65])
def test_bad_load_is_refused_with_the_value(cores: float) -> None:
    with pytest.raises(LoadError, match="background load"):
        load_shares(cores)


def test_bad_period_is_refused() -> None:
    with pytest.raises(LoadError, match="period"), background_load(0.5, period=0):
        pass


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_load_uses_its_share_and_stops() -> None:
    with background_load(0.5) as procs:
        assert len(procs) == 1
        time.sleep(0.5)  # spawn start-up
        c0, t0 = _cpu_seconds(procs[0].pid), time.monotonic()
        time.sleep(1.5)
        share = (_cpu_seconds(procs[0].pid) - c0) / (time.monotonic() - t0)
    # 50 % asked; a busy 2-core machine may slow the spinner down, never speed it up past 100 %
    assert 0.25 < share < 0.8, share
    assert not procs[0].is_alive()


def test_bad_niceness_is_refused() -> None:
    with pytest.raises(LoadError, match="niceness must be 0-19, got 20"), background_load(0.5, nice=20):
        pass


def test_a_niced_load_runs_below_this_process() -> None:
    with background_load(0.3, nice=7) as procs:
        time.sleep(0.5)
        fields = Path(f"/proc/{procs[0].pid}/stat").read_text().rsplit(")", 1)[1].split()
        assert int(fields[16]) == os.nice(0) + 7  # field 19 of stat: the niceness
