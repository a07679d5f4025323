"""package.xml declares what the code imports, so `rosdep install` and `colcon test` work in a workspace."""

from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from nsflow_ros.optional import EXTRAS

ROOT = Path(__file__).resolve().parent.parent

# Top-level module -> rosdep key. The python3-* keys were checked in ros/rosdistro rosdep/python.yaml; the
# others are ROS 2 Jazzy packages. A module absent here makes the test fail: map it when adding an import.
ROSDEP_KEYS = {
    "rclpy": "rclpy",
    "rcl_interfaces": "rcl_interfaces",
    "ament_index_python": "ament_index_python",
    "sensor_msgs": "sensor_msgs",
    "std_msgs": "std_msgs",
    "geometry_msgs": "geometry_msgs",
    "diagnostic_msgs": "diagnostic_msgs",
    "rosgraph_msgs": "rosgraph_msgs",
    "builtin_interfaces": "builtin_interfaces",
    "launch": "launch",
    "launch_ros": "launch_ros",
    "numpy": "python3-numpy",
    "cv2": "python3-opencv",
    "onnxruntime": "python3-onnxruntime-pip",
    "rosbags": "python3-rosbags-pip",
    "lz4": "python3-rosbags-pip",  # a dependency of rosbags (its ROS 1 chunk compression)
    "tqdm": "python3-tqdm",
    "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib",
    "skimage": "python3-skimage",
    "pytest": "python3-pytest",
    "scipy": "python3-scipy",
    "torch": "python3-torch",
}
# Modules with no rosdep key anywhere in rosdistro: installed with pip (setup.py lists them).
NO_ROSDEP_KEY = {"onnx", "evo"}
# Libraries of the extras (eval, train), imported on use through nsflow_ros.optional.require: test_depend,
# never exec_depend, so that a robot installing only rosdep's exec dependencies goes without them.
OPTIONAL = set(EXTRAS)
# Run by the launch files as executables, not imported.
EXECUTABLES = {"rviz2"}


def _runtime_imports() -> dict[str, set[str]]:
    """What the package and its launch files import."""
    return {**_imports(ROOT / "launch"), **_imports(ROOT / "nsflow_ros")}


def _imports(folder: Path) -> dict[str, set[str]]:
    """Top-level third-party modules imported anywhere under ``folder`` (module -> files)."""
    local = {p.stem for p in folder.rglob("*.py")} | {"nsflow_ros", "__future__"}
    found: dict[str, set[str]] = {}
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif _is_require(node):
                names = [node.args[0].value]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in local:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _is_require(node: ast.AST) -> bool:
    """``require("module", ...)``: an import of an extra's library through nsflow_ros.optional."""
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "require"
        and bool(node.args)
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    )


def _declared() -> tuple[set[str], set[str]]:
    root = ET.parse(ROOT / "package.xml").getroot()
    run = {e.text.strip() for tag in ("depend", "exec_depend") for e in root.iter(tag) if e.text}
    test = {e.text.strip() for tag in ("depend", "test_depend") for e in root.iter(tag) if e.text}
    return run, test


def test_every_module_import_has_a_known_rosdep_key():
    modules = set(_runtime_imports()) | set(_imports(ROOT / "test"))
    unknown = modules - set(ROSDEP_KEYS) - NO_ROSDEP_KEY
    assert not unknown, f"map these imports to rosdep keys in ROSDEP_KEYS: {sorted(unknown)}"


def test_package_xml_declares_what_the_code_imports():
    run, test = _declared()
    package = _runtime_imports()
    missing_run = {
        ROSDEP_KEYS[m]: sorted(files)[0]
        for m, files in package.items()
        if m in ROSDEP_KEYS and m not in OPTIONAL and ROSDEP_KEYS[m] not in run
    }
    assert not missing_run, f"exec_depend missing in package.xml (key: first importer): {missing_run}"
    tests = _imports(ROOT / "test")
    needed_by_tests = {ROSDEP_KEYS[m] for m in set(tests) | (OPTIONAL & set(package)) if m in ROSDEP_KEYS}
    assert not needed_by_tests - run - test, f"test_depend missing: {sorted(needed_by_tests - run - test)}"


def test_extras_are_test_depend_and_never_exec_depend():
    run, test = _declared()
    keys = {ROSDEP_KEYS[m] for m in OPTIONAL if m in ROSDEP_KEYS}
    assert keys & run == set(), f"an extra's library is exec_depend (a robot would install it): {keys & run}"
    assert keys <= test, f"an extra's library is not test_depend: {sorted(keys - test)}"
    used = {m for m in _runtime_imports() if m in OPTIONAL}
    assert used >= {"matplotlib", "skimage", "onnx", "torch"}, f"the scan misses require() calls: {used}"


def test_package_xml_declares_nothing_unused():
    run, test = _declared()
    used = {ROSDEP_KEYS[m] for m in set(_runtime_imports()) if m in ROSDEP_KEYS} | EXECUTABLES
    used_by_tests = {ROSDEP_KEYS[m] for m in set(_imports(ROOT / "test")) if m in ROSDEP_KEYS}
    assert run - used == set(), f"exec_depend nothing imports: {sorted(run - used)}"
    unused = test - used - used_by_tests
    assert unused == set(), f"test_depend nothing imports: {sorted(unused)}"
