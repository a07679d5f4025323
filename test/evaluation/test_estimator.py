"""The VINS-Fusion runner: the estimator's config copy, locating a build, and the whole subprocess
orchestration (private master, node, play, settle, stop, errors) against fake ``rosmaster`` /
``vins_node`` / ``rosbag`` programs that this test writes, so it runs without a ROS 1 build."""

from __future__ import annotations

import ast
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from vins_fakes import fake_build

from nsflow_ros.ate import Trajectory, write_trajectory
from nsflow_ros.ate.cli import main as ate_main
from nsflow_ros.evaluation import estimator
from nsflow_ros.evaluation.errors import EstimatorError, EvaluationError
from nsflow_ros.evaluation.estimator import (
    IDLE_IMAGE_TOPICS,
    RUN_RECORD,
    VinsBuild,
    estimator_config,
    run_vins,
    score_vio,
)

REPO = Path(__file__).resolve().parents[2]
STEREO = REPO / "config" / "euroc" / "euroc_stereo_imu_config.yaml"

# ---- the fakes: test/vins_fakes.py ----


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    path = tmp_path / "features.bag"
    path.write_bytes(b"#ROSBAG V2.0\n")
    return path


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a zombie still answers; its parent (the test) reaped it through Popen.wait, so this is a live one
    return False


# ---- the config copy ----


def test_config_copy_idles_the_image_topics_and_points_output_into_the_run(tmp_path: Path):
    out = tmp_path / "run"
    copy = estimator_config(STEREO, out)
    assert copy == out.resolve() / "euroc_stereo_imu_config_estimator.yaml"
    text = copy.read_text()
    assert text.startswith("%YAML:1.0\n")
    assert f'image0_topic: "{IDLE_IMAGE_TOPICS[0]}"' in text
    assert f'image1_topic: "{IDLE_IMAGE_TOPICS[1]}"' in text
    assert f'output_path: "{out.resolve()}/"' in text
    assert "/cam0/image_raw" not in text and '/tmp/vins_output/"' not in text
    # everything else is the original, line for line
    orig = STEREO.read_text().splitlines()
    new = text.splitlines()
    assert len(orig) == len(new)
    changed = [o for o, n in zip(orig, new, strict=True) if o != n]
    assert [c.split(":")[0] for c in changed] == ["image0_topic", "image1_topic", "output_path"]
    assert 'imu_topic: "/imu0"' in text
    # the camera files the estimator opens relative to the config are beside the copy
    for cam in ("cam0_pinhole.yaml", "cam1_pinhole.yaml"):
        assert (out / cam).read_bytes() == (STEREO.parent / cam).read_bytes()


def test_config_copy_names_a_missing_key_or_camera_file(tmp_path: Path):
    cfg = tmp_path / "cfg" / "c.yaml"
    cfg.parent.mkdir()
    cfg.write_text('%YAML:1.0\nnum_of_cam: 1\nimage0_topic: "/a"\ncam0_calib: "c0.yaml"\n')
    with pytest.raises(EstimatorError, match="no output_path"):
        estimator_config(cfg, tmp_path / "out")
    cfg.write_text('%YAML:1.0\nnum_of_cam: 1\nimage0_topic: "/a"\noutput_path: "/x/"\ncam0_calib: c0.yaml\n')
    with pytest.raises(EstimatorError, match=r"cam0_calib names .*c0\.yaml, which does not exist"):
        estimator_config(cfg, tmp_path / "out")
    cfg.write_text('%YAML:1.0\nnum_of_cam: 2\nimage0_topic: "/a"\noutput_path: "/x/"\n')
    with pytest.raises(EstimatorError, match="no image1_topic"):
        estimator_config(cfg, tmp_path / "out")
    with pytest.raises(EstimatorError, match="cannot read the VINS config"):
        estimator_config(tmp_path / "nope.yaml", tmp_path / "out")


