"""Tests of the encoders (nsflow_ros.core.encoder)."""

from __future__ import annotations

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from onnx_models import conv_encoder, reference_conv

import nsflow_ros.resources as resources
from nsflow_ros import EncoderError, IntensityEncoder, OnnxEncoder, load_encoder
from nsflow_ros.core.encoder import to_gray


def _image(h=24, w=32, color=False, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3) if color else (h, w), dtype=np.uint8)


def test_intensity_encoder_scales_gray_to_unit_range():
    img = _image()
    out = IntensityEncoder()(img)
    assert out.shape == (24, 32, 1) and out.dtype == np.float32
    np.testing.assert_allclose(out[..., 0], img / 255.0, atol=1e-7)
    bgr = _image(color=True)
    np.testing.assert_allclose(IntensityEncoder()(bgr)[..., 0], cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) / 255.0)


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((10, 10), np.float32), "uint8"),
        (np.zeros((10, 10, 4), np.uint8), r"\(H, W\) mono or \(H, W, 3\) BGR"),
        (np.zeros((0, 10), np.uint8), "empty"),
        ("not an image", "numpy array"),
    ],
)
def test_bad_images_are_rejected(image, match):
    with pytest.raises(EncoderError, match=match):
        IntensityEncoder()(image)


def test_to_gray_passes_mono_through():
    img = _image()
    assert to_gray(img) is img
    assert to_gray(img[..., None]).shape == (24, 32)


@pytest.mark.parametrize("c_in", [1, 3])
def test_onnx_encoder_matches_reference(tmp_path, c_in):
    path = conv_encoder(tmp_path / "m.onnx", c_in=c_in, d=3)
    enc = load_encoder(path, threads=1)
    assert isinstance(enc, OnnxEncoder)
    assert enc.channels == 3 and enc.input_channels == c_in and enc.name == "tiny-d3"
    bgr = _image(color=True)
    out = enc(bgr)
    assert out.shape == (24, 32, 3) and out.dtype == np.float32 and out.flags.c_contiguous
    if c_in == 3:
        x = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).transpose(2, 0, 1) / 255.0
    else:
        x = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[None] / 255.0
    np.testing.assert_allclose(out, reference_conv(x, path), atol=1e-5)
    # mono input to an RGB model is replicated; any size works (dynamic H, W)
    assert enc(_image(40, 50)).shape == (40, 50, 3)


def test_missing_model_names_the_path(tmp_path):
    with pytest.raises(EncoderError, match=r"not found: .*nope\.onnx"):
        load_encoder(tmp_path / "nope.onnx")


def test_garbage_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x00not a model")
    with pytest.raises(EncoderError, match=r"cannot load encoder model .*bad\.onnx"):
        load_encoder(bad)


def _write(path, inputs, outputs, nodes):
    graph = helper.make_graph(nodes, "g", inputs, outputs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, path)
    return path


def test_wrong_signature_reports_expected_and_found(tmp_path):
    f = TensorProto.FLOAT
    rank3 = _write(
        tmp_path / "rank3.onnx",
        [helper.make_tensor_value_info("x", f, [1, "H", "W"])],
        [helper.make_tensor_value_info("y", f, [1, "H", "W"])],
        [helper.make_node("Identity", ["x"], ["y"])],
    )
    with pytest.raises(EncoderError, match=r"expected one input \(1, 1\|3, H, W\).*found inputs \[\('x'"):
        load_encoder(rank3)
    two_out = _write(
        tmp_path / "two.onnx",
        [helper.make_tensor_value_info("x", f, [1, 1, "H", "W"])],
        [helper.make_tensor_value_info("y", f, [1, 1, "H", "W"]),
         helper.make_tensor_value_info("z", f, [1, 1, "H", "W"])],
        [helper.make_node("Identity", ["x"], ["y"]), helper.make_node("Identity", ["x"], ["z"])],
    )
    with pytest.raises(EncoderError, match="found inputs"):
        load_encoder(two_out)
    four_ch = _write(
        tmp_path / "four.onnx",
        [helper.make_tensor_value_info("x", f, [1, 4, "H", "W"])],
        [helper.make_tensor_value_info("y", f, [1, 4, "H", "W"])],
        [helper.make_node("Identity", ["x"], ["y"])],
    )
    with pytest.raises(EncoderError, match=r"\[1, 4, 'H', 'W'\]"):
        load_encoder(four_ch)


def test_default_model_missing_is_a_clear_error(monkeypatch):
    def missing(rel):
        raise resources.ResourceError(f"cannot find shared file {rel} (tried /x)")

    monkeypatch.setattr(resources, "share_file", missing)
    with pytest.raises(EncoderError, match=r"shipped encoder models/nsflow_encoder\.onnx is missing"):
        load_encoder()


def test_threads_must_be_positive(tmp_path):
    with pytest.raises(EncoderError, match="threads"):
        load_encoder(conv_encoder(tmp_path / "m.onnx"), threads=0)
