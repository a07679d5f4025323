"""``--providers`` of the tools reaches the encoder's onnxruntime session (nsflow-replay --offline /
--features-bag, nsflow-bench, nsflow-evaluate), and the benchmark prints the provider in use; the
replay's ``--model`` reaches the tracker."""

from __future__ import annotations

import onnxruntime
import pytest
from onnx_models import conv_encoder

from nsflow_ros.bench import main as bench_main
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.evaluation.cli import main as evaluate_main
from nsflow_ros.ros.replay_node import main as replay_main

NONE_INSTALLED = "none of the execution providers CUDAExecutionProvider is in this onnxruntime"


@pytest.fixture
def cpu_only(monkeypatch):
    monkeypatch.setattr(onnxruntime, "get_available_providers", lambda: ["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("providers") / "seq"
    return make_sample_sequence(root, seed=4, duration=0.3, stereo=False, formats=("asl",), progress=False)


@pytest.mark.parametrize("mode", ["--offline", "--features-bag"])
def test_replay_tracking_takes_the_providers(seq, tmp_path, capsys, cpu_only, mode):
    out = tmp_path / ("f.bag" if mode == "--features-bag" else "off")
    assert replay_main([str(seq.asl_dir), mode, str(out), "--no-progress", "--providers", "cuda"]) == 1
    err = capsys.readouterr().err.strip()
    assert NONE_INSTALLED in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("mode", ["--offline", "--features-bag"])
def test_replay_tracking_takes_the_model_by_file_or_shipped_name(seq, tmp_path, capsys, mode):
    out = tmp_path / ("f.bag" if mode == "--features-bag" else "off")
    missing = tmp_path / "missing.onnx"
    assert replay_main([str(seq.asl_dir), mode, str(out), "--no-progress", "--model", str(missing)]) == 1
    assert "missing.onnx" in capsys.readouterr().err
    assert replay_main([str(seq.asl_dir), mode, str(out), "--no-progress", "--model", "fast"]) == 0


def test_evaluate_takes_the_providers(tmp_path, capsys, cpu_only):
    assert evaluate_main(["--quick", "--only", "pairs", "--out", str(tmp_path), "--providers", "cuda"]) == 1
    assert NONE_INSTALLED in capsys.readouterr().err


def test_bench_takes_the_providers_and_prints_the_one_in_use(tmp_path, capsys):
    model = conv_encoder(tmp_path / "m.onnx", c_in=1, d=1)
    stages_only = ["--tracker-seconds", "0", "--node-seconds", "0", "--frames", "2", "--points", "20",
                   "--model", str(model)]
    assert bench_main([*stages_only, "--providers", "AzureExecutionProvider,cpu"]) == 0
    assert "(d=1) on AzureExecutionProvider" in capsys.readouterr().out
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(onnxruntime, "get_available_providers", lambda: ["CPUExecutionProvider"])
        assert bench_main([*stages_only, "--providers", "cuda"]) == 1
    assert NONE_INSTALLED in capsys.readouterr().err
