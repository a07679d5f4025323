"""The training loop (paper, Algorithm 2): pairs -> encoder -> LK layer -> robust EPE loss -> Adam.

One loop serves every data mix, batch, device, process count, worker count and resumed run: the pairs a
step trains on depend only on the seed, the step and the global batch
(:class:`~nsflow_ros.train.sources.PairStream`), so all of these see the pairs of one uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.core.solver import LMConfig
from nsflow_ros.optional import require
from nsflow_ros.train.basin import basin_loss
from nsflow_ros.train.data import TRAIN_IMAGES, Pair, PairConfig, initial_flow, load_image
from nsflow_ros.train.device import resolve_device, resolve_dtype
from nsflow_ros.train.distill import Teacher, distill_loss
from nsflow_ros.train.distributed import World, all_mean, broadcast_flag, init_distributed, shard
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.evaluate import heldout_pairs
from nsflow_ros.train.figures import plot_loss, plot_validation
from nsflow_ros.train.lk_layer import BackwardMode, lk_track, lk_track_pyramid
from nsflow_ros.train.loss import flow_loss
from nsflow_ros.train.model import Encoder, EncoderSpec
from nsflow_ros.train.ops import pyramid
from nsflow_ros.train.runlog import TENSORBOARD_HINT, Progress, StepLog, run_record
from nsflow_ros.train.sources import (
    DataSpec,
    MixedSource,
    PairSource,
    PairStream,
    PhotoSource,
    SceneSource,
    SourceOptions,
)

__all__ = [
    "TrainConfig",
    "TrainData",
    "TrainResult",
    "batch_loss",
    "encode_pair",
    "load_checkpoint",
    "make_data",
    "train",
    "train_step",
    "validate",
]


@dataclass(frozen=True)
class TrainConfig:
    """Settings of a training run.

    Most fields are the ``nsflow-train`` options of the same name (``huber_delta`` is ``--delta``; see its
    ``--help``); the others and those whose meaning goes beyond the option follow.

    Attributes:
        minutes: wall-clock budget of the training steps (validation and export come after).
        steps: step limit (None = only the time limit).
        lm: solver settings of the training forward. ``min_eigen=0`` because a fresh encoder's nearly flat
            descriptors would otherwise mask every point and stall training.
        coarse_weight: weight of each coarse level's loss, its error in that level's own pixels (with the
            implicit backward the only gradient the coarse maps get); 0 = the finest result only.
        scene_share: share of sample-scene pairs beside the photo pairs when ``data`` is empty.
        scene_cache: folder of the scenes' sample-sequence metadata; None = ``cache`` beside ``out``.
        images: training photos when ``data`` is empty.
        teacher: an ONNX encoder to distil from instead of training through the LK layer (whose settings
            are then unused), unless ``distill_weight`` > 0.
        distill_weight: with ``teacher``, train through the LK layer and add this weight times the
            distillation loss (the teacher's maps anchor what the solver's loss alone would trade away:
            precision and lighting robustness); 0 = distillation alone.
        init: a checkpoint (``encoder.pt`` of an earlier run or an exported ``.onnx``, same spec) to start
            from instead of random weights.
        smoothing: Gaussian smoothing of the descriptor pyramid in the training solver, validation and the
            basin loss, declared by the export; None = none.
        data: the ``--data`` entries; empty = the bundled photos plus ``scene_share`` of scene pairs.
        tartanair_val: TartanAir environments held out; None = the last one when there are two or more.
        batch: pairs per step and process (the loss is the mean of the pairs' losses).
        workers: data-loader worker processes making pairs (0 = in the training process).
        checkpoint_every: steps between checkpoints; 0 = at each validation only (always one at the end).
        resume: continue the run whose checkpoint is in ``out`` with the same pair order.
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
    distill_weight: float = 0.0
    init: Path | None = None
    smoothing: Smoothing | None = None
    data: tuple[DataSpec, ...] = ()
    tartanair_val: tuple[str, ...] | None = None
    footage_topics: tuple[str, ...] | None = None
    footage_holdout: float = 0.2
    batch: int = 1
    device: str = "cpu"
    dtype: str = "float32"
    workers: int = 0
    checkpoint_every: int = 0
    resume: bool = False
    command: str = ""
    tensorboard: bool = True


def _onnx_checkpoint(path: Path) -> dict[str, object]:
    """An exported encoder's weights and spec."""
    onnx = require("onnx", "reading an exported encoder")
    numpy_helper = onnx.numpy_helper

    try:
        proto = onnx.load(str(path))
    except (OSError, ValueError, onnx.onnx_cpp2py_export.checker.ValidationError) as err:
        raise TrainError(f"cannot read ONNX encoder {path}: {err}") from err
    meta = {p.key: p.value for p in proto.metadata_props}
    if "spec" not in meta:
        raise TrainError(f"{path} has no 'spec' metadata: not an encoder exported by nsflow-train")
    state = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in proto.graph.initializer}
    return {"spec": json.loads(meta["spec"]), "state": state}


