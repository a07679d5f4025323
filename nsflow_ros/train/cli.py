"""``nsflow-train``: train the NSFlow encoder from scratch, export it to ONNX, compare it with classical LK.

Example (the shipped model)::

    nsflow-train --minutes 38 --d 4 --out out/train --install

Writes under ``--out``: checkpoint, log, loss curve, one validation figure per epoch, the ONNX model, the
held-out comparison (``eval.md``). ``--install`` also copies the model to ``models/nsflow_encoder.onnx``
(the ``d4`` model) with its figures and writes its card ``models/nsflow_encoder.md``; the hand-written
card of the shipped models, ``models/README.md``, is left alone.
"""

from __future__ import annotations

import argparse
import math
import shlex
import shutil
import sys
from dataclasses import replace
from pathlib import Path

__all__ = ["build_parser", "main"]


def _init_error(text: str) -> tuple[str, float]:
    """``normal:S``, ``uniform:R`` or ``zero`` -> (mode, size)."""
    mode, _, size = text.partition(":")
    if mode == "zero" and not size:
        return mode, 0.0
    try:
        value = float(size)
    except ValueError:
        value = -1.0
    if mode not in ("normal", "uniform") or not value >= 0:
        raise argparse.ArgumentTypeError(f"expected normal:S, uniform:R or zero, got {text!r}")
    return mode, value


def _smoothing(text: str) -> tuple[float, float]:
    """``FINE,COARSE`` Gaussian sigmas (px, >= 0) -> (fine, coarse)."""
    try:
        fine, coarse = (float(v) for v in text.split(","))
    except ValueError:
        fine = coarse = -1.0
    if not (0 <= fine < math.inf and 0 <= coarse < math.inf):
        raise argparse.ArgumentTypeError(f"expected FINE,COARSE (two sigmas >= 0 in px), got {text!r}")
    return fine, coarse


