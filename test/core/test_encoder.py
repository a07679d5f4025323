"""Tests of the encoders (nsflow_ros.core.encoder)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from onnx_models import conv_encoder, graph_encoder, reference_conv

import nsflow_ros.resources as resources
from nsflow_ros import EncoderError, IntensityEncoder, OnnxEncoder, Smoothing, load_encoder
from nsflow_ros.core.encoder import (
    DEFAULT_MODEL,
    SHIPPED_MODELS,
    ExecutionProviders,
    encoder_provider,
    model_file,
    to_gray,
)
from nsflow_ros.core.pyramid import gaussian_kernel, sampling_source


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
    assert out.shape == (24, 32, 3) and out.dtype == np.float32
    # three channels come as the leading ones of a C-contiguous 4-channel block (the pyramid's layout)
    assert sampling_source(out).shape == (24, 32, 4) and sampling_source(out).flags.c_contiguous
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
    with pytest.raises(EncoderError, match=r"shipped encoder models/nsflow_encoder_fast\.onnx is missing"):
        load_encoder()


def test_shipped_models_load_by_name_and_a_file_passes_through(tmp_path):
    assert set(SHIPPED_MODELS) == {"default", "fast", "d4"} and SHIPPED_MODELS["default"] == DEFAULT_MODEL
    assert model_file() == model_file("default") == model_file("fast") == resources.share_file(DEFAULT_MODEL)
    assert model_file("d4") == resources.share_file("models/nsflow_encoder.onnx")
    path = conv_encoder(tmp_path / "m.onnx")
    assert model_file(path) == path and model_file(str(path)) == path
    default = load_encoder(threads=1)
    # one channel, smoothed as the four-channel model is, with the gain fitted on the finest level
    assert default.channels == 1 and default.smoothing == Smoothing(fine=1.0, coarse=1.0)
    assert default.gain_levels == 1
    d4 = load_encoder(Path("d4"), threads=1)
    assert d4.channels == 4 and d4.gain_levels == 0


def test_a_shipped_model_missing_from_the_install_is_named(monkeypatch):
    def missing(rel):
        raise resources.ResourceError(f"cannot find shared file {rel} (tried /x)")

    monkeypatch.setattr(resources, "share_file", missing)
    with pytest.raises(EncoderError, match=r"shipped encoder models/nsflow_encoder\.onnx is missing"):
        load_encoder("d4")


def test_threads_must_be_positive(tmp_path):
    with pytest.raises(EncoderError, match="threads"):
        load_encoder(conv_encoder(tmp_path / "m.onnx"), threads=0)


def _conv(name, src, dst, c_in, c_out, k, rng, dilation=1):
    from onnx import numpy_helper

    w = numpy_helper.from_array(rng.normal(0, 0.5, (c_out, c_in, k, k)).astype(np.float32), f"{name}_w")
    pad = dilation * (k - 1) // 2
    node = helper.make_node(
        "Conv", [src, f"{name}_w"], [dst], pads=[pad] * 4, dilations=[dilation, dilation]
    )
    return node, w


@pytest.mark.parametrize("threads", [1, 2])
def test_shipped_model_tiled_equals_whole_frame(threads):
    tiled = load_encoder("d4", threads=threads, tile_rows=16)
    whole = load_encoder("d4", threads=threads, tile_rows=0, bands=False)
    assert tiled.tiled and tiled.halo == 2  # two 3x3 convolutions
    assert not whole.tiled
    img = _image(150, 200, color=True, seed=3)
    a, b = tiled(img), whole(img)
    assert a.shape == (150, 200, 4) and a.flags.c_contiguous
    np.testing.assert_array_equal(a, b)
    # by default one thread encodes the whole frame (in its band layout: the same sums in another order),
    # several run strips (the halos buy parallelism)
    auto = load_encoder("d4", threads=threads)
    assert auto.tiled == (threads > 1) and (auto.layout == "bands") == (threads == 1)
    for h, w in ((400, 320), (480, 752), (7, 9)):
        np.testing.assert_allclose(auto(_image(h, w)), whole(_image(h, w)), rtol=2e-6, atol=2e-6)


def _blur(desc, sigma):
    k = gaussian_kernel(sigma)
    out = cv2.sepFilter2D(desc, cv2.CV_32F, k, k, borderType=cv2.BORDER_REPLICATE)
    return out if out.ndim == 3 else out[..., None]


@pytest.mark.parametrize("name", ["default", "d4"])
def test_shipped_model_declares_its_smoothing_and_the_encoder_applies_the_fine_part(name):
    enc = load_encoder(name, threads=1)
    assert enc.smoothing == Smoothing(fine=1.0, coarse=1.0)
    raw = load_encoder(name, threads=1, tile_rows=0, smoothing=Smoothing())
    assert raw.smoothing == Smoothing()
    img = _image(120, 160, seed=4)
    np.testing.assert_allclose(enc(img), _blur(raw(img), 1.0), atol=1e-6)
    assert IntensityEncoder.smoothing == Smoothing()


@pytest.mark.parametrize("threads", [1, 2])
def test_smoothed_strips_equal_the_smoothed_whole_frame(tmp_path, threads):
    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    sm = Smoothing(fine=1.3, coarse=0.0)  # 7 taps: the strips' halo must grow by 3 rows
    tiled = load_encoder(path, threads=threads, tile_rows=5, smoothing=sm)
    whole = load_encoder(path, threads=threads, tile_rows=0, smoothing=sm)
    plain = load_encoder(path, threads=1, tile_rows=0)
    assert tiled.tiled and tiled.halo == 1 and plain.smoothing == Smoothing()
    for h, w in ((61, 47), (6, 9)):
        img = _image(h, w, seed=5)
        np.testing.assert_allclose(tiled(img), whole(img), atol=1e-6)
        np.testing.assert_allclose(whole(img), _blur(plain(img), 1.3), atol=1e-6)


@pytest.mark.parametrize("value", ["1.0", "a,b", "1.0,-1", "1,2,3"])
def test_malformed_smoothing_metadata_is_named(tmp_path, value):
    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    model = onnx.load(str(path))
    entry = model.metadata_props.add()
    entry.key, entry.value = "smoothing", value
    onnx.save(model, str(path))
    with pytest.raises(EncoderError, match=r"m\.onnx: metadata 'smoothing' must be 'fine,coarse'"):
        load_encoder(path)
    with pytest.raises(EncoderError, match="Smoothing or None"):
        load_encoder(conv_encoder(tmp_path / "n.onnx"), smoothing=(1.0, 0.5))  # type: ignore[arg-type]


@pytest.mark.parametrize(("value", "levels"), [("0", 0), ("2", 2), ("-1", None), ("one", None)])
def test_gain_levels_metadata_is_read_or_named(tmp_path, value, levels):
    from nsflow_ros.train.declare import set_metadata

    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=3)
    assert load_encoder(path).gain_levels == 0  # undeclared: the offset-only residual
    set_metadata(path, {"gain_levels": value})
    if levels is None:
        with pytest.raises(EncoderError, match=r"m\.onnx: metadata 'gain_levels' must be an integer >= 0"):
            load_encoder(path)
    else:
        assert load_encoder(path).gain_levels == levels


def test_halo_is_measured_from_the_model(tmp_path):
    rng = np.random.default_rng(0)
    n1, w1 = _conv("a", "image", "h", 1, 3, 5, rng)
    n2, w2 = _conv("b", "h", "descriptors", 3, 2, 3, rng, dilation=3)
    enc = load_encoder(graph_encoder(tmp_path / "m.onnx", [n1, n2], [w1, w2], d=2), threads=1, tile_rows=7)
    assert enc.halo == 2 + 3
    img = _image(60, 40, seed=1)
    np.testing.assert_allclose(enc(img), load_encoder(enc.path, threads=1, tile_rows=0)(img), atol=1e-6)


def test_a_model_that_looks_at_the_whole_image_is_not_tiled(tmp_path):
    rng = np.random.default_rng(0)
    conv, w = _conv("a", "image", "h", 1, 2, 3, rng)
    nodes = [
        conv,
        helper.make_node("ReduceMean", ["h"], ["m"], axes=[2, 3], keepdims=1),
        helper.make_node("Sub", ["h", "m"], ["descriptors"]),
    ]
    enc = load_encoder(graph_encoder(tmp_path / "g.onnx", nodes, [w], d=2), threads=1, tile_rows=8)
    assert not enc.tiled and enc.halo is None
    img = _image(64, 48, seed=2)
    out = enc(img)
    np.testing.assert_allclose(out.mean(axis=(0, 1)), 0.0, atol=1e-5)  # centred over the whole frame


def test_single_channel_models_keep_their_channel_axis(tmp_path):
    path = conv_encoder(tmp_path / "m.onnx", c_in=1, d=1)
    out = load_encoder(path, threads=1, tile_rows=5)(_image(30, 20))
    assert out.shape == (30, 20, 1) and out.flags.c_contiguous


def test_tile_rows_must_not_be_negative(tmp_path):
    with pytest.raises(EncoderError, match="tile_rows"):
        load_encoder(conv_encoder(tmp_path / "m.onnx"), tile_rows=-1)


# -- execution providers -------------------------------------------------------------------------------

CPU = "CPUExecutionProvider"


def _installed(monkeypatch, *names):
    import onnxruntime

    monkeypatch.setattr(onnxruntime, "get_available_providers", lambda: list(names))


def test_provider_lists_take_short_and_full_names():
    parse = ExecutionProviders.parse
    assert parse("tensorrt, CUDA ,cpu").names == (
        "TensorrtExecutionProvider", "CUDAExecutionProvider", CPU
    )
    assert parse(["cuda", "CPUExecutionProvider", "cpu"]).names == ("CUDAExecutionProvider", CPU)
    assert parse(None).names == parse("").names == (CPU,) == ExecutionProviders().names
    assert parse("OpenVINOExecutionProvider").names == ("OpenVINOExecutionProvider",)
    with pytest.raises(EncoderError, match=r"unknown execution provider 'gpu'; short names: cpu, cuda"):
        parse("gpu,cpu")
    with pytest.raises(EncoderError, match="empty name"):
        parse("cuda,,cpu")


def test_tensorrt_options_become_provider_options():
    eps = ExecutionProviders.parse("tensorrt,cuda,cpu", tensorrt_fp16=True, tensorrt_cache="/tmp/trt")
    trt, cuda, cpu = eps.session_providers(eps.names)
    assert trt == ("TensorrtExecutionProvider", {
        "trt_fp16_enable": "True", "trt_engine_cache_enable": "True", "trt_engine_cache_path": "/tmp/trt"
    })
    assert (cuda, cpu) == ("CUDAExecutionProvider", CPU)
    plain = ExecutionProviders.parse("tensorrt").session_providers(["TensorrtExecutionProvider"])
    assert plain == [("TensorrtExecutionProvider", {"trt_fp16_enable": "False"})]


def test_missing_providers_give_one_warning_and_the_cpu_runs(monkeypatch, caplog):
    _installed(monkeypatch, "AzureExecutionProvider", CPU)
    with caplog.at_level("WARNING", logger="nsflow_ros.core.encoder"):
        enc = load_encoder(threads=2, providers="tensorrt,cuda,cpu")
    assert enc.provider == CPU and enc.tiled
    (record,) = caplog.records
    message = record.getMessage()
    assert "\n" not in message
    assert message == (
        "execution provider(s) TensorrtExecutionProvider, CUDAExecutionProvider not in this onnxruntime "
        "(installed: AzureExecutionProvider, CPUExecutionProvider); using CPUExecutionProvider"
    )


def test_no_requested_provider_installed_is_a_one_line_error(monkeypatch):
    _installed(monkeypatch, CPU)
    with pytest.raises(EncoderError) as info:
        load_encoder(providers="tensorrt,cuda")
    text = str(info.value)
    assert "\n" not in text
    assert text == (
        "none of the execution providers TensorrtExecutionProvider, CUDAExecutionProvider is in this "
        "onnxruntime (installed: CPUExecutionProvider)"
    )


@pytest.mark.filterwarnings("ignore:Specified provider 'CUDAExecutionProvider' is not in available")
def test_a_listed_provider_that_cannot_start_falls_back_with_a_warning(monkeypatch, caplog):
    # this onnxruntime reports CUDA, but its session cannot use it: onnxruntime runs the CPU instead
    _installed(monkeypatch, "CUDAExecutionProvider", CPU)
    with caplog.at_level("WARNING", logger="nsflow_ros.core.encoder"):
        enc = load_encoder(threads=2, providers="cuda,cpu")
    assert enc.provider == CPU and enc.tiled and len(enc._sessions) == 2
    assert [r.getMessage() for r in caplog.records] == [
        "execution provider CUDAExecutionProvider could not start; using CPUExecutionProvider"
    ]


def test_cpu_provider_gives_the_descriptors_of_a_plain_cpu_session():
    import onnxruntime

    img = _image(480, 752, seed=5)
    enc = load_encoder(threads=2, providers="cpu")
    assert enc.provider == CPU and enc.tiled
    assert all(s.get_providers() == [CPU] for s in enc._sessions)
    plain = onnxruntime.InferenceSession(str(enc.path), providers=[CPU])
    x = img[None, None].astype(np.float32)
    x *= 1.0 / 255.0
    (out,) = plain.run(None, {plain.get_inputs()[0].name: x})
    reference = load_encoder(threads=2, smoothing=Smoothing())
    unsmoothed = load_encoder(threads=2, providers=[CPU], smoothing=Smoothing())
    np.testing.assert_array_equal(unsmoothed(img), reference(img))
    np.testing.assert_allclose(unsmoothed(img), out[0].transpose(1, 2, 0), rtol=0, atol=1e-5)
    np.testing.assert_array_equal(enc(img), load_encoder(threads=2)(img))


def test_another_provider_runs_one_whole_frame_session_with_the_same_descriptors():
    # the Azure provider of the CPU build of onnxruntime stands in for a GPU one: it is not the CPU's
    import onnxruntime

    azure = "AzureExecutionProvider"
    assert azure in onnxruntime.get_available_providers()
    enc = load_encoder(threads=2, providers=[azure, "cpu"])
    assert enc.provider == azure and not enc.tiled and len(enc._sessions) == 1
    assert encoder_provider(enc) == azure and encoder_provider(IntensityEncoder()) == encoder_provider(None)
    img = _image(480, 752, seed=6)
    np.testing.assert_array_equal(enc(img), load_encoder(threads=2)(img))


def test_the_tracker_settings_providers_reach_the_session(monkeypatch):
    from nsflow_ros.core.camera import PinholeCamera
    from nsflow_ros.core.methods import make_method
    from nsflow_ros.core.tracker import FeatureTracker, TrackerSettings

    azure = "AzureExecutionProvider"
    assert make_method("nsflow", threads=1, providers=azure).encoder.provider == azure
    cam = PinholeCamera(fx=200.0, fy=200.0, cx=160.0, cy=120.0, width=320, height=240)
    tracker = FeatureTracker([cam], TrackerSettings(providers=f"{azure},cpu", num_threads=1))
    assert tracker.encoder.provider == azure
    assert FeatureTracker([cam], TrackerSettings(num_threads=1)).encoder.provider == CPU
    with pytest.raises(EncoderError, match="unknown execution provider 'gpu'"):
        TrackerSettings(providers="gpu")
    _installed(monkeypatch, CPU)
    with pytest.raises(EncoderError, match="none of the execution providers CUDAExecutionProvider"):
        FeatureTracker([cam], TrackerSettings(providers="cuda"))
