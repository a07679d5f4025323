"""The front-ends over many scenes and camera rates: per-feature errors, and the estimator's ATE when a build
is given (``nsflow-scenes``).

One sample sequence per (scene seed, camera rate) is rendered once (cached); per perturbation and method it is
tracked frame by frame into a feature bag exactly as ``nsflow-replay --features-bag`` does, and every frame
written is scored against the exact optical flow as it goes: camera 0's carried-over features (from where
the truth carries the previous published pixel) and the stereo matches. With a VINS-Fusion build
(:mod:`~nsflow_ros.evaluation.estimator`) each bag is played into the stock estimator ``runs`` times and its
trajectory scored (ATE RMSE, SE3 alignment); a cell's figure is the mean of its runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.argtypes import method_variant, method_variants, names, non_negative_float, program_name
from nsflow_ros.core.methods import BASELINE
from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.errors import NSFlowError
from nsflow_ros.evaluation.errors import EvaluationError

__all__ = ["CellResult", "FeatureErrors", "evaluate_cell", "main", "summary", "tables"]

DEFAULT_CONFIG = "config/euroc/euroc_stereo_imu_config.yaml"

DRAW_NOISE = 1.0
"""Gray levels of the extra sensor noise of a draw > 0: the samples' own (``image_noise``), so a draw's
images carry sqrt(2) times a sample's noise."""


class FeatureErrors:
    """Errors of a published feature stream against a sample's exact flow, frame by frame.

    Temporal: camera 0's features carried over from the previous published frame, measured from where the
    truth carries the previous pixel. Stereo: camera 1's matches against camera 0's pixel moved by the
    truth. Occluded or out-of-image truth is left out.
    """

    def __init__(self, sample: Any) -> None:
        self.sample = sample
        self._stamps = np.asarray(sample.stamps_ns, dtype=np.int64)
        self._prev: dict[int, np.ndarray] = {}
        self._prev_index: int | None = None
        self.temporal: list[np.ndarray] = []
        self.stereo: list[np.ndarray] = []
        self.features = 0
        self.frames = 0

    def __call__(self, frame: FrameFeatures) -> None:
        c0 = frame.cameras[0]
        self.frames += 1
        self.features += len(c0)
        # The frame's stamp is seconds as a float (a few hundred ns off): the nearest image stamp.
        gap = np.abs(self._stamps - int(frame.stamp * 1e9))
        i = int(np.argmin(gap))
        if gap[i] > 1_000_000:
            return
        if self._prev_index is not None and self._prev:
            rows = [k for k, j in enumerate(c0.ids) if int(j) in self._prev]
            if rows:
                prev = np.array([self._prev[int(c0.ids[k])] for k in rows])
                flow, visible = self.sample.flow(self._prev_index, i, prev)
                self.temporal.append(np.hypot(*(c0.pixels[rows] - prev - flow).T)[visible])
        if len(frame.cameras) > 1 and len(frame.cameras[1]):
            c1 = frame.cameras[1]
            idx = np.searchsorted(c0.ids, c1.ids)
            flow, visible = self.sample.flow(i, i, c0.pixels[idx], 0, 1)
            self.stereo.append(np.hypot(*(c1.pixels - c0.pixels[idx] - flow).T)[visible])
        self._prev = {int(j): p for j, p in zip(c0.ids, c0.pixels, strict=True)}
        self._prev_index = i

    def figures(self) -> dict[str, float]:
        """Median error and share above 1 px, temporal and stereo, and features per frame."""
        out: dict[str, float] = {"features_per_frame": self.features / max(self.frames, 1)}
        for key, parts in (("temporal", self.temporal), ("stereo", self.stereo)):
            e = np.concatenate(parts) if parts else np.zeros(0)
            out[f"{key}_median_px"] = float(np.median(e)) if e.size else float("nan")
            out[f"{key}_over_1px"] = float(np.mean(e > 1.0)) if e.size else float("nan")
            out[f"{key}_count"] = float(e.size)
        return out


