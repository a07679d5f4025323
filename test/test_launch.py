"""The launch files and the RViz2 config: what they pass exists, and setup.py installs them.

``ros2 launch`` (launch, launch_ros) is not installable from the package registries these tests run
with, so the files are read as Python syntax trees: their module-level constants say which node
parameters and tool options they pass, and those are checked against the settings table and the tools.
"""

from __future__ import annotations

import ast
from glob import glob
from pathlib import Path

import yaml

from nsflow_ros.ros.replay_node import _parser as replay_parser
from nsflow_ros.vins.settings import SETTINGS, setting

ROOT = Path(__file__).resolve().parent.parent
TRACKER = ROOT / "launch" / "tracker.launch.py"
REPLAY = ROOT / "launch" / "replay.launch.py"
RVIZ = ROOT / "rviz" / "nsflow.rviz"
# What the tracker launch file must offer (the node parameters among them are rows of the table).
TRACKER_ARGUMENTS = {"config_file", "params_file", "method", "model_path", "image_transport", "providers",
                     "namespace", "use_sim_time", "rviz"}


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _constant(path: Path, name: str):
    """A module-level constant (literal) of a launch file."""
    for node in _tree(path).body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                return ast.literal_eval(node.value)
    raise AssertionError(f"{path.name} has no constant {name}")


def _node_calls(path: Path) -> list[dict[str, object]]:
    """The literal keyword arguments of every Node(...) call."""
    calls = []
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Node":
            kw = {}
            for k in node.keywords:
                try:
                    kw[k.arg] = ast.literal_eval(k.value)
                except ValueError:
                    kw[k.arg] = None
            calls.append(kw)
    return calls


def test_launch_files_are_python_with_a_launch_description():
    for path in (TRACKER, REPLAY):
        names = {n.name for n in _tree(path).body if isinstance(n, ast.FunctionDef)}
        assert "generate_launch_description" in names, path


def test_tracker_launch_offers_the_arguments_and_passes_only_table_parameters():
    arguments = _constant(TRACKER, "ARGUMENTS")
    assert set(arguments) >= TRACKER_ARGUMENTS
    passed = _constant(TRACKER, "NODE_PARAMETERS")
    table = {s.name for s in SETTINGS}
    missing = sorted(set(passed) - table)
    assert missing == [], f"launch/tracker.launch.py passes parameters the node does not have: {missing}"
    assert set(passed) <= set(arguments)
    # an empty default leaves the params file's value, or the node's default
    assert all(arguments[name][0] == "" for name in passed)
    # the only other parameter set on the node is ROS's own use_sim_time
    source = TRACKER.read_text()
    keys = {n.slice.value for n in ast.walk(_tree(TRACKER))
            if isinstance(n, ast.Subscript) and isinstance(n.slice, ast.Constant)
            and isinstance(n.value, ast.Name) and n.value.id == "given"}
    assert keys == {"use_sim_time"} and "parameters=parameters" in source
    executables = {c.get("executable") for c in _node_calls(TRACKER)}
    assert executables == {"tracker", "rviz2"}


def test_replay_launch_passes_tracker_arguments_and_replay_options_that_exist():
    tracker_args = set(_constant(TRACKER, "ARGUMENTS"))
    passed_on = set(_constant(REPLAY, "TRACKER_ARGUMENTS"))
    assert passed_on <= tracker_args and "use_sim_time" not in passed_on  # replays run on /clock
    options = {o for a in replay_parser()._actions for o in a.option_strings}
    used = {n.value for n in ast.walk(_tree(REPLAY))
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value.startswith("--")}
    assert used and used <= options, sorted(used - options)
    assert {"path", "rate"} <= set(_constant(REPLAY, "REPLAY_ARGUMENTS"))
    assert {c.get("executable") for c in _node_calls(REPLAY)} == {"replay"}


def test_executables_the_launch_files_start_are_installed_for_ros2_run():
    tools = _constant(ROOT / "setup.py", "TOOLS")
    short = {name for _, name, _ in tools}
    assert {"tracker", "replay"} <= short


def test_rviz_config_shows_the_debug_image_and_the_feature_cloud():
    cfg = yaml.safe_load(RVIZ.read_text())
    displays = {d["Class"]: d for d in cfg["Visualization Manager"]["Displays"]}
    image = displays["rviz_default_plugins/Image"]["Topic"]["Value"]
    cloud = displays["rviz_default_plugins/PointCloud"]["Topic"]["Value"]
    assert image == "/" + str(setting("image_track_topic").default)
    assert cloud == setting("feature_topic").default
    assert displays["rviz_default_plugins/PointCloud"]["Topic"]["Reliability Policy"] == "Reliable"


def _data_files() -> list[tuple[str, list[str]]]:
    """setup.py's data_files, computed as setup.py does without running setup()."""
    tree = _tree(ROOT / "setup.py")
    func = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "_data_files")
    namespace = {"glob": glob, "Path": Path, "PACKAGE": _constant(ROOT / "setup.py", "PACKAGE")}
    exec(compile(ast.Module(body=[func], type_ignores=[]), "setup.py", "exec"), namespace)
    import os

    here = os.getcwd()
    try:
        os.chdir(ROOT)
        return namespace["_data_files"]()
    finally:
        os.chdir(here)


def test_setup_installs_the_launch_files_and_the_rviz_config():
    installed = {f"{dest}/{Path(src).name}" for dest, files in _data_files() for src in files}
    for path in (TRACKER, REPLAY, RVIZ):
        assert f"share/nsflow_ros/{path.relative_to(ROOT)}" in installed, path
