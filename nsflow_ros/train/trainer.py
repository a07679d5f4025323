"""The training loop (paper, Algorithm 2): pair -> encoder -> LK layer -> robust EPE loss -> Adam."""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.train.basin import basin_loss
from nsflow_ros.train.data import TRAIN_IMAGES, Pair, PairConfig, load_image, make_pair
from nsflow_ros.train.distill import Teacher, distill_step
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.evaluate import heldout_pairs
from nsflow_ros.train.figures import plot_loss, plot_validation
from nsflow_ros.train.lk_layer import BackwardMode, lk_track, lk_track_pyramid
from nsflow_ros.train.loss import flow_loss
from nsflow_ros.train.model import Encoder, EncoderSpec
from nsflow_ros.train.ops import pyramid
from nsflow_ros.train.scenes import ScenePool, make_scene_pair

__all__ = ["TrainConfig", "TrainResult", "encode_pair", "load_checkpoint", "train", "train_step", "validate"]


@dataclass(frozen=True)
class TrainConfig:
    """Settings of a training run.

    Attributes:
        spec: encoder shape.
        out: run folder (checkpoint, figures, log).
        minutes: wall-clock budget (training stops after it; validation and export come after).
        steps: step limit (None = only the time limit).
        seed: seeds torch and the pair generator.
        lr: Adam learning rate.
        mode: LK layer backward.
        lm: solver settings in the training forward. ``levels=1`` (the shipped model's) solves at full
            resolution only; more levels solve coarse to fine through the descriptor pyramid as the tracker
            does (:func:`~nsflow_ros.train.lk_layer.lk_track_pyramid`). ``min_eigen=0``: the loss masks only
            lost points (outside the image, non-finite), not flat windows - a fresh encoder's descriptors
            are nearly flat everywhere and would otherwise mask every point and stall training.
        coarse_weight: weight of each coarse level's loss (0 = the finest result only). A coarse level's
            result (scaled to level-0 pixels) is compared with the ground truth in that level's own pixels
            (error / 2^level, same robust penalty and scale): it only has to land inside the next level's
            basin. With the implicit backward this term is the only gradient the coarse maps get.
        basin_weight: weight of the basin loss (:mod:`~nsflow_ros.train.basin`: where the solver's first
            step lands from a random start near the answer, on every training level); 0 = off.
        basin_radius: largest start offset of the basin loss, in each level's own pixels.
        pair: pair settings (photo and scene pairs alike).
        scene_share: share of training pairs rendered from the sample scenes
            (:mod:`~nsflow_ros.train.scenes`: stereo at the EuRoC baseline and temporal pairs, exact flow);
            the rest are photo homographies. 0 = photos only (the shipped model's data).
        scene_cache: folder of the scenes' sample-sequence metadata (made once, reused);
            None = ``cache`` beside ``out``.
        huber_delta: scale of the robust loss in pixels.
        rho: the robust loss (see :func:`~nsflow_ros.train.loss.flow_loss`).
        val_every: steps between validations (one "epoch").
        val_per_image: validation pairs per held-out photo and condition.
        threads: torch intra-op threads.
        images: training photos.
        teacher: an ONNX encoder to distil from (:mod:`~nsflow_ros.train.distill`): each step then
            regresses the encoder's maps of both frames on the teacher's, and the LK-layer settings
            (``mode``, ``lm``, ``coarse_weight``, ``basin_*``, ``rho``, ``huber_delta``) are not used.
            None = end-to-end training through the LK layer.
        init: a checkpoint (``encoder.pt`` of an earlier run, same spec) to start from instead of
            random weights, e.g. to fine-tune a distilled encoder through the LK layer.
        smoothing: Gaussian smoothing of the descriptor pyramid in the training solver, validation
            and the basin loss, as the tracker applies a model's declared smoothing
            (``nsflow_ros.core.pyramid.Smoothing``); the export then declares it. None = none.
    """

    spec: EncoderSpec = field(default_factory=EncoderSpec)
    out: Path = Path("out/train")
    minutes: float = 40.0
    steps: int | None = None
    seed: int = 0
    lr: float = 1e-3
    mode: BackwardMode = BackwardMode.IMPLICIT
    # lambda_scale=0: the fixed lambda^(0) the shipped model was trained with (models/README.md)
    lm: LMConfig = field(
        default_factory=lambda: LMConfig(
            levels=1, max_iterations=30, eps=1e-3, min_eigen=0.0, lambda_scale=0.0
        )
    )
    coarse_weight: float = 0.0
    basin_weight: float = 0.0
    basin_radius: float = 4.0
    pair: PairConfig = field(default_factory=PairConfig)
    scene_share: float = 0.0
    scene_cache: Path | None = None
    huber_delta: float = 1.0
    rho: str = "huber"
    val_every: int = 500
    val_per_image: int = 3
    threads: int = 2
    images: tuple[str, ...] = TRAIN_IMAGES
    teacher: Path | None = None
    init: Path | None = None
    smoothing: Smoothing | None = None


