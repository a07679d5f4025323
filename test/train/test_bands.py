"""The band layout written from an exported encoder (nsflow_ros.train.bands) reproduces it."""

from __future__ import annotations

import shutil

import numpy as np
import onnx
import pytest
import torch
from onnx_models import conv_encoder

from nsflow_ros.core.bands import bands_file
from nsflow_ros.core.encoder import load_encoder
from nsflow_ros.train.bands import MAX_WIDTH, export_bands, main
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.export import export_onnx
from nsflow_ros.train.model import Encoder, EncoderSpec


def _whole(path, tmp_path):
    plain = tmp_path / "plain" / path.name
    plain.parent.mkdir(exist_ok=True)
    shutil.copy(path, plain)
    return load_encoder(plain, threads=1)


@pytest.mark.parametrize(("d", "head"), [(1, "none"), (2, "sigmoid"), (3, "relu")])
def test_a_width_1_export_gets_a_band_layout_that_reproduces_it(tmp_path, d, head):
    torch.manual_seed(d)
    path = export_onnx(Encoder(EncoderSpec(d=d, width=1, head=head)), tmp_path / "enc.onnx")
    assert bands_file(path).is_file()
    enc, whole = load_encoder(path, threads=1), _whole(path, tmp_path)
    assert enc.layout == "bands" and whole.layout == "whole frame"
    img = np.random.default_rng(d).integers(0, 256, (70, 45), dtype=np.uint8)
    np.testing.assert_allclose(enc(img), whole(img), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize(
    ("w3", "b3", "w4", "kept"),
    [
        ([0.5, 1.5], [0.1, -0.01], [3.0, -1.5], ["Clip"]),  # one unit linear on h >= 0, one clipped
        ([0.5, 1.5], [-0.1, -0.01], [3.0, 1.5], ["Relu", "Relu"]),  # both bend, positive weights
        ([0.5, -1.5], [0.1, -0.01], [3.0, 2.0], []),  # one linear, one always 0
    ],
)
def test_the_one_channel_head_is_folded_into_per_band_convolutions(tmp_path, w3, b3, w4, kept):
    """y = b4 + sum_j w4_j relu(w3_j h + b3_j) with h >= 0: a unit whose ReLU is the identity (or 0) there
    joins the linear term, the others keep an activation; the layout still equals the model."""
    torch.manual_seed(0)
    model = Encoder(EncoderSpec(d=1, width=1))
    with torch.no_grad():
        model.conv3.weight.copy_(torch.tensor(w3).view(2, 1, 1, 1))
        model.conv3.bias.copy_(torch.tensor(b3))
        model.conv4.weight.copy_(torch.tensor(w4).view(1, 2, 1, 1))
    path = export_onnx(model, tmp_path / "enc.onnx")
    graph = onnx.load(str(bands_file(path))).graph
    ops = [n.op_type for n in graph.node]
    assert [op for op in ops if op in ("Relu", "Clip")] == ["Relu", "Relu", *kept]
    groups = [a.i for n in graph.node if n.op_type == "Conv" for a in n.attribute if a.name == "group"]
    assert ops.count("Conv") == 3 + len(kept) and set(groups) == {16}
    enc, whole = load_encoder(path, threads=1), _whole(path, tmp_path)
    assert enc.layout == "bands"
    img = np.random.default_rng(1).integers(0, 256, (80, 60), dtype=np.uint8)
    np.testing.assert_allclose(enc(img), whole(img), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize(("d", "width"), [(4, 3), (1, 2)])
def test_a_narrow_export_gets_a_band_layout_of_per_band_convolutions_and_a_matrix_head(tmp_path, d, width):
    torch.manual_seed(width)
    path = export_onnx(Encoder(EncoderSpec(d=d, width=width, head="sigmoid")), tmp_path / "enc.onnx")
    graph = onnx.load(str(bands_file(path))).graph
    groups = {a.i for n in graph.node if n.op_type == "Conv" for a in n.attribute if a.name == "group"}
    ops = [n.op_type for n in graph.node]
    # every 3x3 a depthwise conv per pair of channels, the head two matrix products
    assert groups == {16} and ops.count("Conv") == width + width**2 and ops.count("Gemm") == 2
    enc = load_encoder(path, threads=1)
    assert enc.layout == "bands"
    img = np.random.default_rng(0).integers(0, 256, (70, 45), dtype=np.uint8)
    np.testing.assert_allclose(enc(img), _whole(path, tmp_path)(img), rtol=2e-6, atol=2e-6)


def test_a_wider_export_gets_none_but_can_be_written(tmp_path):
    path = export_onnx(Encoder(EncoderSpec(d=2, width=MAX_WIDTH + 1)), tmp_path / "enc.onnx")
    assert not bands_file(path).exists()
    assert export_bands(path, bands=4) == bands_file(path)
    enc = load_encoder(path, threads=1)
    assert enc.layout == "bands" and enc._bands.bands == 4
    img = np.random.default_rng(0).integers(0, 256, (40, 30), dtype=np.uint8)
    np.testing.assert_allclose(enc(img), _whole(path, tmp_path)(img), rtol=2e-6, atol=2e-6)


def test_errors_name_the_fault(tmp_path):
    with pytest.raises(TrainError, match="bands must be >= 2"):
        export_bands(tmp_path / "x.onnx", bands=1)
    with pytest.raises(TrainError, match=r"cannot read the ONNX model .*x\.onnx"):
        export_bands(tmp_path / "x.onnx")
    other = conv_encoder(tmp_path / "one_conv.onnx", c_in=1, d=3)
    with pytest.raises(TrainError, match=r"one_conv\.onnx: expected the encoder's four convolutions"):
        export_bands(other)


def test_command_line(tmp_path, capsys):
    path = export_onnx(Encoder(EncoderSpec(d=1, width=2)), tmp_path / "enc.onnx")
    assert main([str(path), "--bands", "8"]) == 0
    assert str(bands_file(path)) in capsys.readouterr().out
    assert load_encoder(path, threads=1)._bands.bands == 8
    assert main([str(tmp_path / "none.onnx")]) == 1
    assert "none.onnx" in capsys.readouterr().out