def build_parser() -> argparse.ArgumentParser:
    from nsflow_ros.argtypes import positive_int, program_name

    p = argparse.ArgumentParser(
        prog=program_name("nsflow-train"),
        description="Train the NSFlow encoder from scratch through the differentiable LM Lucas-Kanade layer, "
        "export it to ONNX and compare it with classical LK on held-out photos. Writes a checkpoint, a log, "
        "the loss curve, a validation figure per epoch, the ONNX model and eval.md under --out.",
    )
    p.add_argument("--minutes", type=float, default=40.0, help="training wall-clock budget (default 40)")
    p.add_argument("--steps", type=int, default=None, help="step limit (default: only the time limit)")
    p.add_argument("--out", type=Path, default=Path("out/train"), help="run folder (default out/train)")
    p.add_argument("--seed", type=int, default=0, help="seed of weights, pairs and noise (default 0)")
    p.add_argument("--d", type=int, default=4, help="descriptor channels (default 4)")
    p.add_argument(
        "--head", choices=("sigmoid", "relu", "none"), default="sigmoid",
        help="activation of the encoder's last layer (default sigmoid)",
    )
    p.add_argument("--rgb", action="store_true", help="3-channel input (default gray)")
    p.add_argument(
        "--teacher", type=Path, default=None, metavar="ONNX",
        help="distil from this trained encoder (regression on its descriptor maps and their x/y "
        "differences) instead of training through the LK layer; the LK-layer options are then unused "
        "(unless --distill-weight)",
    )
    p.add_argument(
        "--light-min", type=float, default=0.0, metavar="S",
        help="training pairs' illumination change strength uniform in [S, 1] (default 0; higher = stronger "
        "lighting augmentation)",
    )
    p.add_argument(
        "--distill-weight", type=float, default=0.0, metavar="W",
        help="with --teacher: train through the LK layer AND add W x the distillation loss (default 0: "
        "distillation alone)",
    )
    p.add_argument(
        "--init", type=Path, default=None, metavar="CHECKPOINT",
        help="start from this encoder.pt of an earlier run (same --d / --width / --head) instead of "
        "random weights",
    )
    p.add_argument(
        "--width", type=positive_int, default=8,
        help="channels of the encoder's 3x3 convs, 2x in its 1x1 hidden layer (default 8, the paper's)",
    )
    p.add_argument(
        "--mode", choices=("implicit", "unroll"), default="implicit",
        help="LK layer backward: implicit differentiation or unrolled iterations (default implicit)",
    )
    p.add_argument(
        "--rho", choices=("huber", "cauchy", "charbonnier"), default="cauchy",
        help="robust loss on the endpoint error (default cauchy)",
    )
    p.add_argument("--delta", type=float, default=1.0, help="robust loss scale in px (default 1)")
    p.add_argument(
        "--levels", type=int, default=1,
        help="pyramid levels of the training solver, solved coarse to fine as the tracker does (default 1)",
    )
    p.add_argument(
        "--jacobian", choices=("forward", "esm"), default="forward",
        help="J of the training solver's step: the paper's (D2's derivative) or ESM (its mean with D1's, "
        "as the tracker solves); default forward",
    )
    p.add_argument(
        "--smoothing", type=_smoothing, default=None, metavar="FINE,COARSE",
        help="Gaussian smoothing of the training solver's descriptor pyramid (sigma at full resolution, "
        "sigma on coarser levels, px), as the tracker applies the smoothing a model declares; the "
        "exported model declares it (the shipped model: 1.0,1.0). Default: none",
    )
    p.add_argument(
        "--gain-levels", type=int, default=0, metavar="N",
        help="the exported model declares that the tracker compares windows up to a gain too on its N "
        "finest pyramid levels (metadata gain_levels; the shipped fast model: 1). Default 0: offset only",
    )
    p.add_argument(
        "--zero-mean", action="store_true",
        help="the training solver compares windows up to a constant per channel (LMConfig.zero_mean, as "
        "the tracker solves); default off",
    )
    p.add_argument(
        "--coarse-loss", type=float, default=0.0, metavar="W",
        help="weight of each coarse level's loss, robust scale --delta x 2^level (default 0: finest only)",
    )
    p.add_argument(
        "--init-error", type=_init_error, default=("normal", 2.5), metavar="MODE[:PX]",
        help="initial flow of training points: normal:S = GT + N(0, S^2) per axis, uniform:R = GT + an error "
        "of length uniform in [0, R], zero = zero flow (default normal:2.5)",
    )
    p.add_argument(
        "--basin-loss", type=float, default=0.0, metavar="W",
        help="weight of the basin loss: landing error of the solver's first step from a random start within "
        "--basin-radius of the answer, on every training level (default 0)",
    )
    p.add_argument(
        "--basin-radius", type=float, default=4.0, metavar="R",
        help="largest start offset of the basin loss, in each level's pixels (default 4)",
    )
    p.add_argument(
        "--scene-share", type=float, default=0.0, metavar="P",
        help="share of training pairs rendered from the sample scenes (stereo and temporal pairs with exact "
        "flow) instead of photo homographies (default 0)",
    )
    p.add_argument(
        "--translation", type=float, default=8.0,
        help="largest common shift of the training homographies per axis, px (default 8)",
    )
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    p.add_argument("--val-every", type=int, default=1000, help="steps per epoch (validation + figure)")
    p.add_argument("--val-per-image", type=int, default=3, help="validation pairs per held-out photo")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument(
        "--eval-per-image", type=int, default=20, help="held-out pairs per photo in the final comparison"
    )
    p.add_argument(
        "--install", action="store_true",
        help="copy the model to models/ and write its card there (nsflow_encoder.md)",
    )
    p.add_argument(
        "--models-dir", type=Path, default=Path("models"),
        help="where --install puts the model and its card (default models)",
    )
    p.add_argument("--card-notes", type=Path, default=None, help="Markdown file added to the model card")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    g = p.add_argument_group("data, devices and long runs")
    g.add_argument(
        "--data", action="append", default=None, metavar="KIND[:PATH][:WEIGHT]",
        help="a training data source, repeatable, mixed by weight: photos (the bundled photos), scenes "
        "(the sample scenes; PATH = their cache), tartanair:DIR (TartanAir folders), footage:PATH (a ROS 1 / "
        "ROS 2 bag, ASL folder or image folder, made into homography pairs). Default: photos, plus "
        "--scene-share of scenes",
    )
    g.add_argument(
        "--tartanair-val", default=None, metavar="ENV[,ENV]",
        help="TartanAir environments kept for validation, never trained on (default: the last by name "
        "when there are two or more; 'none' for none)",
    )
    g.add_argument(
        "--footage-topic", action="append", default=None, metavar="TOPIC",
        help="camera topic of footage bags / ASL folders, repeatable (default /cam0/image_raw, "
        "/cam1/image_raw)",
    )
    g.add_argument(
        "--footage-holdout", type=float, default=0.2, metavar="P",
        help="share of each footage's frames, at its end, kept for validation and the footage "
        "evaluation (default 0.2)",
    )
    g.add_argument("--size", type=_size, default=(320, 240), metavar="WxH", help="pair size, default 320x240")
    g.add_argument("--points", type=positive_int, default=200, help="keypoints per pair (default 200)")
    g.add_argument("--iterations", type=positive_int, default=30, help="LM iterations, training (default 30)")
    g.add_argument("--window", type=positive_int, default=11, help="solver window side, odd (default 11)")
    g.add_argument("--batch", type=positive_int, default=1, help="pairs per step and process (default 1)")
    g.add_argument(
        "--device", default="cpu", help="auto, cpu, cuda or cuda:K (default cpu; under torchrun, auto and "
        "cuda take the process's LOCAL_RANK GPU)",
    )
    g.add_argument(
        "--dtype", choices=("float32", "float64"), default="float32",
        help="dtype of the descriptor maps in the LK layer (default float32; float64 is the CPU reference)",
    )
    g.add_argument(
        "--dataloader-workers", type=int, default=0, metavar="N",
        help="processes making pairs beside training (default 0: in the training process)",
    )
    g.add_argument(
        "--checkpoint-every", type=int, default=0, metavar="N",
        help="steps between checkpoints with the optimiser state (default: at every validation; always "
        "one at the end)",
    )
    g.add_argument(
        "--resume", action="store_true",
        help="continue the run in --out from its checkpoint (same step, optimiser state and pair order)",
    )
    g.add_argument(
        "--recipe", choices=("paper",), default=None,
        help="preset: paper = the paper's stated settings (640x480 RGB TartanAir pairs, 200 keypoints, 50 "
        "iterations, 11x11 window, Adam 1e-3, batch 1, d 3, ReLU head); needs --data tartanair:DIR; "
        "options given explicitly win",
    )
    g.add_argument(
        "--footage-eval-per-frame", type=positive_int, default=4, metavar="N",
        help="pairs per held-out footage frame and lighting condition in the footage evaluation (default 4)",
    )
    return p