def load_checkpoint(model: Encoder, path: str | Path) -> None:
    """Load an ``encoder.pt`` into ``model``; a missing file or another encoder shape is a TrainError."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError) as err:
        raise TrainError(f"cannot read checkpoint {path}: {err}") from err
    spec = model.spec.as_dict()
    if not isinstance(ckpt, dict) or ckpt.get("spec") != spec:
        got = ckpt.get("spec") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise TrainError(f"checkpoint {path} holds an encoder of spec {got}, this run trains {spec}")
    model.load_state_dict(ckpt["state"])


@dataclass
class TrainResult:
    """What a run produced."""

    model: Encoder
    losses: list[float]
    val_steps: list[int]
    val_within: list[float]
    steps: int
    seconds: float
    files: dict[str, Path]


def _to_tensor(image: np.ndarray, in_channels: int) -> torch.Tensor:
    x = torch.from_numpy(image.astype(np.float32) / 255.0)[None, None]
    return x.expand(1, in_channels, *image.shape).contiguous() if in_channels == 3 else x


def encode_pair(model: Encoder, pair: Pair) -> tuple[torch.Tensor, torch.Tensor]:
    """Encoder outputs (d, H, W) of both frames of a pair (one batched forward)."""
    x = torch.cat(
        [_to_tensor(pair.image1, model.spec.in_channels), _to_tensor(pair.image2, model.spec.in_channels)]
    )
    d = model(x)
    return d[0], d[1]


def train_step(model: Encoder, opt: torch.optim.Optimizer, pair: Pair, cfg: TrainConfig) -> float | None:
    """One optimisation step on one pair; returns the loss, or None when no point was usable."""
    d1, d2 = encode_pair(model, pair)
    pts, flow0, gt = (torch.from_numpy(a) for a in (pair.points, pair.flow0, pair.flow_gt))
    if cfg.lm.levels == 1:
        s1, s2 = (pyramid(d, 1, cfg.smoothing)[0] for d in (d1, d2))
        res = lk_track(s1, s2, pts, flow0, cfg.lm, mode=cfg.mode)
        loss, used = flow_loss(res.flow, gt, res.status, cfg.huber_delta, cfg.rho)
    else:
        out = lk_track_pyramid(d1, d2, pts, flow0, cfg.lm, mode=cfg.mode, smoothing=cfg.smoothing)
        loss, used = flow_loss(out.flow, gt, out.status, cfg.huber_delta, cfg.rho)
        if cfg.coarse_weight > 0:
            for lev, res in enumerate(out.levels[1:], start=1):
                s = 2.0**lev
                term = flow_loss(res.flow / s, gt / s, res.status, cfg.huber_delta, cfg.rho)[0]
                loss = loss + cfg.coarse_weight * term
    if used == 0:
        return None
    if cfg.basin_weight > 0:
        basin = basin_loss(
            d1, d2, pts, gt, cfg.lm, cfg.basin_radius, cfg.huber_delta, cfg.rho, smoothing=cfg.smoothing
        )
        loss = loss + cfg.basin_weight * basin
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def _pair_errors(
    model: Encoder | None, pair: Pair, lm: LMConfig, smoothing: Smoothing | None = None
) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        if model is None:
            d1 = torch.from_numpy(pair.image1.astype(np.float32) / 255.0)[None]
            d2 = torch.from_numpy(pair.image2.astype(np.float32) / 255.0)[None]
        else:
            d1, d2 = (pyramid(d, 1, smoothing)[0] for d in encode_pair(model, pair))
        out = lk_track(d1, d2, torch.from_numpy(pair.points), torch.from_numpy(pair.flow0), lm)
    err = np.linalg.norm(out.flow.numpy() - pair.flow_gt, axis=1)
    return np.where(out.status.numpy(), err, np.inf), out.status.numpy()


def validate(
    model: Encoder | None, pairs: list[Pair], lm: LMConfig, smoothing: Smoothing | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Endpoint errors (inf where lost) and statuses of all points; ``model=None`` is the classical mode
    (never smoothed); ``smoothing`` is the model's (only its fine part acts: ``lm`` solves one level)."""
    errs, stats = zip(*(_pair_errors(model, p, lm, smoothing) for p in pairs if len(p.points)), strict=True)
    return np.concatenate(errs), np.concatenate(stats)