@dataclass
class CellResult:
    """One (scene seed, camera rate, perturbation, method): its feature errors and estimator ATEs (m).

    With several sensor-noise draws (``nsflow-scenes --draws``) the errors are the draws' means and
    ``ate_runs`` holds every draw's runs; ``draw_ates`` is each draw's mean (inf: every run of it failed).
    """

    seed: int
    rate: float
    perturb: str
    method: str
    errors: dict[str, float]
    ate_runs: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    draw_ates: list[float] = field(default_factory=list)

    @property
    def ate(self) -> float:
        """Mean ATE RMSE over the runs (m), or over the draws' means with several draws (each draw weighs
        alike, whatever its runs); inf when every run failed or diverged, NaN without runs."""
        if len(self.draw_ates) > 1:
            finite = [a for a in self.draw_ates if np.isfinite(a)]
            if finite:
                return float(np.mean(finite))
            return float("inf") if any(np.isinf(a) for a in self.draw_ates) else float("nan")
        if not self.ate_runs and not self.failures:
            return float("nan")
        return float(np.mean(self.ate_runs)) if self.ate_runs else float("inf")


def evaluate_cell(
    sample: Any,
    out_dir: Path,
    method: str,
    perturb: str,
    *,
    config: Path,
    model: str | None = None,
    vins: Any = None,
    runs: int = 2,
    draws: int = 1,
    timeout_s: float = 300.0,
    progress: bool = False,
    resume: bool = False,
    solver_time: float | None = None,
    overrides: dict[str, Any] | None = None,
    bags_from: Path | None = None,
) -> CellResult:
    """Track one sample into a feature bag (as ``nsflow-replay --features-bag``), score it, and with a
    VINS-Fusion build run the estimator ``runs`` times on it; with ``draws`` > 1, the same on further
    realisations of the images' sensor noise, and the cell's figures are the draws' means.

    Args:
        sample: a :class:`~nsflow_ros.data.sample.SampleSequence` with an ASL folder.
        out_dir: this cell's folder (the bag, each estimator run's folder; draw k > 0 in ``draw<k>/``).
        method, perturb: the tracking method and the perturbation (seeded by the sample's seed).
        config: the VINS-Fusion config tracked with and given to the estimator.
        model: the learned methods' model (None: each method's shipped default).
        vins: a :class:`~nsflow_ros.evaluation.estimator.VinsBuild`, or None for no estimator.
        draws: sensor-noise realisations: draw 0 is the sample's images, draw k > 0 adds
            :class:`~nsflow_ros.data.perturb.ImageNoise` (1 gray level, seed k) after the perturbation.
        resume: keep each draw's stored result (its ``cell.json``) when a run before measured it.
        solver_time: the estimator's ``max_solver_time`` (s); None = the config's
            (:func:`~nsflow_ros.evaluation.estimator.estimator_config`).
        overrides: tracker settings of this cell's method (e.g. ``{"reverse_checks": True}``).
        bags_from: this cell's folder in an earlier run's output: each draw's feature bag and feature
            figures are taken from there instead of tracked again, and only the estimator runs (to score
            the same tracks with another estimator build).

    Raises:
        NSFlowError: a source, config or model that cannot be used; with ``bags_from``, a draw without its
            ``features.bag`` or ``cell.json`` there.
    """
    if draws < 1:
        raise EvaluationError(f"draws must be >= 1, got {draws}")
    parts = [_evaluate_draw(sample, _draw_dir(out_dir, d), method, perturb, d, config=config,
                            model=model, vins=vins, runs=runs, timeout_s=timeout_s, progress=progress,
                            resume=resume, solver_time=solver_time, overrides=overrides,
                            bags_from=_draw_dir(bags_from, d) if bags_from else None)
             for d in range(draws)]
    if draws == 1:
        return parts[0]
    keys = parts[0].errors.keys()
    errors = {k: float(np.sum([p.errors[k] for p in parts])) if k.endswith("_count")
              else float(np.mean([p.errors[k] for p in parts])) for k in keys}
    return CellResult(parts[0].seed, parts[0].rate, perturb, method, errors,
                      [a for p in parts for a in p.ate_runs], [f for p in parts for f in p.failures],
                      [p.ate for p in parts])


