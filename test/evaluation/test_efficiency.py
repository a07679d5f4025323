"""Inference efficiency: parameter / FLOP counts from the ONNX graph by hand, timings, a quick run."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from onnx_models import conv_encoder

from nsflow_ros.bench import paper_encoder_onnx
from nsflow_ros.core.encoder import load_encoder
from nsflow_ros.evaluation import efficiency as ef
from nsflow_ros.evaluation.context import EvalContext
from nsflow_ros.evaluation.errors import EvaluationError
from nsflow_ros.evaluation.methods import CLASSICAL, KLT, NSFLOW, NSFLOW_LK, eval_method
from nsflow_ros.resources import share_file


def _grouped_strided_conv(path):
    """Conv 4 -> 6 channels, 3x3, group 2, stride 2, pads 1, then Flatten and a Gemm 6*5*10 -> 7 (transB)."""
    rng = np.random.default_rng(0)
    w = numpy_helper.from_array(rng.normal(size=(6, 2, 3, 3)).astype(np.float32), "w")
    b = numpy_helper.from_array(np.zeros(6, np.float32), "b")
    g = numpy_helper.from_array(rng.normal(size=(7, 300)).astype(np.float32), "g")
    nodes = [
        helper.make_node("Conv", ["image", "w", "b"], ["c"], group=2, strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Flatten", ["c"], ["f"]),
        helper.make_node("Gemm", ["f", "g"], ["out"], transB=1),
    ]
    graph = helper.make_graph(
        nodes, "grouped", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 4, "H", "W"])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 7])], initializer=[w, b, g],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, path)
    return path


def test_one_conv_model_counts_equal_the_hand_computation(tmp_path):
    path = conv_encoder(tmp_path / "one.onnx", c_in=1, d=3)  # 3x3 conv 1 -> 3, pads 1
    c = ef.onnx_complexity(path, width=20, height=10)
    assert c.parameters == 3 * 1 * 9 + 3
    assert c.macs == (3 * 20 * 10) * (1 * 9)
    assert c.flops == 2 * c.macs and c.size == (20, 10)


def test_group_stride_and_gemm_are_counted(tmp_path):
    c = ef.onnx_complexity(_grouped_strided_conv(tmp_path / "g.onnx"), width=20, height=10)
    # conv output 6 x 5 x 10, each from 2 channels x 9 taps; Gemm 1 x 7 outputs of 300 inputs
    assert [layer["output_shape"] for layer in c.layers] == [[1, 6, 5, 10], [1, 7]]
    assert c.macs == 6 * 5 * 10 * 2 * 9 + 7 * 300
    assert c.parameters == 6 * 2 * 9 + 6 + 7 * 300


def test_shipped_and_paper_architectures_match_their_stated_sizes(tmp_path):
    shipped = ef.onnx_complexity(load_encoder("d4").path)
    assert shipped.parameters == 166 and shipped.flops == 23_040_000  # models/README.md: 166, 0.023 G
    teacher = ef.onnx_complexity(share_file("models/nsflow_encoder_w8.onnx"))
    assert teacher.parameters == 876 and teacher.flops == 129_024_000  # the paper's shape, width 8
    fast = ef.onnx_complexity(load_encoder().path)  # the default
    assert fast.parameters == 27 and fast.flops == 3_379_200  # models/README.md: width 1, d 1
    paper = ef.onnx_complexity(paper_encoder_onnx(tmp_path / "paper.onnx", c_in=3, d=3))
    assert paper.parameters == 1003  # bench.paper_encoder_onnx's docstring; the paper reports 1.01e3


def test_bad_models_are_clear_errors(tmp_path):
    with pytest.raises(EvaluationError, match="not found"):
        ef.onnx_complexity(tmp_path / "none.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(EvaluationError, match=r"junk\.onnx"):
        ef.onnx_complexity(junk)
    with pytest.raises(EvaluationError, match="positive"):
        ef.onnx_complexity(conv_encoder(tmp_path / "ok.onnx"), width=0)
    with pytest.raises(EvaluationError, match="at least 2 frames"):
        ef.time_tracker([np.zeros((10, 10), np.uint8)], None, "klt")


def test_quick_run(tmp_path):
    (tmp_path / "report").mkdir()
    methods = [eval_method(name, threads=1) for name in (NSFLOW, NSFLOW_LK, CLASSICAL, KLT)]
    ctx = EvalContext(methods=methods, quick=True, out_dir=tmp_path / "report", progress=False, threads=1)
    sec = ef.run(ctx)
    assert sec.key == "efficiency" and sec.figures[0].is_file()
    assert sec.data["complexity"]["320x240"]["parameters"] == 27  # the default model's
    assert sec.data["complexity"]["752x480"]["flops"] == 2 * 22 * 752 * 480  # multiply-adds per pixel
    names = [m.name for m in methods]
    assert list(sec.data["tracker_ms"]) == names  # every compared method, whole tracker
    for name in names:
        st = sec.data["tracker_ms"][name]
        assert 0 < st["total"]["median_ms"] <= st["total"]["p90_ms"]
    assert sec.data["tracker_ms"][KLT]["encode"]["median_ms"] < 0.05  # OpenCV needs no encoder
    trk = sec.data["tracker_ms"]
    assert trk[NSFLOW_LK]["encode"]["median_ms"] > trk[KLT]["encode"]["median_ms"]  # it encodes, as NSFlow
    enc = sec.data["encoder_ms"]
    assert enc[NSFLOW]["320x240"]["median_ms"] > enc["intensity"]["320x240"]["median_ms"]
    assert "| 27 |" in sec.markdown and "efficiency_times.png" in sec.markdown
