"""Tests of the training data, the loss and the encoder module."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nsflow_ros.train import TrainError  # noqa: E402
from nsflow_ros.train.data import (  # noqa: E402
    HELDOUT_IMAGES,
    TRAIN_IMAGES,
    PairConfig,
    load_image,
    make_pair,
    perturb_frames,
)
from nsflow_ros.train.loss import flow_loss  # noqa: E402
from nsflow_ros.train.model import Encoder, EncoderSpec, count_flops  # noqa: E402


def test_heldout_images_are_disjoint_from_training_images():
    assert not set(HELDOUT_IMAGES) & set(TRAIN_IMAGES)
    for name in HELDOUT_IMAGES:
        assert load_image(name).ndim == 2


def test_ground_truth_flow_is_exact():
    cfg = PairConfig()
    pair = make_pair(load_image("astronaut"), np.random.default_rng(3), cfg, strength=0.0)
    assert len(pair.points) > 50
    # frame2 sampled at x + u_gt must reproduce frame1 at x (up to interpolation of the render).
    f1 = pair.image1.astype(np.float32)
    f2 = pair.image2.astype(np.float32)
    tgt = (pair.points + pair.flow_gt).astype(np.float32)
    a = cv2.remap(
        f1, pair.points[:, :1].astype(np.float32), pair.points[:, 1:].astype(np.float32), cv2.INTER_LINEAR
    )
    b = cv2.remap(f2, tgt[:, :1], tgt[:, 1:], cv2.INTER_LINEAR)
    assert np.median(np.abs(a - b)) < 4.0
    shifted = cv2.remap(f2, tgt[:, :1] + 3, tgt[:, 1:], cv2.INTER_LINEAR)
    assert np.median(np.abs(a - shifted)) > 2 * np.median(np.abs(a - b))
    r = cfg.window // 2
    for q in (pair.points, pair.points + pair.flow_gt):
        assert (
            (q >= r).all() and (q[:, 0] <= cfg.width - 1 - r).all() and (q[:, 1] <= cfg.height - 1 - r).all()
        )


def test_initial_error_has_the_requested_length():
    pair = make_pair(load_image("coffee"), np.random.default_rng(0), strength=1.0, init_error=5.0)
    np.testing.assert_allclose(np.linalg.norm(pair.flow0 - pair.flow_gt, axis=1), 5.0)


def test_training_initial_flow_modes():
    src, rng = load_image("astronaut"), np.random.default_rng(2)
    pair = make_pair(src, rng, PairConfig(init_mode="uniform", init_sigma=30.0), strength=0.0)
    err = np.linalg.norm(pair.flow0 - pair.flow_gt, axis=1)
    assert len(err) > 50 and err.max() <= 30.0 and err.min() < 5.0 and np.mean(err > 15.0) > 0.3
    pair = make_pair(src, rng, PairConfig(init_mode="zero", translation=20.0), strength=0.0)
    assert np.array_equal(pair.flow0, np.zeros_like(pair.flow_gt)) and np.abs(pair.flow_gt).max() > 1.0
    # The default stays the shipped model's: GT + N(0, 2.5^2) per axis.
    pair = make_pair(src, np.random.default_rng(4), PairConfig(), strength=0.0)
    assert 2.0 < np.std(pair.flow0 - pair.flow_gt) < 3.0
    with pytest.raises(TrainError, match="init_mode must be one of"):
        PairConfig(init_mode="gauss")
    with pytest.raises(TrainError, match="init_sigma must be >= 0"):
        PairConfig(init_sigma=-1.0)


def test_perturbation_changes_illumination_but_not_zero_strength():
    img = load_image("camera")[:120, :160]
    rng = np.random.default_rng(0)
    assert all(np.array_equal(f, img) for f in perturb_frames(img, img, rng, 0.0))
    a, b = perturb_frames(img, img, rng, 1.5)  # clipped to the full strength
    for out in (a, b):
        assert out.dtype == np.uint8 and out.shape == img.shape
        assert np.abs(out.astype(float) - img).mean() > 5
    assert not np.array_equal(a, b)  # each frame its own change


def test_loss_masks_invalid_and_non_finite_points():
    flow = torch.tensor(
        [[1.0, 0.0], [float("nan"), 0.0], [10.0, 0.0]], dtype=torch.float64, requires_grad=True
    )
    gt = torch.zeros(3, 2, dtype=torch.float64)
    valid = torch.tensor([True, True, False])
    loss, used = flow_loss(flow, gt, valid, rho="huber")
    assert used == 1 and abs(float(loss.detach()) - 0.5) < 1e-6
    loss.backward()
    assert torch.isfinite(flow.grad).all() and flow.grad[2].abs().sum() == 0
    loss, used = flow_loss(flow, gt, torch.zeros(3, dtype=torch.bool))
    assert used == 0
    with pytest.raises(TrainError, match="rho must be one of"):
        flow_loss(flow.detach(), gt, valid, rho="l2")
    with pytest.raises(TrainError, match=r"valid must have shape \(3,\)"):
        flow_loss(flow.detach(), gt, torch.ones(2, dtype=torch.bool))


def test_encoder_shapes_and_guards():
    model = Encoder(EncoderSpec(d=4))
    out = model(torch.rand(1, 1, 30, 41)).detach()
    assert out.shape == (1, 4, 30, 41) and float(out.min()) > 0 and float(out.max()) < 1
    with pytest.raises(TrainError, match=r"expects \(B, 1, H, W\) input, got \(1, 3, 30, 41\)"):
        model(torch.rand(1, 3, 30, 41))
    with pytest.raises(TrainError, match="head must be one of"):
        EncoderSpec(head="tanh")
    assert count_flops(EncoderSpec(d=4)) == 2 * (9 * 8 + 72 * 8 + 8 * 16 + 16 * 4) * 320 * 240
