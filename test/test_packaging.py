"""The package installs both ways: pip into a fresh virtual environment, and colcon as a ROS package."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from nsflow_ros.data.sample import make_sample_sequence

ROOT = Path(__file__).resolve().parent.parent
SHORT_NAMES = (
    "tracker", "replay", "demo", "ate", "bench", "make_sample", "train", "evaluate", "config", "scenes",
)
PACKAGE_FILES = (
    "package.xml", "setup.py", "setup.cfg", "resource", "nsflow_ros", "config", "models", "launch", "rviz"
)

CHECK_ENTRY_POINTS = """
import importlib, importlib.metadata as md, json
eps = [e for e in md.distribution("nsflow_ros").entry_points if e.group == "console_scripts"]
bad = []
for e in eps:
    mod, _, attr = e.value.partition(":")
    try:
        ok = callable(getattr(importlib.import_module(mod), attr, None))
    except ImportError as err:
        ok = False
        attr = f"{attr} ({err})"
    if not ok:
        bad.append(f"{mod}:{attr}")
print(json.dumps({"names": sorted(e.name for e in eps), "bad": bad}))
"""


def _copy_package(dest: Path) -> Path:
    pkg = dest / "src" / "nsflow_ros"
    pkg.mkdir(parents=True)
    for name in PACKAGE_FILES:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, pkg / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.exists():
            shutil.copy2(src, pkg / name)
    return pkg


@pytest.mark.slow
def test_pip_install_in_fresh_venv(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    pkg = _copy_package(tmp_path)
    proc = subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(pkg)],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    # run from elsewhere so nothing is imported from the checkout
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH")}
    code = (
        "import rclpy, sensor_msgs.msg, std_msgs.msg, rosgraph_msgs.msg, geometry_msgs.msg, nsflow_ros, sys;"
        "import diagnostic_msgs.msg, rcl_interfaces.msg, ament_index_python, importlib.util;"
        # the extras stay out of the robot install: no evaluation, figure, training or test library
        "extras = ('matplotlib', 'skimage', 'scipy', 'onnx', 'torch', 'evo', 'pytest');"
        "assert [m for m in extras if importlib.util.find_spec(m)] == [], extras;"
        "from nsflow_ros.resources import share_dir;"
        "d = share_dir(); print(d); assert (d / 'config').is_dir(), d;"
        "rclpy.init(); n = rclpy.create_node('pip_check'); n.destroy_node(); rclpy.shutdown()"
    )
    out = subprocess.run([str(py), "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert Path(out.stdout.strip().splitlines()[-1]) == venv / "share" / "nsflow_ros"
    eps = subprocess.run(
        [str(py), "-c", CHECK_ENTRY_POINTS], capture_output=True, text=True, cwd=tmp_path, env=env
    )
    assert eps.returncode == 0, eps.stderr[-3000:]
    import json

    found = json.loads(eps.stdout)
    assert found["bad"] == []
    assert found["names"] == sorted(f"nsflow-{s.replace('_', '-')}" for s in SHORT_NAMES)
    for name in found["names"]:
        assert (venv / "bin" / name).exists()
    # the ros2 run names (ate, bench, tracker, ...) are far too generic for a PATH
    assert [s for s in SHORT_NAMES if (venv / "bin" / s).exists()] == []
    for name in ("nsflow-tracker", "nsflow-replay", "nsflow-config", "nsflow-bench"):
        help_out = subprocess.run(
            [str(venv / "bin" / name), "--help"], capture_output=True, text=True, env=env, cwd=tmp_path
        )
        assert help_out.returncode == 0 and f"usage: {name}" in help_out.stdout, help_out.stderr[-2000:]
    # the robot's work runs without the eval extra: an ASL folder (made here, where the extra is) tracked
    seq = make_sample_sequence(tmp_path / "seq", seed=4, duration=0.3, stereo=False, formats=("asl",),
                               progress=False)
    replay = subprocess.run(
        [str(venv / "bin" / "nsflow-replay"), str(seq.asl_dir), "--offline", str(tmp_path / "off"),
         "--no-progress"],
        capture_output=True, text=True, env=env, cwd=tmp_path,
    )
    assert replay.returncode == 0, replay.stderr[-3000:]
    # a tool of the extra says which in one line
    sample = subprocess.run(
        [str(venv / "bin" / "nsflow-make-sample"), "--out", str(tmp_path / "s")],
        capture_output=True, text=True, env=env, cwd=tmp_path,
    )
    assert sample.returncode == 1 and len(sample.stderr.strip().splitlines()) == 1, sample.stderr[-2000:]
    assert "pip install 'nsflow_ros[eval]'" in sample.stderr


@pytest.mark.slow
def test_colcon_build_gives_ros2_run_layout(tmp_path):
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent)) or shutil.which("colcon")
    assert colcon, "colcon is a test dependency (colcon-common-extensions in setup.py's test extra)"
    _copy_package(tmp_path)
    listing = subprocess.run(
        [colcon, "list", "--base-paths", "src"], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    # a package.xml that catkin_pkg rejects silently degrades to "(python)": no ament hooks, no ros2 run
    assert "nsflow_ros" in listing.stdout and "(ros.ament_python)" in listing.stdout, listing.stdout
    build = subprocess.run(
        [colcon, "build", "--base-paths", "src"], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    prefix = tmp_path / "install" / "nsflow_ros"
    for exe in SHORT_NAMES:
        path = prefix / "lib" / "nsflow_ros" / exe
        assert path.is_file() and os.access(path, os.X_OK), path
    assert not (prefix / "bin").exists() or not [s for s in SHORT_NAMES if (prefix / "bin" / s).exists()]
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "nsflow_ros").is_file()
    assert (prefix / "share" / "nsflow_ros" / "package.xml").is_file()
    assert (prefix / "share" / "nsflow_ros" / "config").is_dir()
    # where `ros2 launch nsflow_ros tracker.launch.py` and its rviz:=true look
    for name in ("launch/tracker.launch.py", "launch/replay.launch.py", "rviz/nsflow.rviz"):
        assert (prefix / "share" / "nsflow_ros" / name).is_file(), name
    # what `ros2 run nsflow_ros bench` executes, in the environment `source install/setup.bash` makes
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = str(prefix)
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")])
    run = subprocess.run(
        [str(prefix / "lib" / "nsflow_ros" / "bench"), "--help"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0 and "usage: bench" in run.stdout, run.stderr[-2000:]  # the name typed
    where = subprocess.run(
        [sys.executable, "-c", "from nsflow_ros.resources import share_dir; print(share_dir())"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=True,
    )
    assert Path(where.stdout.strip()) == prefix / "share" / "nsflow_ros"