def _size(text: str) -> tuple[int, int]:
    """``WxH`` -> (width, height), both >= 16."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"expected WxH (two integers >= 16), got {text!r}")
    return w, h


def parse(argv: list[str]) -> argparse.Namespace:
    """Parse the command line; a ``--recipe`` sets its values for every option not given explicitly."""
    from nsflow_ros.train.recipes import recipe_defaults

    parser = build_parser()
    opts = parser.parse_args(argv)
    if opts.recipe is not None:
        parser.set_defaults(**recipe_defaults(opts.recipe))
        opts = parser.parse_args(argv)
    return opts


def main(args: list[str] | None = None) -> int:
    """Entry point; returns the exit code (1 on a known error)."""
    argv = sys.argv[1:] if args is None else args
    opts = parse(argv)
    from nsflow_ros.errors import NSFlowError
    from nsflow_ros.train.distributed import leave_distributed

    clean = False
    try:
        code = _run(opts, argv)
        clean = True
        return code
    except NSFlowError as err:
        print(f"nsflow-train: error: {err}", file=sys.stderr)
        return 1
    finally:
        leave_distributed(clean)


def _run(opts: argparse.Namespace, argv: list[str]) -> int:
    import numpy as np
    import torch

    from nsflow_ros import Jacobian, Smoothing, load_encoder
    from nsflow_ros.core.methods import PAPER_LM
    from nsflow_ros.train.card import CARD_NAME, write_model_card
    from nsflow_ros.train.data import PairConfig
    from nsflow_ros.train.errors import TrainError
    from nsflow_ros.train.evaluate import compare, format_table, heldout_pairs
    from nsflow_ros.train.export import export_onnx
    from nsflow_ros.train.figures import plot_validation
    from nsflow_ros.train.footage_eval import evaluate_footage, format_footage_table, plot_footage
    from nsflow_ros.train.lk_layer import BackwardMode
    from nsflow_ros.train.model import EncoderSpec, count_flops, count_parameters
    from nsflow_ros.train.recipes import PAPER_DATA, PAPER_OPEN
    from nsflow_ros.train.sources import parse_data_spec
    from nsflow_ros.train.trainer import TrainConfig, make_data, train

    data = tuple(parse_data_spec(s) for s in opts.data or ())
    if opts.recipe == "paper" and PAPER_DATA not in {d.kind for d in data}:
        raise TrainError("--recipe paper trains on TartanAir: give --data tartanair:DIR")
    if opts.window < 3 or opts.window % 2 == 0:
        raise TrainError(f"--window must be odd and >= 3, got {opts.window}")
    val_envs = None
    if opts.tartanair_val is not None:
        val_envs = () if opts.tartanair_val == "none" else tuple(opts.tartanair_val.split(","))
    spec = EncoderSpec(d=opts.d, in_channels=3 if opts.rgb else 1, head=opts.head, width=opts.width)
    command = "nsflow-train " + shlex.join(argv)
    # the options named as their TrainConfig fields, then the others
    same = ("out", "minutes", "steps", "seed", "lr", "rho", "scene_share", "basin_radius", "val_every",
            "threads", "val_per_image", "teacher", "distill_weight", "init", "footage_holdout", "batch",
            "device", "dtype", "checkpoint_every", "resume")
    cfg = TrainConfig(
        **{name: getattr(opts, name) for name in same},
        spec=spec,
        mode=BackwardMode(opts.mode),
        huber_delta=opts.delta,
        lm=replace(
            TrainConfig().lm,
            levels=opts.levels,
            jacobian=Jacobian(opts.jacobian),
            zero_mean=opts.zero_mean,
            max_iterations=opts.iterations,
            window=opts.window,
        ),
        coarse_weight=opts.coarse_loss,
        basin_weight=opts.basin_loss,
        pair=PairConfig(
            width=opts.size[0],
            height=opts.size[1],
            max_points=opts.points,
            window=opts.window,
            init_mode=opts.init_error[0],
            init_sigma=opts.init_error[1],
            translation=opts.translation,
            light_min=opts.light_min,
        ),
        smoothing=None if opts.smoothing is None else Smoothing(*opts.smoothing),
        data=data,
        tartanair_val=val_envs,
        footage_topics=tuple(opts.footage_topic) if opts.footage_topic else None,
        workers=opts.dataloader_workers,
        command=command,
    )
    train_data = make_data(cfg)
    result = train(cfg, progress=not opts.no_progress, data=train_data)
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized() and dist.get_rank() != 0:
        return 0  # rank 0 alone exports, evaluates and writes the card
    result.model.cpu()
    out = Path(opts.out)
    meta = {"training_command": command}
    if opts.smoothing is not None:
        meta["smoothing"] = ",".join(f"{v:g}" for v in opts.smoothing)
    if opts.gain_levels < 0:
        raise TrainError(f"--gain-levels must be >= 0, got {opts.gain_levels}")
    if opts.gain_levels:
        meta["gain_levels"] = str(opts.gain_levels)
    onnx_path = export_onnx(result.model, out / "nsflow_encoder.onnx", meta)
    encoder = load_encoder(onnx_path)  # as deployed: with the smoothing it declares
    # The export must reproduce the torch encoder.
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (97, 131), dtype=np.uint8)
    with torch.no_grad():
        x = torch.from_numpy(img.astype(np.float32) / 255.0)[None, None].expand(1, spec.in_channels, 97, 131)
        ref = result.model(x)[0].permute(1, 2, 0).numpy()
    diff = float(np.abs(load_encoder(onnx_path, smoothing=Smoothing())(img) - ref).max())
    print(f"ONNX vs torch max abs difference: {diff:.2e}")
    comparisons = []
    for label, strength in (("perturbed", 1.0), ("clean", 0.0)):
        pairs = heldout_pairs(opts.eval_per_image, strength=strength)
        # Algorithm 1 as written on the paper's pyramid and on one level (the basin the training shapes);
        # the tracker's own configuration is scored by nsflow-evaluate.
        for config in (PAPER_LM, replace(PAPER_LM, levels=1, max_iterations=30)):
            comparisons.append(compare(encoder, pairs, config, label))
    table = format_table(comparisons)
    (out / "eval.md").write_text(table + "\n")
    print(table)
    curves = {
        f"{mode} {c.label}": (err, None)
        for c in comparisons
        if c.config.levels == 3
        for mode, err in (("NSFlow", c.nsflow_errors), ("classical", c.classical_errors))
    }
    eval_png = plot_validation(
        curves, "held-out pairs, NumPy solver (3 levels), 5 px start", out / "eval_heldout.png"
    )
    for name, src in train_data.validation.items():
        frames = src.evaluation_frames()
        if frames:  # this run beside the shipped model
            rows = evaluate_footage(
                {"this run": encoder, "shipped": load_encoder()}, frames, opts.footage_eval_per_frame
            )
            footage_table = format_footage_table(rows)
            (out / f"eval_{name}.md").write_text(footage_table + "\n")
            plot_footage(rows, out / f"eval_{name}.png")
            print(f"held-out frames of {src.describe()['path']}:\n{footage_table}")
    # --val-every 0 runs no validation, so there is no validation figure to install
    files = {"loss": result.files["loss_png"], "val": result.files.get("val_png"), "eval": eval_png}
    if opts.install:
        models = Path(opts.models_dir)
        models.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(onnx_path, models / "nsflow_encoder.onnx")
        shutil.copyfile(files["loss"], models / "train_loss.png")
        shutil.copyfile(files["eval"], models / "eval_heldout.png")
        figures = {
            "Held-out comparison, NumPy solver as deployed (3 levels), 5 px start": "eval_heldout.png",
            "Training loss and held-out validation share < 1 px per epoch": "train_loss.png",
        }
        if files["val"] is not None:
            shutil.copyfile(files["val"], models / "train_validation.png")
            last_epoch = "Held-out validation, last epoch (torch layer, levels=1, 5 px start)"
            figures[last_epoch] = "train_validation.png"
        notes = opts.card_notes.read_text() if opts.card_notes else ""
        card = write_model_card(
            models / CARD_NAME,
            cfg,
            parameters=count_parameters(result.model),
            flops=count_flops(spec),
            steps=result.steps,
            seconds=result.seconds,
            tables=table,
            figures=figures,
            notes=notes,
            data=train_data.source.describe()["sources"] if cfg.data else None,  # type: ignore[arg-type]
            recipe=("paper", PAPER_OPEN) if opts.recipe == "paper" else None,
        )
        print(f"installed {models / 'nsflow_encoder.onnx'} and its card {card}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