def train(cfg: TrainConfig, progress: bool = True) -> TrainResult:
    """Train an encoder from scratch.

    Args:
        cfg: run settings.
        progress: show progress.

    Returns:
        the trained model (final weights, no selection on validation data) and the run's records.
    """
    if cfg.coarse_weight < 0:
        raise TrainError(f"coarse_weight must be >= 0, got {cfg.coarse_weight}")
    if cfg.basin_weight < 0 or cfg.basin_radius < 0:
        raise TrainError(f"basin weight and radius must be >= 0, got {cfg.basin_weight}, {cfg.basin_radius}")
    if not 0.0 <= cfg.scene_share <= 1.0:
        raise TrainError(f"scene_share must be in [0, 1], got {cfg.scene_share}")
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    sources = [load_image(n) for n in cfg.images]
    pool = None
    if cfg.scene_share > 0:
        pool = ScenePool(cfg.scene_cache or out.parent / "cache", seed=cfg.seed)
    model = Encoder(cfg.spec)
    if cfg.init is not None:
        load_checkpoint(model, cfg.init)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    # The kind of step is chosen once: through the LK layer, or regression on a teacher's maps.
    step_fn: Callable[[Pair], float | None]
    if cfg.teacher is None:
        step_fn = functools.partial(train_step, model, opt, cfg=cfg)
    else:
        teacher = Teacher(cfg.teacher, cfg.spec.d, cfg.spec.in_channels)
        step_fn = functools.partial(distill_step, model, opt, teacher=teacher)
    # One level from 5 px needs the longer limit; the residual is the training solver's.
    val_lm = LMConfig(levels=1, max_iterations=30, zero_mean=cfg.lm.zero_mean)
    val_sets = {
        "perturbed": heldout_pairs(cfg.val_per_image, strength=1.0, seed=7),
        "clean": heldout_pairs(cfg.val_per_image, strength=0.0, seed=7),
    }
    baseline = {k: validate(None, v, val_lm) for k, v in val_sets.items()}
    losses: list[float] = []
    val_steps: list[int] = []
    val_within: list[float] = []
    log = (out / "log.jsonl").open("w")
    bar = None
    if progress:
        from nsflow_ros.progress import progress_bar

        bar = progress_bar(total=cfg.steps, unit="step", dynamic_ncols=True)
    start = time.monotonic()
    deadline = start + 60.0 * cfg.minutes
    step = 0

    def run_validation() -> None:
        model.eval()
        results: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        record: dict[str, float | int] = {"step": step, "seconds": round(time.monotonic() - start, 1)}
        for name, pairs in val_sets.items():
            err, st = validate(model, pairs, val_lm, cfg.smoothing)
            results[f"NSFlow {name}"] = (err, st)
            results[f"classical {name}"] = baseline[name]
            record[f"{name}_within1"] = float((err < 1).mean())
            record[f"{name}_median"] = float(np.median(err))
            record[f"{name}_classical_within1"] = float((baseline[name][0] < 1).mean())
        model.train()
        val_steps.append(step)
        val_within.append(float(record["perturbed_within1"]))
        epoch = len(val_steps) - 1
        plot_validation(
            results,
            f"held-out validation, step {step} (levels=1, 5 px start)",
            out / f"val_epoch{epoch:02d}.png",
        )
        log.write(json.dumps(record) + "\n")
        log.flush()
        if bar is not None:
            bar.set_postfix(
                val1px=f"{record['perturbed_within1']:.3f}",
                cls=f"{record['perturbed_classical_within1']:.3f}",
            )

    run_validation()
    model.train()
    while (cfg.steps is None or step < cfg.steps) and time.monotonic() < deadline:
        if pool is not None and rng.uniform() < cfg.scene_share:
            pair = make_scene_pair(pool, rng, cfg.pair, strength=float(rng.uniform(0.0, 1.0)))
        else:
            src = sources[int(rng.integers(len(sources)))]
            pair = make_pair(src, rng, cfg.pair, strength=float(rng.uniform(0.0, 1.0)))
        if len(pair.points) < 4:
            continue
        value = step_fn(pair)
        if value is None:
            continue
        step += 1
        losses.append(value)
        if bar is not None:
            bar.update(1)
            if step % 20 == 0:
                bar.set_description(f"loss {np.mean(losses[-100:]):.4f}")
        if step % cfg.val_every == 0:
            run_validation()
            torch.save(
                {"spec": cfg.spec.as_dict(), "state": model.state_dict(), "step": step}, out / "encoder.pt"
            )
    if not val_steps or val_steps[-1] != step:
        run_validation()
    seconds = time.monotonic() - start
    if bar is not None:
        bar.close()
    log.close()
    torch.save({"spec": cfg.spec.as_dict(), "state": model.state_dict(), "step": step}, out / "encoder.pt")
    np.save(out / "losses.npy", np.asarray(losses))
    loss_png = plot_loss(losses, val_steps, val_within, out / "loss.png")
    files = {
        "checkpoint": out / "encoder.pt",
        "loss_png": loss_png,
        "val_png": out / f"val_epoch{len(val_steps) - 1:02d}.png",
        "log": out / "log.jsonl",
    }
    meta = {"config": {k: str(v) for k, v in asdict(cfg).items()}, "steps": step, "seconds": seconds}
    (out / "run.json").write_text(json.dumps(meta, indent=1))
    return TrainResult(model.eval(), losses, val_steps, val_within, step, seconds, files)
