"""The card of a model ``nsflow-train --install`` installs: a Markdown file of its own beside the model.

The card goes to ``<models>/nsflow_encoder.md`` (:data:`CARD_NAME`), never to ``models/README.md``, the
hand-written card of every shipped model, so an install leaves the other models' documentation as it was.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from nsflow_ros.train.trainer import TrainConfig

__all__ = ["CARD_NAME", "write_model_card"]

CARD_NAME = "nsflow_encoder.md"
"""The installed model's card, beside ``nsflow_encoder.onnx``; the next install rewrites it."""


def write_model_card(
    path: str | os.PathLike[str],
    config: TrainConfig | None = None,
    *,
    parameters: int,
    flops: int,
    steps: int,
    seconds: float,
    tables: str,
    figures: dict[str, str],
    notes: str = "",
    data: list[dict[str, object]] | None = None,
    recipe: tuple[str, tuple[tuple[str, str], ...]] | None = None,
) -> Path:
    """Write the Markdown model card.

    Args:
        path: the card to write (:data:`CARD_NAME` in the models folder).
        config: the training run's settings (the encoder's shape, the command, the solver, the losses, the
            initial flow, the teacher as a path relative to the card where it lies beside it); None = the
            defaults.
        parameters: trainable parameter count.
        flops: FLOPs of one forward at 320x240.
        steps: training steps run.
        seconds: training wall time.
        tables: the held-out comparison, Markdown.
        figures: caption -> PNG path relative to the card.
        notes: extra Markdown (design measurements, caveats).
        data: the training data sources with their shares (``--data``; each a
            ``PairSource.describe()`` with ``share``); None = the bundled photos (and scene share).
        recipe: (name, what the source leaves open and the choice made) of a ``--recipe`` preset.
    """
    if config is None:
        from nsflow_ros.train.trainer import TrainConfig

        config = TrainConfig()
    spec, lm, levels = config.spec, config.lm, config.lm.levels
    coarse_weight, basin_weight, scene_share = config.coarse_weight, config.basin_weight, config.scene_share
    init = _init_text(config.pair.init_mode, config.pair.init_sigma)
    teacher = _teacher_text(config.teacher, Path(path).parent)
    head = {"sigmoid": "sigmoid (descriptors in (0, 1))", "relu": "ReLU", "none": "none (linear)"}[spec.head]
    w = spec.width
    c_in = "gray (1 channel)" if spec.in_channels == 1 else "RGB (3 channels)"
    if levels == 1:
        layer = "single-level LM"
    else:
        layer = f"{levels}-level coarse-to-fine LM through the descriptor pyramid (as the tracker solves)"
    coarse = (
        f" plus {coarse_weight:g} x the same penalty of each coarse level's error in that level's pixels"
        if levels > 1 and coarse_weight > 0
        else ""
    )
    if basin_weight > 0:
        coarse += (
            f"; plus {basin_weight:g} x the basin loss (landing error of the solver's first step from a start"
            f" up to {config.basin_radius:g} px away, per level; `nsflow_ros/train/basin.py`)"
        )
    scenes = (
        f" A share of {scene_share:.0%} of the pairs are instead crops of stereo (EuRoC baseline) and\n"
        "  temporal renders of the sample scenes (`nsflow_ros/train/scenes.py`, sequence seeds 1 and 2; the\n"
        "  evaluation's stereo pairs use seed 0), exact flow, same illumination changes."
        if scene_share > 0
        else ""
    )
    if teacher is None:
        origin = """trained end to end through this project's differentiable LM Lucas-Kanade layer
(`nsflow_ros.train`, implicit-function-theorem backward)"""
        method = f"""* Layer: {layer} (window {lm.window}, up to {lm.max_iterations} iterations per level, \
eps 1e-3), {config.mode.value} backward.
* Loss: mean {config.rho} penalty of the endpoint error (scale {config.huber_delta:g} px) over points that \
stay in the image{coarse};
  Adam, lr {config.lr:g}, one pair per step."""
    else:
        origin = f"""distilled from the wider encoder `{teacher}`, which was trained end to end through
this project's differentiable LM Lucas-Kanade layer (`nsflow_ros.train`)"""
        method = f"""* Distilled from `{teacher}` (`nsflow_ros/train/distill.py`): per step both frames of a
  pair are encoded by the teacher (onnxruntime, as deployed) and by this encoder; loss = mean squared
  difference of the descriptor maps plus that of their x and y forward differences (what the solver
  reads: residuals and Jacobians). No solver in the loop. Adam, lr {config.lr:g}, one pair per step."""
    data_md = ""
    if data:
        lines = "\n".join(f"  * {_source_text(s)}" for s in data)
        data_md = (
            "* Data sources and their shares of the training pairs (every pair with exact ground-truth\n"
            f"  flow and the same random illumination changes; GFTT corners on frame 1):\n{lines}\n"
        )
    if recipe is not None:
        name, open_items = recipe
        items = "\n".join(f"  * {q}: {a}" for q, a in open_items)
        data_md += f"* Recipe `{name}`; what its source leaves open, and the choice made:\n{items}\n"
    photo_note = " (the photo pairs)" if data else ""
    figs = "\n\n".join(f"![{cap}]({p})\n\n*{cap}*" for cap, p in figures.items())
    text = f"""# NSFlow encoder: `nsflow_encoder.onnx`

The learned descriptor CNN of NSFlow ("End-to-End Differentiable Neuro-Symbolic Optical Flow for Visual
Odometry"), {origin}. It replaces the shipped `d4` model (`--model d4`, the node's `model_path:=d4`,
the default of `nsflow_lk`); the tracker runs its descriptors through the same NumPy LM solver as the
classical (intensity) mode.

## Model

| | |
|---|---|
| architecture | 3x3 conv {spec.in_channels}->{w}, ReLU; 3x3 conv {w}->{w}, ReLU; \
1x1 conv {w}->{2 * w}, ReLU; 1x1 conv {2 * w}->{spec.d}; head {head} |
| padding | 1 px, replicated borders (same rule as the solver's Scharr derivatives and sampling) |
| normalisation | none (no BatchNorm, nothing to fold) |
| parameters | {parameters:,} |
| FLOPs at 320x240 | {flops / 1e9:.3f} G (2 per multiply-add, convolutions only) |
| input | `image`: (1, {spec.in_channels}, H, W) float32, {c_in}, pixel / 255 in [0, 1]; H, W dynamic |
| output | `descriptors`: (1, {spec.d}, H, W) float32 |
| ONNX | opset 17, metadata `name=nsflow-d{spec.d}`, `spec`, training command |

## Training

{data_md}* Data{photo_note}: pairs of views of real photos bundled with scikit-image /
  matplotlib, related by random homographies (exact ground-truth flow), with random illumination changes
  on each frame (gain, offset, local shading, gamma, noise; strength uniform in [0, 1]); GFTT corners on
  frame 1 (up to 200);
  initial flow = {init}. Held out (never trained on): coffee, chelsea,
  grace_hopper. See `nsflow_ros/train/data.py`.{scenes}
{method}
* Command: `{config.command}`
* Run: {steps:,} steps in {seconds / 60:.1f} min wall time on a 2-core CPU (shared with other jobs).

## Held-out comparison (NumPy solver through onnxruntime, as deployed)

Pairs from the held-out photos only, initial error exactly 5 px in a random direction. Errors are over
ALL points: a point the solver reports lost counts as a failure (infinite error).

{tables}

{notes}

## Figures

{figs}
"""
    out = Path(path)
    out.write_text(text)
    return out


def _init_text(mode: str, size: float) -> str:
    """The training points' initial flow in words."""
    if mode == "normal":
        return f"ground truth + N(0, {size:g}^2) px"
    if mode == "uniform":
        return f"ground truth + an error of length uniform in [0, {size:g}] px in a random direction"
    return "zero (displacement = the pair's own motion)"


def _teacher_text(teacher: Path | None, models: Path) -> str | None:
    """The teacher as the card names it: its path relative to the card when it lies beside it."""
    if teacher is None:
        return None
    try:
        return teacher.resolve().relative_to(models.resolve()).as_posix()
    except ValueError:
        return teacher.as_posix()


def _source_text(source: dict[str, object]) -> str:
    """One training data source in words, with its share."""
    from nsflow_ros.train.sources import SOURCES

    share = f"{float(source.get('share', 1.0)):.0%}"  # type: ignore[arg-type]
    return f"{share}: {SOURCES[str(source['kind'])].words(source)}"
