"""Feature message layouts (VINS-Fusion, VINS-Mono) and the debug image."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.core.tracker import CameraFeatures, FeatureTracker, FrameFeatures, TrackerSettings
from nsflow_ros.data.sample import make_sample_sequence
from nsflow_ros.vins.config import load_vins_config
from nsflow_ros.vins.draw import draw_tracks, track_colour
from nsflow_ros.vins.messages import (
    COVARIANCE_CHANNELS,
    ID_MODULUS,
    FeatureMessageError,
    decode,
    decode_covariances,
    decode_fusion,
    decode_mono,
    encode,
    encode_fusion,
    encode_mono,
    published_ids,
)

ROOT = Path(__file__).resolve().parents[2]


def _cam(cam_id: int, ids, counts) -> CameraFeatures:
    ids = np.asarray(ids, np.int64)
    n = ids.size
    px = np.c_[10.0 * ids + cam_id, 5.0 * ids + 0.25]
    un = np.c_[0.01 * ids - cam_id * 0.1, -0.02 * ids]
    vel = np.c_[0.5 * ids, -0.25 * ids + cam_id]
    prev = np.where(np.asarray(counts)[:, None] > 1, px - 1.0, np.nan)
    return CameraFeatures(cam_id, ids, px, un, vel, np.asarray(counts, np.int64), prev.reshape(n, 2))


@pytest.fixture
def stereo_frame() -> FrameFeatures:
    # tracker order is by track length, not by id; right has a subset of the left ids
    left = _cam(0, [7, 2, 11, 5], [3, 1, 1, 25])
    right = _cam(1, [11, 7, 5], [1, 3, 25])
    return FrameFeatures(12.5, (left, right), (320, 240))


def test_fusion_layout_sorted_by_id_camera_0_first(stereo_frame):
    cloud = encode_fusion(stereo_frame)
    assert cloud.channels.shape == (9, 7) and cloud.points.dtype == np.float32
    assert np.all(cloud.channels[6:] == 0) and np.all(cloud.points[:, 2] == 1.0)
    assert cloud.channels[0].tolist() == [2, 5, 5, 7, 7, 11, 11]
    assert cloud.channels[1].tolist() == [0, 0, 1, 0, 1, 0, 1]
    feats = decode_fusion(cloud.points, cloud.channels)
    for cam in stereo_frame.cameras:
        for j, fid in enumerate(cam.ids):
            (_, row), = [e for e in feats[int(fid)] if e[0] == cam.camera_id]
            expect = [*cam.undistorted[j], 1.0, *cam.pixels[j], *cam.velocities[j]]
            np.testing.assert_allclose(row, expect, rtol=1e-6, atol=1e-6)
    for entries in feats.values():
        assert [c for c, _ in entries] == sorted(c for c, _ in entries)  # camera 0 before camera 1


def test_mono_layout_drops_new_points_and_packs_camera_into_the_id(stereo_frame):
    cloud = encode_mono(stereo_frame, num_of_cam=2)
    assert cloud.channels.shape == (5, 4)
    assert cloud.channels[0].tolist() == [7 * 2, 5 * 2, 7 * 2 + 1, 5 * 2 + 1]
    feats = decode_mono(cloud.points, cloud.channels, num_of_cam=2)
    assert sorted(feats) == [5, 7] and [c for c, _ in feats[7]] == [0, 1]
    mono = FrameFeatures(1.0, (stereo_frame.cameras[0],), (320, 240))
    single = decode(*(lambda c: (c.points, c.channels))(encode(mono, "mono")), "mono")
    np.testing.assert_allclose(single[5][0][1][3:5], mono.cameras[0].pixels[3], rtol=1e-6)


def test_large_ids_survive_float32_channels():
    cam = _cam(0, [2**24 - 3], [2])
    frame = FrameFeatures(0.0, (cam,), (320, 240))
    cloud = encode_fusion(frame)
    assert list(decode_fusion(cloud.points, cloud.channels)) == [2**24 - 3]


def test_ids_past_float32_precision_wrap_and_round_trip_exactly():
    limit = 2**24
    assert limit == ID_MODULUS and float(np.float32(limit + 1)) == limit  # why: float32 loses them
    left = _cam(0, [limit - 2, limit + 1, limit - 1, limit, 3 * limit + 5], [2, 2, 2, 2, 2])
    right = _cam(1, [limit + 1, limit - 2, limit], [2, 2, 2])
    frame = FrameFeatures(0.0, (left, right), (320, 240))
    cloud = encode_fusion(frame)
    # sorted by the published id, camera 0 before camera 1 within an id
    assert cloud.channels[0].tolist() == [0, 0, 1, 1, 5, limit - 2, limit - 2, limit - 1]
    assert cloud.channels[1].tolist() == [0, 1, 0, 1, 0, 0, 1, 0]
    feats = decode_fusion(cloud.points, cloud.channels)
    for cam in frame.cameras:
        for j, fid in enumerate(cam.ids):
            (_, row), = [e for e in feats[int(fid) % limit] if e[0] == cam.camera_id]
            np.testing.assert_allclose(row[3:5], cam.pixels[j], rtol=1e-6)
    # VINS-Mono packs id * NUM_OF_CAM + camera into one float32: ids wrap at 2^24 / NUM_OF_CAM
    mono = encode_mono(frame, num_of_cam=2)
    assert mono.channels[0].max() < limit
    packed = decode_mono(mono.points, mono.channels, num_of_cam=2)
    half = limit // 2
    assert sorted(packed) == sorted({int(i) % half for i in left.ids})
    assert {fid: [c for c, _ in e] for fid, e in packed.items()}[(limit + 1) % half] == [0, 1]
    single = encode_mono(FrameFeatures(0.0, (left,), (320, 240)), num_of_cam=1)
    assert sorted(decode_mono(single.points, single.channels)) == sorted(int(i) % limit for i in left.ids)
    assert published_ids(np.array([limit + 7]), "mono", 3).tolist() == [(limit + 7) % (limit // 3)]
    with pytest.raises(FeatureMessageError, match="num_of_cam"):
        published_ids(np.array([1]), "mono", 0)


def test_tracker_ids_crossing_2_24_stay_unique_in_messages(tmp_path):
    seq = make_sample_sequence(tmp_path / "seq", seed=0, duration=0.5, stereo=True, formats=("asl",),
                               progress=False)
    cfg = load_vins_config(ROOT / "config" / "euroc" / "euroc_stereo_imu_config.yaml")
    tracker = FeatureTracker(list(cfg.cameras), TrackerSettings(method="klt", stereo=True))
    tracker._next_id = ID_MODULUS - 40  # no public way to start the counter elsewhere
    published: dict[int, int] = {}  # published id -> tracker id, over the whole run
    crossed = False
    for i in range(len(seq)):
        frame = tracker.process(seq.time(i), seq.image(i, 0), seq.image(i, 1))
        crossed |= any(int(c.ids.max(initial=0)) >= ID_MODULUS for c in frame.cameras)
        cloud = encode_fusion(frame)
        feats = decode_fusion(cloud.points, cloud.channels)
        expected = {int(fid) for c in frame.cameras for fid in c.ids}
        assert sorted(feats) == sorted(fid % ID_MODULUS for fid in expected)  # no two ids merged
        for fid in expected:
            assert published.setdefault(fid % ID_MODULUS, fid) == fid  # never two tracker ids on one
        for entries in feats.values():
            assert [c for c, _ in entries] in ([0], [0, 1])
        mono = encode_mono(frame, num_of_cam=2)
        packed = decode_mono(mono.points, mono.channels, num_of_cam=2)
        kept = {int(fid) % (ID_MODULUS // 2) for c in frame.cameras for fid in c.ids[c.track_counts > 1]}
        assert sorted(packed) == sorted(kept)
    assert crossed and tracker.next_id > ID_MODULUS + 100


def test_decoders_reject_what_the_estimator_would_choke_on(stereo_frame):
    cloud = encode_fusion(stereo_frame)
    with pytest.raises(FeatureMessageError, match="6-8"):
        decode_fusion(cloud.points, cloud.channels[:6])
    with pytest.raises(FeatureMessageError, match="at least 6"):
        decode_fusion(cloud.points, cloud.channels[:5])
    bad = cloud.points.copy()
    bad[0, 2] = 0.5
    with pytest.raises(FeatureMessageError, match="z == 1"):
        decode_fusion(bad, cloud.channels)
    with pytest.raises(FeatureMessageError, match="layout"):
        encode(stereo_frame, "ros1")  # type: ignore[arg-type]
    with pytest.raises(FeatureMessageError, match="num_of_cam"):
        encode_mono(stereo_frame, num_of_cam=1)


def test_empty_frame_encodes_to_an_empty_cloud():
    empty = FrameFeatures(0.0, (_cam(0, [], []),), (320, 240))
    for layout in ("fusion", "mono"):
        cloud = encode(empty, layout)
        assert len(cloud) == 0 and cloud.channels.shape[1] == 0


def test_debug_image_colours_and_layout(stereo_frame):
    assert track_colour(1) == (242, 0, 13)
    assert track_colour(20) == track_colour(99) == (0, 0, 255)
    img = np.full((240, 320), 128, np.uint8)
    out = draw_tracks(stereo_frame, img, img)
    assert out.shape == (240, 640, 3) and out.dtype == np.uint8
    left = stereo_frame.cameras[0]
    x, y = np.rint(left.pixels[3]).astype(int)  # 25 frames: red
    assert tuple(out[y, x + 2]) == (0, 0, 255)
    rx, ry = np.rint(stereo_frame.cameras[1].pixels[0]).astype(int)
    assert tuple(out[ry, rx + 320 + 2]) == (0, 255, 0)
    assert draw_tracks(stereo_frame, img).shape == (240, 320, 3)


def _with_covariance(frame: FrameFeatures) -> FrameFeatures:
    cams = []
    for c in frame.cameras:
        n = len(c)
        cov = np.c_[0.1 + 0.01 * c.ids + c.camera_id, 0.001 * c.ids, 0.2 + 0.02 * c.ids].reshape(n, 3)
        cams.append(replace(c, covariance=cov))
    return replace(frame, cameras=tuple(cams))


def test_fusion_covariance_is_channels_9_to_11_and_the_estimator_reads_the_same(stereo_frame):
    cov_frame = _with_covariance(stereo_frame)
    plain, cloud = encode_fusion(stereo_frame), encode_fusion(cov_frame)
    assert plain.channels.shape[0] == 9 and cloud.channels.shape == (12, 7)
    assert cloud.names[9:] == COVARIANCE_CHANNELS
    np.testing.assert_array_equal(cloud.channels[:9], plain.channels)  # what VINS-Fusion reads: unchanged
    np.testing.assert_array_equal(cloud.points, plain.points)
    stock = decode_fusion(cloud.points, cloud.channels)
    stock_plain = decode_fusion(plain.points, plain.channels)
    assert stock.keys() == stock_plain.keys()
    for fid in stock:
        for (ca, ra), (cb, rb) in zip(stock[fid], stock_plain[fid], strict=True):
            assert ca == cb and np.array_equal(ra, rb)
    covs = decode_covariances(cloud.points, cloud.channels, "fusion")
    for cam in cov_frame.cameras:
        for j, fid in enumerate(cam.ids):
            (got,) = [v for c, v in covs[int(fid)] if c == cam.camera_id]
            np.testing.assert_allclose(got, cam.covariance[j], rtol=1e-6)
    assert decode_covariances(plain.points, plain.channels, "fusion") == {}


def test_mono_covariance_only_when_the_frame_carries_it(stereo_frame):
    plain = encode_mono(stereo_frame, num_of_cam=2)
    cloud = encode_mono(_with_covariance(stereo_frame), num_of_cam=2)
    assert plain.channels.shape[0] == 5 and cloud.channels.shape[0] == 8
    np.testing.assert_array_equal(cloud.channels[:5], plain.channels)
    covs = decode_covariances(cloud.points, cloud.channels, "mono", num_of_cam=2)
    right = _with_covariance(stereo_frame).cameras[1]
    j = int(np.flatnonzero(right.ids == 7)[0])
    np.testing.assert_allclose(dict(covs[7])[1], right.covariance[j], rtol=1e-6)
