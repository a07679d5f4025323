"""The replay stream: bytes passed through, perturbation from a seed, remaps, compressed images."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.data.replay import ReplayError, ReplayOptions, parse_remaps, replay_records, replay_stream
from nsflow_ros.data.sample import make_sample_sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    # one sequence for the replay tests of data/, ros/ and vins/: make_sample_sequence reuses it
    root = tmp_path_factory.getbasetemp() / "replay_seq"
    return make_sample_sequence(
        root, seed=3, duration=1.0, stereo=False, formats=("asl", "ros2"), progress=False
    )


def test_unperturbed_stream_passes_bytes_through(seq):
    from nsflow_ros.data.sources import SensorSource

    a = list(replay_stream(ReplayOptions(seq.ros2_dir)))
    b = list(SensorSource(seq.ros2_dir).raw_messages())
    assert len(a) == len(b) > 20
    assert all(x.cdr == y.cdr and x.topic == y.topic for x, y in zip(a, b, strict=True))


def test_perturbed_replay_is_reproducible_from_its_seed(seq):
    def images(seed, level="large"):
        opts = ReplayOptions(seq.asl_dir, ["/cam0/image_raw"], perturb=level, seed=seed)
        return [m.cdr for m in replay_stream(opts)]

    first, again, other = images(5), images(5), images(6)
    assert first == again
    assert first != other
    plain = images(5, "none")
    assert len(plain) == len(first) and plain != first


def test_remaps_rename_topics(seq):
    opts = ReplayOptions(seq.asl_dir, ["/cam0/image_raw"], remap=parse_remaps(["/cam0/image_raw:=/left"]))
    assert {r.topic for r in replay_records(opts)} == {"/left"}
    with pytest.raises(ReplayError, match="bad remap 'cam0'"):
        parse_remaps(["cam0"])
    with pytest.raises(ReplayError, match="rate"):
        ReplayOptions(seq.asl_dir, rate=-1)


def test_compressed_replay_publishes_what_image_transport_would(seq):
    from nsflow_ros.data.images import decode_compressed
    from nsflow_ros.data.messages import COMPRESSED_IMAGE, ros2_store

    raw = list(replay_records(ReplayOptions(seq.asl_dir, ["/cam0/image_raw"])))
    store = ros2_store()
    sizes = {}
    for codec, quality in (("png", 90), ("jpeg", 90), ("jpeg", 50)):
        opts = ReplayOptions(seq.asl_dir, ["/cam0/image_raw"], remap={"/cam0/image_raw": "/left"},
                             compress=codec, jpeg_quality=quality)
        msgs = list(replay_stream(opts))
        assert len(msgs) == len(raw) and {m.topic for m in msgs} == {"/left/compressed"}
        assert {m.msgtype for m in msgs} == {COMPRESSED_IMAGE}
        assert [m.stamp_ns for m in msgs] == [r.stamp_ns for r in raw]
        sizes[codec, quality] = sum(len(m.cdr) for m in msgs)
        for m, r in zip(msgs, raw, strict=True):
            msg = store.deserialize_cdr(m.cdr, COMPRESSED_IMAGE)
            assert msg.format == f"mono8; {codec} compressed mono8"
            assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == r.stamp_ns
            pixels, enc = decode_compressed(msg)
            assert enc == "mono8" and pixels.shape == r.image.shape
            if codec == "png":
                np.testing.assert_array_equal(pixels, r.image)
            else:
                assert np.abs(pixels.astype(int) - r.image).mean() < 3.0
    assert sizes["jpeg", 50] < sizes["jpeg", 90] < sizes["png", 90] < sum(r.image.size for r in raw)
    with pytest.raises(ReplayError, match="compress"):
        ReplayOptions(seq.asl_dir, compress="webp")
    with pytest.raises(ReplayError, match="JPEG quality"):
        ReplayOptions(seq.asl_dir, compress="jpeg", jpeg_quality=101)


def test_compressed_imu_passes_through(seq):
    msgs = list(replay_stream(ReplayOptions(seq.asl_dir, compress="png")))
    assert {m.topic for m in msgs} == {"/cam0/image_raw/compressed", "/imu0"}


def test_dark_replay_comes_from_the_perturbation_registry(seq):
    from nsflow_ros.data.perturb import make_perturber

    opts = ReplayOptions(seq.asl_dir, ["/cam0/image_raw"], perturb="dark", seed=2)
    plain = list(replay_records(ReplayOptions(seq.asl_dir, ["/cam0/image_raw"])))
    dark = list(replay_records(opts))
    p = make_perturber("dark", 2)
    pairs = zip(plain, dark, strict=True)
    assert all(np.array_equal(d.image, p(r.image, r.stamp_ns * 1e-9)) for r, d in pairs)
    with pytest.raises(ReplayError, match="perturb must be one of none, small, large, dark, got 'night'"):
        ReplayOptions(seq.asl_dir, perturb="night")