def _draw_dir(cell_dir: Path, draw: int) -> Path:
    """Where draw ``draw`` of a cell is stored: the cell's folder for draw 0, ``draw<k>/`` in it else."""
    return cell_dir / f"draw{draw}" if draw else cell_dir


def _evaluate_draw(sample: Any, out_dir: Path, method: str, perturb: str, draw: int, *, config: Path,
                   model: str | None, vins: Any, runs: int, timeout_s: float, progress: bool, resume: bool,
                   solver_time: float | None, overrides: dict[str, Any] | None,
                   bags_from: Path | None = None) -> CellResult:
    """One sensor-noise draw of :func:`evaluate_cell`, stored in ``out_dir/cell.json``."""
    from nsflow_ros.data.perturb import ImageNoise, perturb_records
    from nsflow_ros.data.replay import ReplayOptions, replay_records
    from nsflow_ros.vins.config import load_vins_config
    from nsflow_ros.vins.feature_bag import feature_bag_topics, write_feature_bag

    record = out_dir / "cell.json"
    if resume and record.is_file():
        return CellResult(**json.loads(record.read_text(encoding="utf-8")))
    seed = int(sample.params["seed"])
    out_dir.mkdir(parents=True, exist_ok=True)
    if bags_from is not None:
        bag, tracked = _stored_bag(bags_from)
        cell = CellResult(seed, float(sample.params["rate_hz"]), perturb, method, tracked.errors)
    else:
        cfg = load_vins_config(config)
        bag = out_dir / "features.bag"
        bag.unlink(missing_ok=True)  # a cell is re-measured whole
        errors = FeatureErrors(sample)
        records = replay_records(ReplayOptions(sample.root / "asl", topics=feature_bag_topics(cfg), rate=0.0,
                                               perturb=perturb, seed=seed))
        if draw:
            records = perturb_records(records, ImageNoise(DRAW_NOISE, seed=draw))
        fixed = {**({"model_path": model} if model else {}), **(overrides or {})}
        write_feature_bag(records, bag, cfg, method=method, overrides=fixed or None, progress=progress,
                          observe=errors)
        cell = CellResult(seed, float(sample.params["rate_hz"]), perturb, method, errors.figures())
    if vins is not None:
        from nsflow_ros.evaluation.estimator import run_vins, score_vio

        for r in range(runs):
            try:
                vio = run_vins(bag, config, vins, out_dir / f"run{r}", timeout_s=timeout_s,
                               solver_time=solver_time)
                cell.ate_runs.append(float(score_vio(vio, sample.root / "groundtruth.csv").stats.rmse))
            except NSFlowError as err:  # a diverged or dead estimator is a result of the cell, not the end
                cell.failures.append(str(err).splitlines()[0])
    record.write_text(json.dumps(asdict(cell), indent=2) + "\n", encoding="utf-8")
    return cell


def _stored_bag(folder: Path) -> tuple[Path, CellResult]:
    """The feature bag and the stored result of one draw that an earlier run tracked into ``folder``."""
    bag, record = folder / "features.bag", folder / "cell.json"
    for path in (bag, record):
        if not path.is_file():
            raise EvaluationError(f"--bags-from: {path} does not exist (was this cell measured there?)")
    try:
        return bag, CellResult(**json.loads(record.read_text(encoding="utf-8")))
    except (ValueError, TypeError) as err:
        raise EvaluationError(f"--bags-from: {record} is not a cell record: {err}") from err