def load_checkpoint(model: Encoder, path: str | Path) -> dict[str, object]:
    """Load an ``encoder.pt`` (or an exported ``.onnx`` encoder) into ``model``; returns the checkpoint.

    Raises:
        TrainError: a missing or unreadable file, or another encoder shape.
    """
    if Path(path).suffix == ".onnx":
        ckpt: object = _onnx_checkpoint(Path(path))
    else:
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except (OSError, RuntimeError) as err:
            raise TrainError(f"cannot read checkpoint {path}: {err}") from err
    spec = model.spec.as_dict()
    if not isinstance(ckpt, dict) or ckpt.get("spec") != spec:
        got = ckpt.get("spec") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise TrainError(f"checkpoint {path} holds an encoder of spec {got}, this run trains {spec}")
    try:
        model.load_state_dict(ckpt["state"])
    except RuntimeError as err:
        raise TrainError(f"checkpoint {path} does not fit the encoder: {err}") from err
    return ckpt


@dataclass
class TrainResult:
    """What a run produced (``losses`` over the whole run, resumed parts included)."""

    model: Encoder
    losses: list[float]
    val_steps: list[int]
    val_within: list[float]
    steps: int
    seconds: float
    files: dict[str, Path]


def _device_of(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


def _to_tensor(image: np.ndarray, in_channels: int) -> torch.Tensor:
    """(1, c_in, H, W) float32 in [0, 1] of a gray (H, W) or RGB (H, W, 3) uint8 frame."""
    if image.ndim == 3:
        x = torch.from_numpy(image.astype(np.float32) / 255.0).permute(2, 0, 1)[None]
        if in_channels == 1:
            raise TrainError(f"a colour frame {image.shape} reached a gray encoder (use --rgb)")
        return x.contiguous()
    x = torch.from_numpy(image.astype(np.float32) / 255.0)[None, None]
    return x.expand(1, in_channels, *image.shape).contiguous() if in_channels == 3 else x


def _frames(pairs: list[Pair], in_channels: int, device: torch.device) -> torch.Tensor:
    """Both frames of every pair as one (2B, c_in, H, W) batch: pair b's frames at 2b and 2b + 1."""
    x = torch.cat([_to_tensor(im, in_channels) for p in pairs for im in (p.image1, p.image2)])
    return x.to(device)


def encode_pair(model: Encoder, pair: Pair) -> tuple[torch.Tensor, torch.Tensor]:
    """Encoder outputs (d, H, W) of both frames of a pair (one batched forward)."""
    d = model(_frames([pair], model.spec.in_channels, _device_of(model)))
    return d[0], d[1]


def _pair_loss(
    d1: torch.Tensor, d2: torch.Tensor, pair: Pair, cfg: TrainConfig
) -> tuple[torch.Tensor, int]:
    """The LK-layer loss of one pair from its two maps."""
    dev = d1.device
    pts, flow0, gt = (torch.from_numpy(a).to(dev) for a in (pair.points, pair.flow0, pair.flow_gt))
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
    if used and cfg.basin_weight > 0:
        basin = basin_loss(
            d1, d2, pts, gt, cfg.lm, cfg.basin_radius, cfg.huber_delta, cfg.rho, smoothing=cfg.smoothing
        )
        loss = loss + cfg.basin_weight * basin
    return loss, used


def batch_loss(
    model: torch.nn.Module,
    pairs: list[Pair],
    cfg: TrainConfig,
    teacher: Teacher | None = None,
) -> tuple[torch.Tensor, int]:
    """The loss of one step: the mean over ``pairs`` of each pair's loss, and the points used.

    A pair without a usable point adds 0 and the maps always enter the graph, so every parameter of
    every rank gets a gradient, as DistributedDataParallel needs.

    Args:
        model: the encoder (or its DistributedDataParallel wrapper).
        pairs: the step's pairs (same frame size).
        cfg: loss and solver settings.
        teacher: distil from this teacher's maps: alone, or beside the LK layer's loss with weight
            ``cfg.distill_weight`` when that is > 0.
    """
    spec: EncoderSpec = getattr(model, "module", model).spec
    device = _device_of(model)
    d = model(_frames(pairs, spec.in_channels, device))
    anchor = 0.0 * d.sum()
    distilled = None
    if teacher is not None:
        frames = [im for p in pairs for im in (p.image1, p.image2)]
        target = torch.stack([teacher(f) for f in frames]).to(device)
        distilled = distill_loss(d, target)
        if cfg.distill_weight <= 0:
            return distilled + anchor, sum(len(p.points) for p in pairs)
    dtype = resolve_dtype(cfg.dtype)
    maps = d.to(dtype)
    total: torch.Tensor = anchor.to(torch.float64)
    points = 0
    for b, pair in enumerate(pairs):
        loss, used = _pair_loss(maps[2 * b], maps[2 * b + 1], pair, cfg)
        if used:
            total = total + loss.to(torch.float64)
            points += used
    total = total / len(pairs)
    if distilled is not None:
        total = total + cfg.distill_weight * distilled.to(torch.float64)
    return total, points


def train_step(
    model: Encoder, opt: torch.optim.Optimizer, pair: Pair, cfg: TrainConfig, teacher: Teacher | None = None
) -> float | None:
    """One optimisation step on one pair (as :func:`batch_loss`); returns the loss, or None (no step) when
    no point was usable."""
    loss, used = batch_loss(model, [pair], cfg, teacher)
    if used == 0:
        return None
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def _pair_errors(
    model: Encoder | None, pair: Pair, lm: LMConfig, smoothing: Smoothing | None = None
) -> tuple[np.ndarray, np.ndarray]:
    with torch.no_grad():
        if model is None:
            gray = [im if im.ndim == 2 else im.mean(2) for im in (pair.image1, pair.image2)]
            d1, d2 = (torch.from_numpy(g.astype(np.float32) / 255.0)[None] for g in gray)
        else:
            d1, d2 = (pyramid(d, 1, smoothing)[0] for d in encode_pair(model, pair))
        dev = d1.device
        pts, flow0 = (torch.from_numpy(a).to(dev) for a in (pair.points, pair.flow0))
        out = lk_track(d1, d2, pts, flow0, lm)
    flow, status = out.flow.cpu().numpy(), out.status.cpu().numpy()
    err = np.linalg.norm(flow - pair.flow_gt, axis=1)
    return np.where(status, err, np.inf), status


def validate(
    model: Encoder | None, pairs: list[Pair], lm: LMConfig, smoothing: Smoothing | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Endpoint errors (inf where lost) and statuses of all points; ``model=None`` is the classical mode
    (never smoothed)."""
    errs, stats = zip(*(_pair_errors(model, p, lm, smoothing) for p in pairs if len(p.points)), strict=True)
    return np.concatenate(errs), np.concatenate(stats)


@dataclass
class TrainData:
    """A run's data: the training mix and the held-out sources validated beside the held-out photos."""

    source: MixedSource
    validation: dict[str, PairSource] = field(default_factory=dict)

    def describe(self) -> dict[str, object]:
        return {
            "train": self.source.describe(),
            "validation": {k: v.describe() for k, v in self.validation.items()},
        }


def make_data(cfg: TrainConfig) -> TrainData:
    """The training mix and its held-out validation sources from ``cfg.data``.

    Raises:
        TrainError: bad settings (checked before any data is read), or a source cannot be read or split.
    """
    _check(cfg)
    cache = cfg.scene_cache or Path(cfg.out).parent / "cache"
    if not cfg.data:
        parts: list[tuple[PairSource, float]] = []
        if cfg.scene_share > 0:
            parts.append((SceneSource(cache, seed=cfg.seed), cfg.scene_share))
        if cfg.scene_share < 1:
            parts.append((PhotoSource(cfg.images), 1.0 - cfg.scene_share))
        return TrainData(MixedSource(parts))
    parts = []
    validation: dict[str, PairSource] = {}
    opts = SourceOptions(
        seed=cfg.seed,
        cache=cache,
        color=cfg.spec.in_channels == 3,
        tartanair_val=cfg.tartanair_val,
        topics=list(cfg.footage_topics) if cfg.footage_topics else None,
        holdout=cfg.footage_holdout,
    )
    for k, spec in enumerate(cfg.data):
        tag = f"{spec.kind}{k}" if sum(s.kind == spec.kind for s in cfg.data) > 1 else spec.kind
        train_src, held = spec.split(opts)
        parts.append((train_src, spec.weight))
        if held is not None:
            validation[tag] = held
    return TrainData(MixedSource(parts), validation)


def _validation_pairs(source: PairSource, cfg: PairConfig, count: int, seed: int = 7) -> list[Pair]:
    """Fixed validation pairs of a held-out source, initial error 5 px in a random direction."""
    stream = PairStream(source, cfg, seed=seed)
    pairs = []
    for i in range(count):
        p = stream[i]
        flow0 = initial_flow(p.flow_gt, np.random.default_rng([seed, i, 99]), cfg, init_error=5.0)
        pairs.append(dataclasses.replace(p, flow0=flow0))
    return pairs


class _StreamDataset(torch.utils.data.Dataset):
    """The pair stream as a map-style dataset, for data-loader workers."""

    def __init__(self, stream: PairStream) -> None:
        self.stream = stream

    def __len__(self) -> int:  # the stream has no end; the batch sampler bounds it
        return 2**62

    def __getitem__(self, index: int) -> Pair:
        return self.stream[index]


class _StepSampler(torch.utils.data.Sampler):
    """Yields each step's shard of stream indices, from ``first`` on (``last`` = None: no end)."""

    def __init__(self, first: int, last: int | None, batch: int, world: World) -> None:
        self.first, self.last, self.batch, self.world = first, last, batch, world

    def __iter__(self) -> Iterator[list[int]]:
        step = self.first
        while self.last is None or step < self.last:
            yield shard(step, self.batch, self.world)
            step += 1


def _batches(stream: PairStream, first: int, cfg: TrainConfig, world: World) -> Iterator[list[Pair]]:
    sampler = _StepSampler(first, cfg.steps, cfg.batch, world)
    if cfg.workers <= 0:
        return ([stream[i] for i in idx] for idx in sampler)
    loader = torch.utils.data.DataLoader(
        _StreamDataset(stream),
        batch_sampler=sampler,
        num_workers=cfg.workers,
        collate_fn=list,
        persistent_workers=False,
        prefetch_factor=2,
    )
    return iter(loader)


def _save(path: Path, payload: dict[str, object]) -> None:
    """Write a checkpoint atomically, so a run killed while writing keeps the previous one."""
    tmp = path.with_suffix(".pt.tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def _check(cfg: TrainConfig) -> None:
    if cfg.coarse_weight < 0:
        raise TrainError(f"coarse_weight must be >= 0, got {cfg.coarse_weight}")
    if cfg.basin_weight < 0 or cfg.basin_radius < 0:
        raise TrainError(f"basin weight and radius must be >= 0, got {cfg.basin_weight}, {cfg.basin_radius}")
    if not 0.0 <= cfg.scene_share <= 1.0:
        raise TrainError(f"scene_share must be in [0, 1], got {cfg.scene_share}")
    if cfg.batch < 1:
        raise TrainError(f"batch must be >= 1, got {cfg.batch}")
    if cfg.workers < 0 or cfg.checkpoint_every < 0:
        raise TrainError(
            f"workers and checkpoint_every must be >= 0, got {cfg.workers}, {cfg.checkpoint_every}"
        )
    if cfg.steps is not None and cfg.steps < 0:
        raise TrainError(f"steps must be >= 0, got {cfg.steps}")
    resolve_dtype(cfg.dtype)


def train(
    cfg: TrainConfig,
    progress: bool = True,
    data: TrainData | None = None,
    on_step: Callable[[int, float, Encoder], None] | None = None,
) -> TrainResult:
    """Train an encoder; in a distributed run every rank calls this, rank 0 alone writes the run folder.

    Args:
        cfg: run settings.
        progress: show a progress bar (only on a terminal).
        data: the data to train on; None = :func:`make_data` of ``cfg``.
        on_step: called on every rank after every step with (step, loss averaged over ranks, model).

    Returns:
        the trained model (final weights, no selection on validation data) and the run's records.

    Raises:
        TrainError: bad settings, unreadable data, or a checkpoint that does not fit the run.
    """
    _check(cfg)
    device = resolve_device(cfg.device)
    world = init_distributed(device)
    torch.manual_seed(cfg.seed)
    if device.type == "cpu":
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    if world.main:
        out.mkdir(parents=True, exist_ok=True)
    data = data or make_data(cfg)
    stream = PairStream(data.source, cfg.pair, cfg.seed)
    model = Encoder(cfg.spec).to(device)
    if cfg.init is not None and not cfg.resume:
        load_checkpoint(model, cfg.init)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    losses: list[float] = []
    val_steps: list[int] = []
    val_within: list[float] = []
    step = 0
    if cfg.resume:
        ckpt = load_checkpoint(model, out / "encoder.pt")
        if "optimizer" not in ckpt:
            raise TrainError(f"{out / 'encoder.pt'} holds weights only (no optimiser state): use --init")
        run = (ckpt.get("seed"), ckpt.get("global_batch"))
        if run != (cfg.seed, cfg.batch * world.size):
            raise TrainError(
                f"{out / 'encoder.pt'} was trained with seed, global batch {run}; this run has "
                f"{(cfg.seed, cfg.batch * world.size)}: the pair order would differ"
            )
        opt.load_state_dict(ckpt["optimizer"])
        step = int(ckpt["step"])
        losses = list(ckpt["losses"])
        val_steps, val_within = list(ckpt["val_steps"]), list(ckpt["val_within"])
        torch.set_rng_state(ckpt["torch_rng"])
    net: torch.nn.Module = model
    if world.size > 1:
        ids = [device] if device.type == "cuda" else None
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=ids)
    teacher = None
    if cfg.teacher is not None:  # a narrower student's components are fitted on the training photos
        fit = [load_image(name) for name in cfg.images]
        teacher = Teacher(cfg.teacher, cfg.spec.d, cfg.spec.in_channels, fit)
    # One level from 5 px needs the longer limit; the residual is the training solver's.
    val_lm = LMConfig(levels=1, max_iterations=30, zero_mean=cfg.lm.zero_mean)
    val_sets: dict[str, list[Pair]] = {}
    baseline: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    log = steplog = None
    if world.main and cfg.val_every > 0:
        val_sets = {
            "perturbed": heldout_pairs(cfg.val_per_image, strength=1.0, seed=7),
            "clean": heldout_pairs(cfg.val_per_image, strength=0.0, seed=7),
        }
        for name, src in data.validation.items():
            val_sets[name] = _validation_pairs(src, cfg.pair, 3 * cfg.val_per_image)
        baseline = {k: validate(None, v, val_lm) for k, v in val_sets.items()}
    if world.main:
        log = (out / "log.jsonl").open("a" if cfg.resume else "w")
        steplog = StepLog(out, resume=cfg.resume, first=step, tensorboard=cfg.tensorboard)
        record = run_record(
            command=cfg.command,
            data=data.describe(),
            device=str(device),
            world_size=world.size,
            config={k: str(v) for k, v in asdict(cfg).items()},
        )
        if cfg.tensorboard and steplog.tensorboard is None:
            record["tensorboard"] = TENSORBOARD_HINT
        if cfg.resume and (out / "run.json").is_file():
            record["resumed_from"] = json.loads((out / "run.json").read_text())
        (out / "run.json").write_text(json.dumps(record, indent=1))
    first = step
    start = time.monotonic()
    deadline = start + 60.0 * cfg.minutes
    bar = Progress(progress and world.main, step, cfg.steps, deadline)

    def checkpoint() -> None:
        _save(
            out / "encoder.pt",
            {
                "spec": cfg.spec.as_dict(),
                "state": model.state_dict(),
                "step": step,
                "optimizer": opt.state_dict(),
                "losses": losses,
                "val_steps": val_steps,
                "val_within": val_within,
                "torch_rng": torch.get_rng_state(),
                "seed": cfg.seed,
                "global_batch": cfg.batch * world.size,
            },
        )

    def run_validation() -> None:
        assert log is not None and steplog is not None
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
        steplog.scalars(step, {k: float(v) for k, v in record.items() if k not in ("step", "seconds")})
        bar.note(
            val1px=f"{record['perturbed_within1']:.3f}", cls=f"{record['perturbed_classical_within1']:.3f}"
        )

    if world.main and cfg.val_every > 0 and not cfg.resume:
        run_validation()
    model.train()
    batches = _batches(stream, step, cfg, world)
    while cfg.steps is None or step < cfg.steps:
        if broadcast_flag(time.monotonic() >= deadline, world):
            break
        pairs = next(batches)
        loss, used = batch_loss(net, pairs, cfg, teacher)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        value = all_mean(float(loss.detach()), world)
        step += 1
        losses.append(value)
        if on_step is not None:
            on_step(step, value, model)
        if world.main:
            assert steplog is not None
            steplog.step(step, time.monotonic() - start, value, len(pairs) * world.size, used)
            bar.update(float(np.mean(losses[-100:])))
            if cfg.val_every > 0 and step % cfg.val_every == 0:
                run_validation()
            if (cfg.checkpoint_every and step % cfg.checkpoint_every == 0) or (
                cfg.val_every > 0 and step % cfg.val_every == 0
            ):
                checkpoint()
                steplog.flush()
    seconds = time.monotonic() - start
    bar.close()
    files = {"checkpoint": out / "encoder.pt", "log": out / "log.jsonl", "csv": out / "train.csv"}
    if world.main:
        assert log is not None and steplog is not None
        if cfg.val_every > 0 and (not val_steps or val_steps[-1] != step):
            run_validation()
        log.close()
        steplog.close()
        checkpoint()
        np.save(out / "losses.npy", np.asarray(losses))
        files["loss_png"] = plot_loss(losses, val_steps, val_within, out / "loss.png")
        if val_steps:
            files["val_png"] = out / f"val_epoch{len(val_steps) - 1:02d}.png"
        meta = json.loads((out / "run.json").read_text())
        meta.update(steps=step, seconds=seconds, steps_per_second=(step - first) / max(seconds, 1e-9))
        (out / "run.json").write_text(json.dumps(meta, indent=1))
    return TrainResult(model.eval(), losses, val_steps, val_within, step, seconds, files)
