"""APE statistics, RPE, the evaluate pipeline, and agreement with evo (the field's reference tool)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from nsflow_ros.ate import (
    STAT_KEYS,
    ATEError,
    Trajectory,
    error_statistics,
    evaluate_ape,
    position_errors,
    read_trajectory,
    relative_pose_error,
    rpe_errors,
    write_trajectory,
)

STATS = ("rmse", "mean", "median", "std", "min", "max")


def test_statistics_of_a_known_vector():
    s = error_statistics(np.array([3.0, 4.0, 0.0, 1.0]))
    assert s.rmse == pytest.approx(np.sqrt(26 / 4))
    assert s.mean == pytest.approx(2.0)
    assert s.median == pytest.approx(2.0)
    assert s.std == pytest.approx(np.sqrt(2.5))  # population std (ddof 0)
    assert (s.min, s.max, s.n) == (0.0, 4.0, 4)
    assert tuple(s.as_dict()) == STAT_KEYS


def test_statistics_guards():
    with pytest.raises(ATEError, match="0 poses"):
        error_statistics(np.zeros(0))
    with pytest.raises(ATEError, match=r"NaN or inf .* index 1"):
        error_statistics(np.array([0.0, np.nan]))
    with pytest.raises(ATEError, match=r"shape \(N,\)"):
        error_statistics(np.zeros((2, 2)))


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_transformed_copy_scores_zero(gt, rot, align):
    scale = 1.0 if align == "se3" else 0.25
    est = gt.transformed(rot([1, -1, 2], 1.3), np.array([5.0, 6.0, -7.0]), scale).renamed("est")
    result = evaluate_ape(gt, est, align=align)
    assert result.stats.n == len(gt)
    assert result.stats.rmse < 1e-9 and result.stats.max < 1e-9
    assert result.alignment.scale == pytest.approx(1 / scale)
    # Without alignment the error is the offset between the frames.
    assert evaluate_ape(gt, est, align="none").stats.min > 1.0


def test_known_constant_offset_without_alignment(gt):
    est = Trajectory(gt.stamps, gt.positions + np.array([0.3, 0.4, 0.0]), gt.quaternions, "est")
    s = evaluate_ape(gt, est, align="none").stats
    for key in STATS:
        assert getattr(s, key) == pytest.approx(0.5 if key != "std" else 0.0, abs=1e-12)
    np.testing.assert_allclose(position_errors(gt, est), 0.5)


def test_skip_leaves_out_the_estimators_start(gt):
    # The first second 1 m off: it carries the whole error until skipped.
    start = gt.stamps < gt.stamps[0] + 1.0
    est = Trajectory(gt.stamps, gt.positions + np.where(start[:, None], [1.0, 0.0, 0.0], 0.0), gt.quaternions)
    assert evaluate_ape(gt, est, align="none").stats.max == pytest.approx(1.0)
    skipped = evaluate_ape(gt, est, align="none", skip=1.0)
    assert skipped.stats.max == pytest.approx(0.0, abs=1e-12)
    assert skipped.stats.n == len(gt) - start.sum()
    assert evaluate_ape(gt, est, align="none", skip=0.5).stats.n == len(gt) - start.sum() // 2
    for bad in (-1.0, float("nan")):
        with pytest.raises(ATEError, match=f"skip must be .* got {bad}"):
            evaluate_ape(gt, est, skip=bad)


def test_fewer_than_three_matches(gt):
    est = gt.take([0, 1]).renamed("short")
    pattern = r"only 2 matched poses between gt and short \(need at least 3"
    with pytest.raises(ATEError, match=pattern) as info:
        evaluate_ape(gt, est)
    assert info.value.reason == "too_few"
    with pytest.raises(ATEError, match="need at least 10"):
        evaluate_ape(gt, gt.take(range(5)), min_matches=10)
    with pytest.raises(ATEError, match="same number of poses"):
        position_errors(gt, est)


def test_rpe_sanity(gt, rot):
    # A rigid transform of the whole trajectory leaves every relative motion unchanged.
    moved = gt.transformed(rot([0, 1, 0], 0.7), np.array([1.0, 2.0, 3.0]))
    trans, angle = rpe_errors(gt, moved, delta=5)
    assert trans.shape == (119,) and np.max(trans) < 1e-9 and np.max(angle) < 1e-6
    # A step of d metres between poses 300 and 301 shows in exactly one consecutive pair.
    step = gt.positions.copy()
    step[301:] += [0.0, 0.2, 0.0]
    jumped = Trajectory(gt.stamps, step, gt.quaternions, "jump")
    trans, _ = rpe_errors(gt, jumped, delta=1)
    assert np.count_nonzero(trans > 1e-9) == 1
    assert trans.max() == pytest.approx(0.2)
    res = relative_pose_error(gt, jumped, delta=1, all_pairs=True)
    assert res.translation.n == 599 and res.as_dict()["translation"]["max"] == pytest.approx(0.2)
    # All pairs with delta 10 give N - 10 pairs; consecutive pairs give floor((N - 1) / 10).
    assert relative_pose_error(gt, jumped, delta=10, all_pairs=True).translation.n == 590
    assert relative_pose_error(gt, jumped, delta=10).translation.n == 59


def test_rpe_guards(gt):
    with pytest.raises(ATEError, match="integer >= 1"):
        rpe_errors(gt, gt, delta=0)
    with pytest.raises(ATEError, match="needs more than 600"):
        rpe_errors(gt, gt, delta=600)
    result = evaluate_ape(gt, gt, rpe_delta=2)
    assert result.rpe is not None and result.rpe.translation.max < 1e-12


# ---------------------------------------------------------------------------------------------------------
# Agreement with evo on the same files. evo is a test dependency only.


def _noisy_estimate(gt: Trajectory, rot, aaq, *, every: int, jitter: float, seed: int) -> Trajectory:
    """A drifting, noisy, Sim(3)-transformed estimate sampled every ``every`` ground-truth poses."""
    rng = np.random.default_rng(seed)
    idx = np.arange(3, len(gt) - 3, every)
    stamps = gt.stamps[idx] + rng.uniform(-jitter, jitter, idx.size)
    drift = np.cumsum(rng.normal(0, 0.01, (idx.size, 3)), axis=0)
    pos = gt.positions[idx] + drift + rng.normal(0, 0.02, (idx.size, 3))
    wobble = np.stack([aaq(rng.normal(size=3), rng.normal(0, 0.02)) for _ in idx])
    quats = np.stack([_hamilton(q, w) for q, w in zip(gt.quaternions[idx], wobble, strict=True)])
    noisy = Trajectory(stamps, pos, quats, "est")
    return noisy.transformed(rot([0.2, 0.9, -0.4], 2.4), np.array([4.0, -1.0, 0.7]), 0.6)


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _evo_stats(gt_path, est_path, est_format, align, n_align=None, offset=0.0, rpe_delta=None):
    evo_sync = pytest.importorskip("evo.core.sync")
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    ref = file_interface.read_euroc_csv_trajectory(str(gt_path))
    if est_format == "tum":
        est = file_interface.read_tum_trajectory_file(str(est_path))
    else:  # evo has no VINS reader (trailing comma): parse the same file independently.
        raw = np.loadtxt(est_path, delimiter=",", usecols=range(8))
        est = PoseTrajectory3D(raw[:, 1:4], raw[:, 4:8], raw[:, 0] / 1e9)
    ref, est = evo_sync.associate_trajectories(ref, est, max_diff=0.01, offset_2=offset)
    est = copy.deepcopy(est)
    if align != "none":
        est.align(ref, correct_scale=align == "sim3", n=-1 if n_align is None else n_align)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    out = {"ape": ape.get_all_statistics(), "n": ref.num_poses}
    if rpe_delta is not None:
        for key, relation in (
            ("rpe_t", evo_metrics.PoseRelation.translation_part),
            ("rpe_r", evo_metrics.PoseRelation.rotation_angle_deg),
        ):
            rpe = evo_metrics.RPE(relation, delta=rpe_delta, delta_unit=evo_metrics.Unit.frames)
            rpe.process_data((ref, est))
            out[key] = rpe.get_all_statistics()
    return out


def _assert_agree(ours, theirs):
    for key in STATS:
        assert abs(getattr(ours, key) - theirs[key]) <= 1e-6, key


@pytest.fixture(scope="module")
def files(tmp_path_factory, rot, aaq):
    """Ground truth (EuRoC, 200 Hz) and an estimate (20 Hz) written as TUM and as VINS csv."""
    here = tmp_path_factory.mktemp("evo")
    t = 1403636579.0 + np.arange(3000) / 200.0
    s = t - t[0]
    pos = np.stack([3 * np.sin(0.3 * s), 2 * np.sin(0.45 * s + 0.5), 1 + 0.5 * np.sin(0.2 * s)], axis=1)
    half = 0.2 * s
    quats = np.stack([np.cos(half), 0.1 * np.sin(half), 0.2 * np.sin(half), np.sin(half)], axis=1)
    gt = Trajectory(t, pos, quats, "gt")
    est = _noisy_estimate(gt, rot, aaq, every=10, jitter=0.004, seed=1)
    dense = _noisy_estimate(gt.take(range(0, 3000, 20)), rot, aaq, every=1, jitter=0.0, seed=2)
    return {
        "gt": write_trajectory(gt, here / "gt.csv", "euroc"),
        "tum": write_trajectory(est, here / "est.tum", "tum"),
        "vins": write_trajectory(est, here / "vio.csv", "vins"),
        "sparse_gt": write_trajectory(gt.take(range(0, 3000, 40)), here / "sparse_gt.csv", "euroc"),
        "dense": write_trajectory(dense, here / "dense.tum", "tum"),
    }


@pytest.mark.parametrize("est_format", ["tum", "vins"])
@pytest.mark.parametrize("align", ["se3", "sim3", "none"])
def test_agrees_with_evo(files, est_format, align):
    theirs = _evo_stats(files["gt"], files[est_format], est_format, align)
    ours = evaluate_ape(read_trajectory(files["gt"]), read_trajectory(files[est_format]), align=align)
    assert ours.stats.n == theirs["n"] > 250
    _assert_agree(ours.stats, theirs["ape"])


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_agrees_with_evo_first_n_offset_and_rpe(files, align):
    theirs = _evo_stats(files["gt"], files["tum"], "tum", align, n_align=50, offset=0.003, rpe_delta=7)
    ours = evaluate_ape(
        read_trajectory(files["gt"]),
        read_trajectory(files["tum"]),
        align=align,
        n_align=50,
        offset=0.003,
        rpe_delta=7,
    )
    assert ours.stats.n == theirs["n"]
    _assert_agree(ours.stats, theirs["ape"])
    assert ours.rpe is not None
    _assert_agree(ours.rpe.translation, theirs["rpe_t"])
    _assert_agree(ours.rpe.rotation_deg, theirs["rpe_r"])


@pytest.mark.parametrize("align", ["se3", "sim3", "none"])
def test_agrees_with_evo_when_the_estimate_is_denser(files, align):
    # The ground truth is the shorter trajectory here: the association starts from it.
    theirs = _evo_stats(files["sparse_gt"], files["dense"], "tum", align)
    ours = evaluate_ape(read_trajectory(files["sparse_gt"]), read_trajectory(files["dense"]), align=align)
    assert ours.stats.n == theirs["n"]
    _assert_agree(ours.stats, theirs["ape"])