def summary(cells: Sequence[CellResult], baseline: str = BASELINE) -> dict[str, dict[str, float]]:
    """Per method, its figures over ``baseline``'s in the same cells: ATE ratio (max, median; a failed
    baseline counts as a win, ratio 0), the share of cells at most 1.15x, and the median error ratios."""
    base = {(c.seed, c.rate, c.perturb): c for c in cells if c.method == baseline}
    out: dict[str, dict[str, float]] = {}
    for method in dict.fromkeys(c.method for c in cells if c.method != baseline):
        ate, temporal, stereo = [], [], []
        for c in cells:
            b = base.get((c.seed, c.rate, c.perturb))
            if c.method != method or b is None:
                continue
            if np.isfinite(b.ate) or np.isfinite(c.ate):
                ate.append(0.0 if not np.isfinite(b.ate) and np.isfinite(c.ate) else c.ate / b.ate)
            temporal.append(c.errors["temporal_median_px"] / b.errors["temporal_median_px"])
            stereo.append(c.errors["stereo_median_px"] / b.errors["stereo_median_px"])
        a = np.array([x for x in ate if not np.isnan(x)])
        out[method] = {
            "cells": float(len(temporal)),
            "ate_ratio_max": float(a.max()) if a.size else float("nan"),
            "ate_ratio_median": float(np.median(a)) if a.size else float("nan"),
            "ate_cells_within_1.15": float(np.mean(a <= 1.15)) if a.size else float("nan"),
            "temporal_median_ratio_max": float(np.max(temporal)) if temporal else float("nan"),
            "stereo_median_ratio_max": float(np.max(stereo)) if stereo else float("nan"),
        }
    return out


def _mm(v: float) -> str:
    return "-" if np.isnan(v) else ("failed" if not np.isfinite(v) else f"{v * 1e3:.1f}")


def _ate_text(c: CellResult) -> str:
    """The cell's mean ATE (mm), with its draws' range when it has several and its failed runs."""
    text = _mm(c.ate)
    if len(c.draw_ates) > 1:
        text += f" ({_mm(min(c.draw_ates))}-{_mm(max(c.draw_ates))})"
    return text + (f" ({len(c.failures)} failed)" if c.failures else "")


