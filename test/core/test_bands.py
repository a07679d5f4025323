"""Tests of the band layout (nsflow_ros.core.bands) with the shipped default model and its sibling."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from nsflow_ros import EncoderError, load_encoder
from nsflow_ros.core.bands import BANDS_SUFFIX, BandLayout, bands_file
from nsflow_ros.core.encoder import model_file


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w), dtype=np.uint8)


@pytest.fixture(scope="module")
def shipped():
    """The default model (with its shipped band layout) and a copy of it without one."""
    return load_encoder("default", threads=1)


@pytest.fixture()
def whole(tmp_path):
    path = tmp_path / "fast.onnx"
    shutil.copy(model_file("default"), path)
    return load_encoder(path, threads=1)


def test_the_default_model_ships_its_band_layout(shipped, whole):
    assert bands_file(model_file("default")).is_file()
    assert bands_file(model_file("default")).name == "nsflow_encoder_fast" + BANDS_SUFFIX
    assert shipped.layout == "bands" and shipped._bands is not None and shipped._bands.bands >= 2
    assert whole.layout == "whole frame"


@pytest.mark.parametrize("shape", [(480, 752), (101, 100), (64, 37), (97, 8), (752, 480)])
def test_bands_equal_the_whole_frame(shipped, whole, shape):
    img = _image(*shape, seed=shape[0])
    a, b = shipped(img), whole(img)
    assert a.shape == b.shape == (*shape, 1) and a.flags.c_contiguous
    # float32 rounding only: the same sums in another order
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=2e-6)
    bands = shipped._bands
    assert bands.fits(*shape)
    x = img[None, None].astype(np.float32) * np.float32(1 / 255)
    raw = bands(img)  # before the declared smoothing: every pixel, the outer rows and columns included
    np.testing.assert_allclose(raw, whole._run(x), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("shape", [(63, 50), (100, 7)])
def test_a_short_or_narrow_image_runs_whole(shipped, whole, shape):
    img = _image(*shape)
    assert not shipped._bands.fits(*img.shape)
    np.testing.assert_array_equal(shipped(img), whole(img))


def test_the_edges_come_from_the_original_network(shipped, whole):
    """Without the mended outer lines the layout differs from the model there, and only there."""
    img = _image(96, 40, seed=3)
    x = img[None, None].astype(np.float32) * np.float32(1 / 255)
    bands = shipped._bands
    unmended = BandLayout(bands.session, 1, lambda e: np.full((1, 1, *e.shape[2:]), np.nan, np.float32))
    diff = np.abs(unmended(img) - whole._run(x))[0, 0]
    assert np.isnan(diff[[0, -1]]).all() and np.isnan(diff[:, [0, -1]]).all()
    assert diff[1:-1, 1:-1].max() < 2e-6


def test_strips_over_threads_do_not_use_bands_and_bands_can_be_turned_off():
    assert load_encoder("default", threads=2).layout == "strips"
    assert load_encoder("default", threads=1, bands=False).layout == "whole frame"


def test_a_session_of_another_graph_is_refused(whole):
    with pytest.raises(EncoderError, match=r"band layout: expected one input"):
        BandLayout(whole._sessions[0], 1, whole._run)


def test_a_layout_of_the_earlier_two_input_form_is_ignored_naming_the_command_to_rewrite_it(tmp_path, caplog):
    path = tmp_path / "fast.onnx"
    shutil.copy(model_file("default"), path)
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, c, None, None])
              for n, c in (("bands", 16), ("edges", 1))]
    outputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, c, None, None])
               for n, c in (("descriptors", 16), ("edge_descriptors", 1))]
    nodes = [helper.make_node("Identity", ["bands"], ["descriptors"]),
             helper.make_node("Identity", ["edges"], ["edge_descriptors"])]
    old = helper.make_model(helper.make_graph(nodes, "old", inputs, outputs),
                            opset_imports=[helper.make_opsetid("", 17)])
    old.ir_version = 8
    onnx.save(old, str(bands_file(path)))
    with caplog.at_level(logging.WARNING):
        enc = load_encoder(path, threads=1)
    assert enc.layout == "whole frame"
    assert "python -m nsflow_ros.train.bands" in caplog.text


def test_a_layout_of_other_weights_is_ignored_with_a_warning(tmp_path, caplog):
    proto = onnx.load(str(model_file("default")))
    for init in proto.graph.initializer:
        if init.name == "conv2.weight":
            init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * np.float32(1.5), init.name))
    path = tmp_path / "other.onnx"
    onnx.save(proto, str(path))
    shutil.copy(bands_file(model_file("default")), bands_file(path))
    with caplog.at_level(logging.WARNING):
        enc = load_encoder(path, threads=1)
    assert enc.layout == "whole frame"
    assert "does not reproduce other.onnx" in caplog.text


def test_a_layout_of_another_channel_count_is_ignored(tmp_path, caplog):
    path = tmp_path / "d4.onnx"
    shutil.copy(model_file("d4"), path)
    shutil.copy(bands_file(model_file("default")), bands_file(path))
    with caplog.at_level(logging.WARNING):
        enc = load_encoder(path, threads=1)
    assert enc.layout == "whole frame" and "ignoring the band layout" in caplog.text