def test_config_copy_can_lift_the_solver_budget(tmp_path: Path):
    copy = estimator_config(STEREO, tmp_path / "run", solver_time=1.0)
    changed = [n for o, n in zip(STEREO.read_text().splitlines(), copy.read_text().splitlines(), strict=True)
               if o != n]
    assert [c.split(":")[0] for c in changed] == ["image0_topic", "image1_topic", "output_path",
                                                  "max_solver_time"]
    assert "max_solver_time: 1   #" in copy.read_text()
    with pytest.raises(EstimatorError, match="solver_time must be > 0"):
        estimator_config(STEREO, tmp_path / "run2", solver_time=0.0)
    cfg = tmp_path / "c.yaml"
    cfg.write_text('%YAML:1.0\nnum_of_cam: 1\nimage0_topic: "/a"\noutput_path: "/x/"\ncam0_calib: c0.yaml\n')
    with pytest.raises(EstimatorError, match="no max_solver_time"):
        estimator_config(cfg, tmp_path / "run3", solver_time=1.0)


# ---- locating the build ----


def test_locate_names_what_is_missing(tmp_path: Path):
    with pytest.raises(EstimatorError, match=r"does not exist; build it with: scripts/build_vins_fusion\.sh"):
        VinsBuild.locate(tmp_path / "nothing")
    ws = tmp_path / "ws"
    ws.mkdir()
    with pytest.raises(EstimatorError, match=r"devel/setup\.bash .*devel/lib/vins/vins_node") as info:
        VinsBuild.locate(ws)
    assert isinstance(info.value, EvaluationError)
    (ws / "devel" / "lib" / "vins").mkdir(parents=True)
    (ws / "devel" / "setup.bash").write_text("")
    node = ws / "devel" / "lib" / "vins" / "vins_node"
    node.write_text("")
    node.chmod(0o644)
    with pytest.raises(EstimatorError, match="executable bit"):
        VinsBuild.locate(ws)
    node.chmod(0o755)
    build = VinsBuild.locate(ws)
    assert build.vins_node == node.resolve() and build.setup == (ws / "devel" / "setup.bash").resolve()


def test_locate_defaults_to_the_environment_variable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("NSFLOW_VINS_WS", str(tmp_path / "from_env"))
    with pytest.raises(EstimatorError, match="from_env"):
        VinsBuild.locate()


# ---- the orchestration, against the fakes ----


def test_a_run_starts_master_node_and_play_then_stops_them_and_returns_vio(tmp_path: Path, bag: Path):
    vins = fake_build(tmp_path)
    out = tmp_path / "run"
    vio = run_vins(bag, STEREO, vins, out, timeout_s=20, settle_s=0.1)
    assert vio == out.resolve() / "vio.csv"
    assert len(vio.read_text().splitlines()) >= 1
    node = json.loads((out / "node.json").read_text())
    assert node["argv"][1] == str(out.resolve() / "euroc_stereo_imu_config_estimator.yaml")
    assert node["values"]["image0_topic"] == IDLE_IMAGE_TOPICS[0]
    assert node["master"].startswith("http://127.0.0.1:") and node["master"] != "http://127.0.0.1:11311/"
    assert node["path_has_fakes"].endswith("fake_bin")  # the workspace's setup.bash was sourced
    assert json.loads((out / "rosbag.json").read_text()) == ["play", "-q", "-d", "1", str(bag.resolve())]
    record = json.loads((out / RUN_RECORD).read_text())
    assert record["master_uri"] == node["master"] and record["poses"] >= 1 and record["wall_s"] > 0
    assert _gone(node["pid"])


def test_two_runs_at_once_each_have_their_own_master(tmp_path: Path, bag: Path):
    vins = fake_build(tmp_path)
    outs = [tmp_path / "run_a", tmp_path / "run_b"]
    with ThreadPoolExecutor(2) as pool:
        vios = list(pool.map(lambda out: run_vins(bag, STEREO, vins, out, timeout_s=20, settle_s=0.1), outs))
    assert [v.parent for v in vios] == [o.resolve() for o in outs]
    masters = {json.loads((out / "node.json").read_text())["master"] for out in outs}
    assert len(masters) == 2


