"""Sample sequence generator: EuRoC layout, determinism, reuse, atomic output, ground truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from nsflow_ros.data import sample as sample_mod
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.motion import quaternion_to_rotation
from nsflow_ros.data.sample import SampleSequence, is_sample, make_sample_sequence
from nsflow_ros.data.writers import ASL_CAMERA_HEADER, ASL_GROUNDTRUTH_HEADER, ASL_IMU_HEADER

SHORT = {"duration": 0.15, "stereo": False, "formats": ("asl",), "progress": False}


def test_euroc_layout(sample_seq):
    mav0 = sample_seq.asl_dir / "mav0"
    for cam in ("cam0", "cam1"):
        lines = (mav0 / cam / "data.csv").read_text().splitlines()
        assert lines[0] == ASL_CAMERA_HEADER and len(lines) == 11
        stamp, name = lines[1].split(",")
        assert name == f"{stamp}.png" and int(stamp) == sample_seq.t0_ns
        img = cv2.imread(str(mav0 / cam / "data" / name), cv2.IMREAD_UNCHANGED)
        assert img.shape == (480, 752) and img.dtype == np.uint8
        assert "distortion_model: radial-tangential" in (mav0 / cam / "sensor.yaml").read_text()
    imu = (mav0 / "imu0" / "data.csv").read_text().splitlines()
    assert imu[0] == ASL_IMU_HEADER and len(imu) == 102
    assert np.diff([int(x.split(",")[0]) for x in imu[1:]]).tolist() == [5_000_000] * 100
    gt = (mav0 / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    assert gt[0] == ASL_GROUNDTRUTH_HEADER and len(gt) == 102 and len(gt[1].split(",")) == 17
    assert sample_seq.groundtruth_csv.read_text().splitlines() == gt
    assert (sample_seq.ros2_dir / "metadata.yaml").is_file() and sample_seq.ros1_path.is_file()
    assert (sample_seq.root / "done").is_file()
    meta = json.loads((sample_seq.root / "sequence.json").read_text())
    assert meta["topics"]["images"] == ["/cam0/image_raw", "/cam1/image_raw"]
    assert meta["cameras"][0]["distortion"][0] == pytest.approx(-0.28340811)


def test_groundtruth_matches_poses(sample_seq):
    rows = np.loadtxt(sample_seq.asl_dir / "mav0" / "state_groundtruth_estimate0" / "data.csv", delimiter=",")
    T = sample_seq.body_pose(4)
    row = rows[rows[:, 0].astype(np.int64) == sample_seq.stamps_ns[4]][0]
    assert np.allclose(row[1:4], T[:3, 3]) and np.allclose(quaternion_to_rotation(row[4:8])[0], T[:3, :3])
    assert np.allclose(sample_seq.pose(4, 1), T @ sample_seq.cameras[1].T_BS)


def test_stored_images_and_ground_truth_flow(sample_seq):
    assert np.array_equal(sample_seq.image(3, 1), sample_seq.render(3, 1).image)
    u, v = np.meshgrid(np.arange(20.0, 740.0, 8.0), np.arange(20.0, 470.0, 8.0))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    flow, vis = sample_seq.flow(2, 3, pix)
    img2, img3 = sample_seq.image(2).astype(np.float32), sample_seq.image(3).astype(np.float32)
    tgt = (pix + flow)[vis].astype(np.float32)
    warped = cv2.remap(img3, tgt[:, None, 0], tgt[:, None, 1], cv2.INTER_LINEAR)[:, 0]
    src = img2[pix[vis, 1].astype(int), pix[vis, 0].astype(int)]
    assert vis.mean() > 0.8 and np.abs(warped - src).mean() < 2.5  # includes the 1-gray-level image noise
    depth = sample_seq.depth(2)
    assert np.allclose(sample_seq.depth_at(2, pix[:5]), depth[pix[:5, 1].astype(int), pix[:5, 0].astype(int)],
                       rtol=1e-4)
    # Stereo: matches satisfy the epipolar constraint of the cam0 -> cam1 extrinsics exactly.
    stereo, svis = sample_seq.flow(2, 2, pix, cam=0, cam_j=1)
    assert svis.mean() > 0.8
    T = np.linalg.inv(sample_seq.pose(2, 1)) @ sample_seq.pose(2, 0)
    t = T[:3, 3]
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T[:3, :3]
    x0 = np.c_[sample_seq.cameras[0].pixels_to_normalized(pix[svis]), np.ones(svis.sum())]
    x1 = np.c_[sample_seq.cameras[1].pixels_to_normalized(pix[svis] + stereo[svis]), np.ones(svis.sum())]
    assert np.abs(np.einsum("ni,ij,nj->n", x1, E, x0)).max() < 1e-9
    with pytest.raises(DataError, match=r"frame index 10 outside 0\.\.9"):
        sample_seq.flow(0, 10, pix)


def test_identical_parameters_reuse_and_determinism(tmp_path):
    a = make_sample_sequence(tmp_path / "a", seed=9, **SHORT)
    png = sorted((a.asl_dir / "mav0" / "cam0" / "data").iterdir())
    mtime = png[0].stat().st_mtime_ns
    again = make_sample_sequence(tmp_path / "a", seed=9, **SHORT)
    assert again.root == a.root and png[0].stat().st_mtime_ns == mtime  # nothing re-rendered
    b = make_sample_sequence(tmp_path / "b", seed=9, **SHORT)
    for rel in ("asl/mav0/cam0/data.csv", "asl/mav0/imu0/data.csv", "sequence.json", "done",
                f"asl/mav0/cam0/data/{png[1].name}"):
        assert (a.root / rel).read_bytes() == (b.root / rel).read_bytes(), rel
    c = make_sample_sequence(tmp_path / "c", seed=10, **SHORT)
    assert not np.array_equal(c.image(0), a.image(0))


def test_other_parameters_replace_a_sample_but_never_foreign_files(tmp_path):
    root = tmp_path / "seq"
    make_sample_sequence(root, seed=1, **SHORT)
    seq = make_sample_sequence(root, seed=2, **SHORT)
    assert seq.params["seed"] == 2 and SampleSequence.load(root).params["seed"] == 2
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    with pytest.raises(DataError, match="exists and is not a sample sequence"):
        make_sample_sequence(foreign, **SHORT)
    assert (foreign / "thesis.tex").read_text() == "precious"
    make_sample_sequence(foreign, overwrite=True, **SHORT)
    assert not (foreign / "thesis.tex").exists()


def test_an_interrupted_run_leaves_nothing_that_looks_complete(tmp_path, monkeypatch):
    calls = {"n": 0}
    original = sample_mod.AslWriter.write_image

    def failing(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(sample_mod.AslWriter, "write_image", failing)
    with pytest.raises(KeyboardInterrupt):
        make_sample_sequence(tmp_path / "seq", **SHORT)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(sample_mod.AslWriter, "write_image", original)
    with pytest.raises(DataError, match="not a complete sample sequence"):
        SampleSequence.load(tmp_path)


def test_a_flight_at_rest_is_its_own_sample_and_starts_still(tmp_path):
    moving = make_sample_sequence(tmp_path / "moving", seed=3, **SHORT)
    assert "rest" not in moving.params  # the key of a flight without rest is the one it always had
    still = make_sample_sequence(tmp_path / "still", seed=3, rest=0.5, **SHORT)
    assert still.params["rest"] == 0.5 and still.trajectory.rest == 0.5
    assert np.array_equal(still.pose(0), moving.pose(0)) and np.array_equal(still.pose(2), still.pose(0))
    assert np.array_equal(still.image(0), moving.image(0))
    flow, visible = still.flow(0, 2, np.array([[300.0, 200.0]]))
    assert visible.all() and np.abs(flow).max() < 1e-9
    # Reused with the same rest, replaced with another.
    assert make_sample_sequence(tmp_path / "still", seed=3, rest=0.5, **SHORT).params["rest"] == 0.5
    assert "rest" not in make_sample_sequence(tmp_path / "still", seed=3, **SHORT).params


def test_parameter_errors(tmp_path):
    with pytest.raises(DataError, match=r"unknown format.*'hdf5'"):
        make_sample_sequence(tmp_path / "x", formats=("asl", "hdf5"))
    with pytest.raises(DataError, match="must be positive"):
        make_sample_sequence(tmp_path / "x", duration=-1.0)
    with pytest.raises(DataError, match="gives no frame"):
        make_sample_sequence(tmp_path / "x", duration=0.01)
    with pytest.raises(DataError, match=r"rest must be a finite number of seconds >= 0, got -0\.5"):
        make_sample_sequence(tmp_path / "x", rest=-0.5)
    assert not (tmp_path / "x").exists()


def test_is_sample_needs_the_metadata_and_the_completion_mark(sample_seq, tmp_path):
    assert is_sample(sample_seq.root)
    assert not is_sample(tmp_path)
    (tmp_path / "sequence.json").write_text("{}")
    assert not is_sample(tmp_path)  # no completion mark: an interrupted run
