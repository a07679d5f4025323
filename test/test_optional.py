"""The extras' libraries are imported on use only (nsflow_ros.optional): the robot install runs without them.

The runtime checks run in a subprocess whose import system hides every library of an extra (matplotlib,
scikit-image, SciPy, onnx, torch) and records any attempt to import one, so a module-level import or a
stray call on the node's path fails here although this environment has them all.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.optional import EXTRAS, MissingExtraError, require, require_extra

ROOT = Path(__file__).resolve().parent.parent

# Runs before the code under test: every extra's library raises ModuleNotFoundError, and is recorded.
HIDE = textwrap.dedent(
    """
    import atexit, json, sys
    HIDDEN = {hidden!r}
    TRIED = []

    class _Hide:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HIDDEN:
                TRIED.append(name)
                raise ModuleNotFoundError(f"No module named {{name!r}} (hidden by the test)", name=name)
            return None

    sys.meta_path.insert(0, _Hide())
    atexit.register(lambda: print("TRIED=" + json.dumps(sorted(set(TRIED))), file=sys.stderr))
    """
).format(hidden=sorted({*EXTRAS, "scipy"}))  # SciPy: scikit-image's, none of ours

# Everything but nsflow_ros.train (the train extra's own subpackage, which refuses to import without torch).
# (module, program, main's arguments: the tracker's include the program, as ROS passes them)
RUNTIME_TOOLS = [
    ("nsflow_ros.ros.tracker_node", "nsflow-tracker", ["nsflow-tracker", "--help"]),
    ("nsflow_ros.ros.replay_node", "nsflow-replay", ["--help"]),
    ("nsflow_ros.vins.cli", "nsflow-config", ["--help"]),
]


def _hidden(code: str, cwd: Path) -> tuple[int, str, str, list[str]]:
    """Run ``code`` with the extras hidden: (exit code, stdout, stderr without the record, tried)."""
    argv = [sys.executable, "-c", HIDE + textwrap.dedent(code)]
    proc = subprocess.run(argv, capture_output=True, text=True, cwd=cwd, timeout=120)
    lines = proc.stderr.splitlines()
    record = [ln for ln in lines if ln.startswith("TRIED=")]
    assert record, proc.stderr[-3000:]
    err = "\n".join(ln for ln in lines if not ln.startswith("TRIED="))
    return proc.returncode, proc.stdout, err, json.loads(record[-1].removeprefix("TRIED="))


@pytest.fixture(scope="module")
def asl(tmp_path_factory) -> Path:
    """A 0.3 s monocular ASL folder (made here, where the eval extra is installed)."""
    root = tmp_path_factory.mktemp("lean") / "seq"
    seq = make_sample_sequence(root, seed=4, duration=0.3, stereo=False, formats=("asl",), progress=False)
    return seq.asl_dir


def test_every_module_outside_train_imports_and_the_runtime_tools_help_without_the_extras(tmp_path):
    modules = sorted(
        ".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for p in (ROOT / "nsflow_ros").rglob("*.py")
        if "train" not in p.relative_to(ROOT / "nsflow_ros").parts and p.name != "__main__.py"
    )
    assert "nsflow_ros.ros.tracker_node" in modules and "nsflow_ros.vins.feature_bag" in modules
    code = f"""
        import contextlib, importlib, io
        for m in {modules!r}:
            importlib.import_module(m)
        for module, prog, args in {RUNTIME_TOOLS!r}:
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                assert importlib.import_module(module).main(args) == 0, prog
            assert f"usage: {{prog}}" in out.getvalue(), (prog, out.getvalue())
    """
    rc, _, err, tried = _hidden(code, tmp_path)
    assert rc == 0, err[-3000:]
    assert tried == []


def test_replay_offline_and_feature_bag_run_without_the_extras(tmp_path, asl):
    code = f"""
        from nsflow_ros.ros.replay_node import main
        common = ["--no-progress", "--model", "fast"]
        assert main([{str(asl)!r}, "--offline", {str(tmp_path / "off")!r}, *common]) == 0
        assert main([{str(asl)!r}, "--features-bag", {str(tmp_path / "f.bag")!r}, *common]) == 0
    """
    rc, _, err, tried = _hidden(code, tmp_path)
    assert rc == 0, err[-3000:]
    assert tried == []
    assert any((tmp_path / "off").rglob("*")) and (tmp_path / "f.bag").exists()


def _tum(path: Path, shift: float) -> Path:
    t = np.arange(20) * 0.1
    rows = [f"{s:.3f} {np.sin(s) + shift:.6f} {np.cos(s):.6f} 0 0 0 0 1" for s in t]
    path.write_text("\n".join(rows) + "\n")
    return path


# The tools of the eval extra: (name, module, main's arguments); {tmp} is the test's folder.
EVAL_TOOLS = [
    ("make-sample", "nsflow_ros.data.cli", ["--out", "{tmp}/sample", "--duration", "0.1"]),
    ("ate-plot", "nsflow_ros.ate.cli", ["ape", "{tmp}/gt.tum", "{tmp}/est.tum", "--plot", "{tmp}/ate.png"]),
    ("bench", "nsflow_ros.bench", ["--frames", "3"]),
    ("demo", "nsflow_ros.demo", ["--out", "{tmp}/demo"]),
    ("evaluate", "nsflow_ros.evaluation.cli", ["--quick", "--out", "{tmp}/ev"]),
]


def test_each_tool_of_the_extra_names_it_in_one_line(tmp_path):
    _tum(tmp_path / "gt.tum", 0.0)
    _tum(tmp_path / "est.tum", 0.01)
    tools = [(name, module, [a.format(tmp=tmp_path) for a in args]) for name, module, args in EVAL_TOOLS]
    # one process for all (the hidden libraries never load, so each tool meets them missing)
    code = f"""
        import contextlib, importlib, io, json
        got = {{}}
        for name, module, args in {tools!r}:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                got[name] = [importlib.import_module(module).main(args), err.getvalue()]
        print(json.dumps(got))
    """
    rc, out, err, tried = _hidden(code, tmp_path)
    assert rc == 0, err[-3000:]
    got = json.loads(out.strip().splitlines()[-1])
    for name, _, _ in EVAL_TOOLS:
        code_, text = got[name]
        assert code_ == 1 and len(text.strip().splitlines()) == 1, (name, code_, text)
        assert "pip install 'nsflow_ros[eval]'" in text, (name, text)
    assert {"skimage", "matplotlib"} <= {t.split(".")[0] for t in tried}


def test_require_names_the_extra_and_passes_present_libraries_through(monkeypatch):
    assert require("matplotlib", "a test").__name__ == "matplotlib"
    monkeypatch.setitem(sys.modules, "onnx", None)  # None in sys.modules: import raises ModuleNotFoundError
    with pytest.raises(MissingExtraError, match=r"the FLOP count needs onnx, .*'eval' extra: pip install"):
        require("onnx", "the FLOP count")
    with pytest.raises(KeyError):
        require("cv2", "not an extra's library")


def test_require_extra_names_every_missing_library(monkeypatch):
    require_extra("eval", "a test")  # all here
    monkeypatch.setitem(sys.modules, "onnx", None)
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None if name == "skimage" else object())
    with pytest.raises(MissingExtraError, match=r"^the demo needs skimage, of the 'eval' extra: pip install"):
        require_extra("eval", "the demo")