def test_a_node_that_ignores_sigint_is_killed(tmp_path: Path, bag: Path):
    vins = fake_build(tmp_path, node="ignore_sigint")
    out = tmp_path / "run"
    run_vins(bag, STEREO, vins, out, timeout_s=20, settle_s=0.1, stop_timeout_s=0.2)
    record = json.loads((out / RUN_RECORD).read_text())
    assert record["exit_status_after_stop"]["vins_node"] == -9
    assert _gone(json.loads((out / "node.json").read_text())["pid"])


@pytest.mark.parametrize(
    ("node", "bag_mode", "message"),
    [
        ("die", "ok", r"vins_node exited with status 3 during the play(.|\n)*segmentation fault"),
        ("crash_at_start", "ok", r"vins_node exited with status 1 before it subscribed(.|\n)*cannot parse"),
        ("no_output", "ok", r"vins_node wrote no pose to .*vio\.csv"),
        ("ok", "fail", r"rosbag_play exited with status 1 playing(.|\n)*bag unindexed"),
    ],
)
def test_failures_name_the_process_and_quote_its_log(
    tmp_path: Path, bag: Path, node: str, bag_mode: str, message: str
):
    vins = fake_build(tmp_path, node=node, bag=bag_mode)
    out = tmp_path / "run"
    with pytest.raises(EstimatorError, match=message):
        run_vins(bag, STEREO, vins, out, timeout_s=20, settle_s=0.1)
    assert not (out / RUN_RECORD).exists()
    if (out / "node.json").exists():
        assert _gone(json.loads((out / "node.json").read_text())["pid"])


@pytest.mark.parametrize(
    ("node", "bag_mode", "message"),
    [("ok", "slow", "the play had not ended"), ("endless", "ok", "still writing .*vio.csv")],
)
def test_a_run_over_its_time_limit_is_stopped_and_cleaned_up(
    tmp_path: Path, bag: Path, node: str, bag_mode: str, message: str
):
    vins = fake_build(tmp_path, node=node, bag=bag_mode)
    out = tmp_path / "run"
    with pytest.raises(EstimatorError, match="longer than timeout_s=1 s .*" + message):
        run_vins(bag, STEREO, vins, out, timeout_s=1, settle_s=0.1)
    assert _gone(json.loads((out / "node.json").read_text())["pid"])


def test_a_missing_bag_is_refused_before_anything_starts(tmp_path: Path):
    vins = fake_build(tmp_path)
    with pytest.raises(EstimatorError, match=r"feature bag .*nope\.bag does not exist"):
        run_vins(tmp_path / "nope.bag", STEREO, vins, tmp_path / "run", timeout_s=5)
    assert not (tmp_path / "run").exists()


# ---- scoring ----


def test_score_vio_is_what_nsflow_ate_align_se3_prints(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    rng = np.random.default_rng(0)
    t = np.arange(50) * 0.05 + 1.0
    pos = np.stack([np.sin(t), np.cos(2 * t), 0.1 * t], axis=1)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (50, 1))
    gt = write_trajectory(Trajectory(t, pos, quat, "gt"), tmp_path / "groundtruth.csv", "euroc")
    # the estimate: rotated and shifted (the SE3 alignment removes that) plus ~3 mm of noise
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    est_pos = (pos + rng.normal(0, 0.003, pos.shape)) @ rot.T + [1.0, 2.0, 3.0]
    vio = write_trajectory(Trajectory(t, est_pos, quat, "vio"), tmp_path / "run" / "vio.csv", "vins")
    result = score_vio(vio, gt)
    assert result.alignment.method == "se3" and result.stats.n == 50
    assert 0.002 < result.stats.rmse < 0.005
    assert ate_main([str(gt), str(vio), "--align", "se3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rmse"] == pytest.approx(result.stats.rmse, rel=1e-12)


def test_the_runner_imports_no_ros():
    """Its own imports: the standard library and the project's pure ATE code (checked without importing)."""
    tree = ast.parse(Path(estimator.__file__).read_text())
    mods = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    mods |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    project = {m for m in mods if m.startswith("nsflow_ros")}
    assert project == {"nsflow_ros.ate", "nsflow_ros.evaluation.errors"}
    assert {m.split(".")[0] for m in mods - project} <= set(sys.stdlib_module_names)
