"""Tests of the device and dtype choice (nsflow_ros.train.device) and float32 vs float64 solves."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros.train.data import PairConfig, load_image, make_pair  # noqa: E402
from nsflow_ros.train.device import resolve_device, resolve_dtype  # noqa: E402
from nsflow_ros.train.errors import TrainError  # noqa: E402
from nsflow_ros.train.lk_layer import lk_track  # noqa: E402
from nsflow_ros.train.model import Encoder, EncoderSpec  # noqa: E402
from nsflow_ros.train.trainer import TrainConfig, batch_loss, encode_pair  # noqa: E402


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        assert resolve_device("auto") == torch.device("cpu")
        with pytest.raises(TrainError, match="sees no GPU"):
            resolve_device("cuda:0")
        with pytest.raises(TrainError, match="sees no GPU"):
            resolve_device("cuda")
    for bad in ("gpu", "cuda:x", "tpu:0"):
        with pytest.raises(TrainError, match="device must be auto, cpu, cuda or cuda:K"):
            resolve_device(bad)
    assert resolve_dtype("float64") is torch.float64
    with pytest.raises(TrainError, match="dtype must be one of"):
        resolve_dtype("float16")


def test_float32_and_float64_maps_agree_on_a_solve(textures32):
    """The LK layer on float32 maps (GPU training) lands where it lands on float64 maps (the CPU
    reference): same statuses, median difference < 1e-4 px, 95 % < 1e-3 px, every point < 1e-2 px
    (measured on this pair: 5e-6, 2e-5 and 7e-4 px)."""
    img1, img2, pts, flow0 = textures32
    cfg = TrainConfig().lm
    d1 = torch.from_numpy(img1)[None]
    d2 = torch.from_numpy(img2.astype(np.float32))[None]
    out = {
        dt: lk_track(d1.to(dt), d2.to(dt), torch.from_numpy(pts), torch.from_numpy(flow0), cfg)
        for dt in (torch.float32, torch.float64)
    }
    a, b = out[torch.float32], out[torch.float64]
    assert torch.equal(a.status, b.status) and float(a.status.float().mean()) > 0.8
    diff = (a.flow - b.flow).norm(dim=1)[a.status].numpy()
    assert np.median(diff) < 1e-4 and np.percentile(diff, 95) < 1e-3 and diff.max() < 1e-2


def test_float32_and_float64_training_losses_agree():
    pair = make_pair(load_image("astronaut"), np.random.default_rng(1), PairConfig(128, 96, max_points=40))
    torch.manual_seed(0)
    model = Encoder(EncoderSpec(d=2))
    values = {}
    for dtype in ("float32", "float64"):
        loss, used = batch_loss(model, [pair], TrainConfig(dtype=dtype))
        assert used > 10
        values[dtype] = float(loss.detach())
    assert values["float32"] == pytest.approx(values["float64"], rel=1e-3)
    d1, _ = encode_pair(model, pair)
    assert d1.dtype is torch.float32  # the encoder itself always runs in float32


def test_a_batch_loss_is_the_mean_of_its_pairs():
    cfg = PairConfig(128, 96, max_points=40)
    pairs = [make_pair(load_image(n), np.random.default_rng(2), cfg) for n in ("astronaut", "camera")]
    torch.manual_seed(0)
    model = Encoder(EncoderSpec(d=2))
    one = [float(batch_loss(model, [p], TrainConfig())[0].detach()) for p in pairs]
    both, used = batch_loss(model, pairs, TrainConfig())
    assert float(both.detach()) == pytest.approx(np.mean(one), rel=1e-5)
    assert used == sum(int(batch_loss(model, [p], TrainConfig())[1]) for p in pairs)
