"""nsflow-scenes: the feature scoring, the summary against klt, the table, and the command on a tiny scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from vins_fakes import fake_build

from nsflow_ros.core.tracker import CameraFeatures, FrameFeatures
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.scenes import CellResult, FeatureErrors, evaluate_cell, main, summary, tables
from nsflow_ros.resources import STEREO_CONFIG, share_file
from nsflow_ros.results import markdown


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> object:
    return make_sample_sequence(tmp_path_factory.mktemp("scene") / "s", seed=3, duration=0.5, rate_hz=20.0,
                                stereo=True, formats=("asl",), progress=False)


def _camera(cam: int, ids: list[int], pixels: np.ndarray) -> CameraFeatures:
    n = len(ids)
    z = np.zeros((n, 2))
    nan = np.full((n, 2), np.nan)
    return CameraFeatures(cam, np.asarray(ids, np.int64), pixels, z, z, np.ones(n, np.int64), nan)


def _frame(sample: object, i: int, left: np.ndarray, right: np.ndarray | None = None) -> FrameFeatures:
    ids = list(range(len(left)))
    cams = [_camera(0, ids, left)] + ([] if right is None else [_camera(1, ids, right)])
    return FrameFeatures(sample.stamps_ns[i] * 1e-9, tuple(cams), (752, 480))  # type: ignore[attr-defined]


def test_feature_errors_against_the_exact_flow(tiny: object) -> None:
    pts = np.array([[200.0, 150.0], [400.0, 250.0], [500.0, 300.0]])
    flow, visible = tiny.flow(0, 1, pts)  # type: ignore[attr-defined]
    assert visible.all()
    stereo, _ = tiny.flow(1, 1, pts + flow, 0, 1)  # type: ignore[attr-defined]
    errors = FeatureErrors(tiny)
    errors(_frame(tiny, 0, pts))
    moved = pts + flow + np.array([[0.0, 0.0], [0.1, 0.0], [2.0, 0.0]])  # errors 0, 0.1 and 2 px
    errors(_frame(tiny, 1, moved, pts + flow + stereo + 0.3))
    fig = errors.figures()
    assert fig["temporal_median_px"] == pytest.approx(0.1, abs=1e-6)
    assert fig["temporal_over_1px"] == pytest.approx(1 / 3)
    # the stereo error is measured from the published left pixel, so the left error carries into it
    assert fig["stereo_count"] == 3 and fig["features_per_frame"] == 3


def test_summary_ratios_and_a_failed_baseline() -> None:
    e = {"temporal_median_px": 0.04, "stereo_median_px": 0.06}
    cells = [
        CellResult(1, 20.0, "none", "klt", e, [0.010, 0.010]),
        CellResult(1, 20.0, "none", "nsflow", {**e, "temporal_median_px": 0.05}, [0.012, 0.012]),
        CellResult(2, 20.0, "none", "klt", e, [], ["vins_node died"]),
        CellResult(2, 20.0, "none", "nsflow", e, [0.020]),
    ]
    assert cells[2].ate == float("inf") and np.isnan(CellResult(1, 1.0, "none", "klt", e).ate)
    s = summary(cells)["nsflow"]
    assert s["ate_ratio_max"] == pytest.approx(1.2)  # the failed klt counts as a win: ratio 0
    assert s["ate_ratio_median"] == pytest.approx(0.6)
    assert s["ate_cells_within_1.15"] == pytest.approx(0.5)
    assert s["temporal_median_ratio_max"] == pytest.approx(1.25)
    full = {k: 0.0 for k in ("temporal_over_1px", "stereo_over_1px", "features_per_frame")}
    for c in cells:
        c.errors.update(full)
    header = {"date": "d", "machine": "m", "command": "nsflow-scenes", "versions": {}}
    table = markdown({"header": header, "tables": tables(cells)})
    assert "| 2 | 20 | none | failed (1 failed) / 20.0 | - | 0.0400 / 0.0400 |" in table
    assert "| 1 | 20 | none | 10.0 / 12.0 | 1.20 | 0.0400 / 0.0500 |" in table
    assert "| nsflow | 2 | 1.20 | 0.60 | 50 % | 1.25 | 1.00 |" in table


def test_a_cell_without_estimator(tiny: object, tmp_path: Path) -> None:
    cell = evaluate_cell(tiny, tmp_path / "cell", "klt", "none", config=Path(share_file(STEREO_CONFIG)))
    assert (tmp_path / "cell" / "features.bag").is_file()
    assert cell.ate_runs == [] and np.isnan(cell.ate)
    again = evaluate_cell(tiny, tmp_path / "cell", "klt", "none", config=Path(share_file(STEREO_CONFIG)),
                          resume=True)  # the stored cell.json, not a new measurement
    assert again == cell
    assert cell.errors["features_per_frame"] > 50
    assert 0 < cell.errors["temporal_median_px"] < 0.5 and 0 < cell.errors["stereo_median_px"] < 0.5


def test_draws_track_other_noise_realisations(tiny: object, tmp_path: Path) -> None:
    config = Path(share_file(STEREO_CONFIG))
    one = evaluate_cell(tiny, tmp_path / "cell", "klt", "none", config=config)
    three = evaluate_cell(tiny, tmp_path / "cell", "klt", "none", config=config, draws=3, resume=True)
    assert (tmp_path / "cell" / "draw2" / "features.bag").is_file()
    # draw 0 is the sample's own images, kept; the others see other noise, so other features
    assert (tmp_path / "cell" / "draw1" / "features.bag").read_bytes() != (
        tmp_path / "cell" / "features.bag").read_bytes()
    parts = [one] + [CellResult(**json.loads((tmp_path / "cell" / f"draw{d}" / "cell.json").read_text()))
                     for d in (1, 2)]
    assert three.errors["temporal_median_px"] == pytest.approx(
        np.mean([p.errors["temporal_median_px"] for p in parts]))
    assert three.errors["temporal_count"] == sum(p.errors["temporal_count"] for p in parts)
    assert len(three.draw_ates) == 3 and np.isnan(three.ate)  # no estimator: no ATE
    with pytest.raises(EvaluationError, match="draws"):
        evaluate_cell(tiny, tmp_path / "cell", "klt", "none", config=config, draws=0)


def test_bags_from_scores_the_stored_tracks_without_tracking_again(tiny: object, tmp_path: Path) -> None:
    config = Path(share_file(STEREO_CONFIG))
    first = evaluate_cell(tiny, tmp_path / "a" / "cell", "klt", "none", config=config, draws=2)
    vins = fake_build(tmp_path)  # plays the bag it is given; its trajectory does not match: a failure
    again = evaluate_cell(tiny, tmp_path / "b" / "cell", "klt", "none", config=config, draws=2, vins=vins,
                          runs=1, bags_from=tmp_path / "a" / "cell")
    assert again.errors == first.errors  # the stored figures, the same tracks
    assert not list((tmp_path / "b").rglob("features.bag"))
    for sub in ("", "draw1/"):
        played = json.loads((tmp_path / "b" / "cell" / sub / "run0" / "rosbag.json").read_text())
        assert str(tmp_path / "a" / "cell" / sub / "features.bag") in played
    assert len(again.failures) == 2
    with pytest.raises(EvaluationError, match=r"--bags-from: .*draw2.*features\.bag does not exist"):
        evaluate_cell(tiny, tmp_path / "c", "klt", "none", config=config, draws=3, vins=vins,
                      bags_from=tmp_path / "a" / "cell")


def test_draws_range_in_the_table() -> None:
    def cell(method: str, draws: list[float]) -> CellResult:
        errors = {"temporal_median_px": 0.05, "temporal_over_1px": 0.01, "stereo_median_px": 0.06,
                  "stereo_over_1px": 0.01}
        return CellResult(1, 10.0, "none", method, errors, draws, [], draws)

    weighed = CellResult(1, 10.0, "none", "x", {}, [0.01, 0.01, 0.04], [], [0.01, 0.04])
    assert weighed.ate == pytest.approx(0.025)  # each draw alike, whatever its runs
    assert CellResult(1, 10.0, "none", "x", {}, [], ["diverged"] * 2, [np.inf, np.inf]).ate == np.inf
    doc = tables([cell("klt", [0.016, 0.027]), cell("nsflow", [0.023, 0.014])])
    assert doc[0]["rows"][0][3] == "21.5 (16.0-27.0) / 18.5 (14.0-23.0)"
    assert doc[0]["rows"][0][4] == "0.86"


def test_command_writes_table_and_json(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rc = main(["--seeds", "4", "--rates", "20", "--duration", "0.3", "--methods", "klt", "--no-progress",
               "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")])
    assert rc == 0
    cells = json.loads((tmp_path / "out" / "cells.json").read_text())
    assert [c["method"] for c in cells] == ["klt"]
    doc = json.loads((tmp_path / "out" / "scenes.json").read_text())
    assert doc["header"]["command"].startswith("nsflow-scenes --seeds 4")
    assert markdown(doc) == (tmp_path / "out" / "scenes.md").read_text()
    assert "| 4 | 20 | none | - |" in capsys.readouterr().out
    # A flight at rest first is another scene, rendered beside the one in flight.
    assert main(["--seeds", "4", "--rates", "20", "--duration", "0.3", "--methods", "klt", "--no-progress",
                 "--rest", "0.2", "--out", str(tmp_path / "rest"), "--cache", str(tmp_path / "cache")]) == 0
    scenes = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert scenes == ["seed4-20hz-0.3s", "seed4-20hz-0.3s-rest0.2s"]


@pytest.mark.parametrize("argv, message", [
    (["--vins", "/nonexistent/ws"], "/nonexistent/ws"),
    (["--runs", "0"], "--runs"),
    (["--draws", "0"], "--draws"),
    (["--bags-from", "out/scenes"], "give --vins too"),
])
def test_known_errors_exit_1(argv: list[str], message: str, capsys: pytest.CaptureFixture) -> None:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("nsflow-scenes: ") and message in err


def test_bad_option_values_exit_2() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--seeds", "one"])
    assert exc.value.code == 2