def tables(cells: Sequence[CellResult], baseline: str = BASELINE) -> list[dict[str, Any]]:
    """The cells as the tables the docs paste (:mod:`nsflow_ros.results`): a row per scene, rate and
    perturbation with the methods side by side (``baseline`` first, "a / b" in one column), then the
    summary against the baseline."""
    from nsflow_ros.results import table

    methods = list(dict.fromkeys([baseline, *(c.method for c in cells)]))
    methods = [m for m in methods if any(c.method == m for c in cells)]
    by_key: dict[tuple[int, float, str], dict[str, CellResult]] = {}
    for c in cells:
        by_key.setdefault((c.seed, c.rate, c.perturb), {})[c.method] = c
    names = " / ".join(methods)

    def joined(row: dict[str, CellResult], fmt: Any) -> str:
        return " / ".join(fmt(row[m]) if m in row else "-" for m in methods)

    rows = []
    for (seed, rate, perturb), row in by_key.items():
        base = row.get(baseline)
        ratios = [f"{row[m].ate / base.ate:.2f}" if base is not None and m in row and np.isfinite(base.ate)
                  and base.ate > 0 else "-" for m in methods if m != baseline]
        rows.append([
            str(seed), f"{rate:g}", perturb,
            joined(row, _ate_text),
            " / ".join(ratios),
            joined(row, lambda c: f"{c.errors['temporal_median_px']:.4f}"),
            joined(row, lambda c: f"{100 * c.errors['temporal_over_1px']:.2f}"),
            joined(row, lambda c: f"{c.errors['stereo_median_px']:.4f}"),
            joined(row, lambda c: f"{100 * c.errors['stereo_over_1px']:.2f}"),
        ])
    others = " / ".join(m for m in methods if m != baseline)
    columns = ["scene", "rate Hz", "perturbation", f"ATE mm ({names})", f"ATE / {baseline}'s ({others})",
               f"temporal median px ({names})", f"temporal % > 1 px ({names})", f"stereo median px ({names})",
               f"stereo % > 1 px ({names})"]
    per_cell = table(
        "Per scene, rate and perturbation", columns, rows,
        "ATE: RMSE after SE3 alignment, the mean of the estimator's runs (each run in cells.json), over the "
        "sensor-noise draws with several (their range in brackets); failed: the estimator died or diverged. "
        "Errors: every published feature against the exact flow (the draws' mean).")
    sums = [[m, f"{s['cells']:.0f}", f"{s['ate_ratio_max']:.2f}", f"{s['ate_ratio_median']:.2f}",
             f"{100 * s['ate_cells_within_1.15']:.0f} %", f"{s['temporal_median_ratio_max']:.2f}",
             f"{s['stereo_median_ratio_max']:.2f}"] for m, s in summary(cells, baseline).items()]
    against = table(f"Against `{baseline}` in the same cells", ["method", "cells", "ATE ratio, max",
                    "ATE ratio, median", "cells <= 1.15x", "temporal median ratio, max",
                    "stereo median ratio, max"], sums,
                    f"A cell where `{baseline}`'s estimator failed counts as a win (ratio 0).")
    return [per_cell, against]


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _seeds(text: str) -> list[int]:
    try:
        out: list[int] = []
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            out += list(range(int(lo), int(hi or lo) + 1))
        return out
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seeds like 1-8 or 1,2,5, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    p = argparse.ArgumentParser(
        prog=program_name("nsflow-scenes"),
        description="Track sample scenes at several camera rates with every method into feature bags (as "
        "nsflow-replay --features-bag), score each feature against the exact optical flow, and with "
        "--vins play each bag into a stock VINS-Fusion estimator and score its trajectory (ATE, SE3). "
        "Writes scenes.json / scenes.md (the tables) and cells.json (every cell's figures).",
    )
    p.add_argument("--seeds", type=_seeds, default=[1, 2], help="scene seeds, e.g. 1-8 (default 1,2)")
    p.add_argument("--rates", type=_floats, default=[20.0, 10.0, 20.0 / 3.0],
                   help="camera rates in Hz (default 20,10,6.67)")
    p.add_argument("--perturb", default="none", help="perturbations, comma-separated (default none)")
    p.add_argument("--methods", type=method_variants, default="nsflow,klt",
                   help="methods, comma-separated, each optionally with tracker settings after colons, e.g. "
                   "nsflow:reverse_checks=1 (default nsflow,klt)")
    p.add_argument("--model", default=None, help="the learned methods' model (default: each one's own)")
    p.add_argument("--duration", type=float, default=20.0, help="seconds per scene (default 20)")
    p.add_argument("--rest", type=non_negative_float, default=0.0,
                   help="seconds each flight holds its first pose before it flies, as EuRoC's do (default 0: "
                   "in flight from the first frame, which the estimator must then initialise at speed)")
    p.add_argument("--config", default=None, help=f"VINS-Fusion config (default {DEFAULT_CONFIG})")
    p.add_argument("--vins", default=None,
                   help="a VINS-Fusion catkin workspace (scripts/build_vins_fusion.sh): run the estimator")
    p.add_argument("--runs", type=int, default=2, help="estimator runs per bag (default 2)")
    p.add_argument("--draws", type=int, default=1,
                   help="sensor-noise realisations per cell (default 1: the sample's images): draw k > 0 "
                   f"adds {DRAW_NOISE:g} gray level of Gaussian noise seeded by k; a cell's figures are the "
                   "draws' means. The estimator's ATE moves more between draws than between front-ends: use "
                   "3 or more, with --runs 1 --solver-time 1")
    p.add_argument("--solver-time", type=float, default=None,
                   help="the estimator's max_solver_time in s (default the config's 0.04); e.g. 1 on a busy "
                   "machine: the solver then stops at its iteration limit and the runs agree")
    p.add_argument("--out", default="out/scenes", help="output folder (default out/scenes)")
    p.add_argument("--cache", default="data/scenes", help="where scenes are rendered (default data/scenes)")
    p.add_argument("--bags-from", default=None,
                   help="an earlier run's --out: take each cell's feature bags and feature figures from "
                   "there and only run the estimator (needs --vins; e.g. to score the same tracks with "
                   "another estimator build)")
    p.add_argument("--resume", action="store_true",
                   help="keep the cells a run before measured into --out (their cell.json)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def _cells(opts: argparse.Namespace, config: Path, vins: Any) -> Iterator[CellResult]:
    """Every cell of the command line's grid, scene by scene, printing a line for each."""
    from nsflow_ros.data.sample import make_sample_sequence

    levels = names(opts.perturb)
    methods = {m: method_variant(m) for m in opts.methods}
    for seed in opts.seeds:
        for rate in opts.rates:
            rest = f"-rest{opts.rest:g}s" if opts.rest else ""
            name = f"seed{seed}-{rate:g}hz-{opts.duration:g}s{rest}"
            sample = make_sample_sequence(Path(opts.cache) / name,
                                          seed=seed, duration=opts.duration, rate_hz=rate, stereo=True,
                                          formats=("asl",), progress=not opts.no_progress, rest=opts.rest)
            for level in levels:
                for label, (method, overrides) in methods.items():
                    folder = label.replace(":", "_").replace("=", "-")
                    cell_dir = Path(f"seed{seed}") / f"{rate:g}hz" / level / folder
                    stored = Path(opts.bags_from) / cell_dir if opts.bags_from else None
                    cell = evaluate_cell(sample, Path(opts.out) / cell_dir, method, level, config=config,
                                         model=opts.model, vins=vins, runs=opts.runs, draws=opts.draws,
                                         progress=not opts.no_progress, resume=opts.resume,
                                         solver_time=opts.solver_time, overrides=overrides, bags_from=stored)
                    cell.method = label
                    e = cell.errors
                    print(f"nsflow-scenes: seed {seed} {rate:g} Hz {level} {label}: ATE {_mm(cell.ate)} mm, "
                          f"median {e['temporal_median_px']:.4f} / {e['stereo_median_px']:.4f} px",
                          flush=True)
                    yield cell


def main(args: list[str] | None = None) -> int:
    """Entry point; 0 when every cell was measured, 1 on a known error."""
    from nsflow_ros.results import command_line, markdown, run_header, write_tables

    opts = build_parser().parse_args(args)
    try:
        from nsflow_ros.resources import STEREO_CONFIG, share_file

        if opts.runs < 1 or opts.draws < 1 or opts.duration <= 0:
            raise EvaluationError(f"--runs and --draws must be >= 1 and --duration > 0, got {opts.runs}, "
                                  f"{opts.draws}, {opts.duration}")
        config = Path(opts.config) if opts.config else Path(share_file(STEREO_CONFIG))
        if opts.bags_from and not opts.vins:
            raise EvaluationError("--bags-from only runs the estimator: give --vins too")
        vins = None
        if opts.vins:
            from nsflow_ros.evaluation.estimator import VinsBuild

            vins = VinsBuild.locate(opts.vins)
        out = Path(opts.out)
        cells = list(_cells(opts, config, vins))
        doc = {"header": run_header(command_line("nsflow-scenes", args)), "tables": tables(cells)}
        out.mkdir(parents=True, exist_ok=True)
        write_tables(doc, out / "scenes.json", out / "scenes.md")
        (out / "cells.json").write_text(json.dumps([asdict(c) for c in cells], indent=2) + "\n",
                                        encoding="utf-8")
    except NSFlowError as err:
        print(f"nsflow-scenes: {err}", file=sys.stderr)
        return 1
    print(markdown(doc), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
