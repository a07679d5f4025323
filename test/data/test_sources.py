"""SensorSource over ROS 1 / ROS 2 bags and ASL folders: same streams, windows, and clear errors."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from nsflow_ros.data.errors import DataError
from nsflow_ros.data.messages import IMAGE, image_message, ros2_store
from nsflow_ros.data.perturb import IlluminationPerturber, perturb_records
from nsflow_ros.data.records import ImageRecord, ImuRecord
from nsflow_ros.data.sources import SensorSource, detect_kind, read_raw_messages, read_records
from nsflow_ros.data.writers import BagWriter, write_ros2_bag


def _same(a, b) -> bool:
    if type(a) is not type(b) or (a.topic, a.stamp_ns, a.frame_id) != (b.topic, b.stamp_ns, b.frame_id):
        return False
    if isinstance(a, ImageRecord):
        same_kind = a.encoding == b.encoding and a.image.dtype == b.image.dtype
        return same_kind and np.array_equal(a.image, b.image)
    return np.array_equal(a.gyro, b.gyro) and np.array_equal(a.accel, b.accel)


@pytest.fixture(scope="module")
def streams(sample_seq):
    return {fmt: list(SensorSource(sample_seq.path(fmt))) for fmt in ("asl", "ros2", "ros1")}


def test_the_three_formats_give_the_same_stream(sample_seq, streams):
    asl = streams["asl"]
    assert len(asl) == 2 * 10 + 101
    assert [r.stamp_ns for r in asl] == sorted(r.stamp_ns for r in asl)
    for fmt in ("ros2", "ros1"):
        assert len(streams[fmt]) == len(asl)
        assert all(_same(a, b) for a, b in zip(asl, streams[fmt], strict=True)), fmt
    first = asl[:3]
    assert [r.topic for r in first] == ["/imu0", "/cam0/image_raw", "/cam1/image_raw"]
    img = first[1]
    assert img.image.shape == (480, 752) and img.encoding == "mono8" and img.frame_id == "cam0"
    assert np.array_equal(img.image, sample_seq.image(0, 0))


def test_raw_cdr_is_identical_for_all_formats(sample_seq):
    raws = {fmt: list(read_raw_messages(sample_seq.path(fmt))) for fmt in ("asl", "ros2", "ros1")}
    for fmt in ("ros2", "ros1"):
        assert [(m.topic, m.msgtype, m.stamp_ns, m.cdr) for m in raws[fmt]] == \
               [(m.topic, m.msgtype, m.stamp_ns, m.cdr) for m in raws["asl"]]
    # Raw mode reads other types too.
    gt = list(read_raw_messages(sample_seq.ros1_path, topics=["/leica/position"]))
    assert len(gt) == 10 and gt[0].msgtype == "geometry_msgs/msg/PointStamped"
    assert gt[0].cdr[:4] == b"\x00\x01\x00\x00"


@pytest.mark.parametrize("fmt", ["asl", "ros2", "ros1"])
def test_topic_selection_and_time_window(sample_seq, fmt):
    path = sample_seq.path(fmt)
    assert detect_kind(path) == fmt
    recs = list(read_records(path, topics=["/cam1/image_raw"], start=0.1, duration=0.2))
    offsets_ms = [(r.stamp_ns - sample_seq.t0_ns) // 1_000_000 for r in recs]
    assert offsets_ms == [100, 150, 200, 250]
    assert all(r.topic == "/cam1/image_raw" and r.frame_id == "cam1" for r in recs)
    imu = list(read_records(path, topics=["/imu0"], start=0.49))
    assert len(imu) == 3 and all(isinstance(r, ImuRecord) for r in imu)


@pytest.mark.parametrize("fmt", ["asl", "ros2", "ros1"])
def test_missing_topic_is_named_with_the_topics_present(sample_seq, fmt):
    with pytest.raises(DataError, match=r"/cam2/image_raw not found in .*topics present: /cam0/image_raw"):
        list(read_records(sample_seq.path(fmt), topics=["/cam0/image_raw", "/cam2/image_raw"]))


def test_records_refuse_other_types_but_name_them(sample_seq):
    with pytest.raises(DataError, match=r"/leica/position .* has type geometry_msgs/msg/PointStamped"):
        list(read_records(sample_seq.ros2_dir, topics=["/leica/position"]))


def test_bad_paths_and_arguments(sample_seq, tmp_path):
    with pytest.raises(DataError, match=f"data set not found: {tmp_path / 'nope.bag'}"):
        SensorSource(tmp_path / "nope.bag")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DataError, match=r"notes\.txt is not a bag"):
        SensorSource(tmp_path / "notes.txt")
    with pytest.raises(DataError, match="neither a ROS 2 bag folder"):
        SensorSource(tmp_path)
    with pytest.raises(DataError, match="duration must be > 0"):
        SensorSource(sample_seq.asl_dir, duration=0)
    with pytest.raises(DataError, match="start must be >= 0"):
        SensorSource(sample_seq.ros1_path, start=-1.0)


@pytest.mark.parametrize("fmt, name", [("ros1", "sample.bag"), ("ros2", "ros2/ros2.mcap")])
def test_truncated_bag_yields_what_is_readable_then_fails(sample_seq, streams, tmp_path, fmt, name):
    src = sample_seq.root / name
    dst = tmp_path / name
    dst.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "ros2":
        shutil.copy(sample_seq.ros2_dir / "metadata.yaml", dst.parent / "metadata.yaml")
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * 0.55)])
    got = []
    with pytest.raises(DataError, match=rf"{dst}.* truncated"):
        for rec in SensorSource(tmp_path / name.split("/")[0]):
            got.append(rec)
    full = streams[fmt]
    assert 0.3 * len(full) < len(got) < len(full)
    assert all(_same(a, b) for a, b in zip(got, full[: len(got)], strict=True))


def test_sqlite3_bags_and_writing_a_perturbed_stream(sample_seq, tmp_path):
    pert = IlluminationPerturber("large", seed=1)
    n = write_ros2_bag(tmp_path / "pert", perturb_records(SensorSource(sample_seq.asl_dir), pert),
                       storage="sqlite3")
    assert n == 121 and detect_kind(tmp_path / "pert") == "ros2"
    back = list(SensorSource(tmp_path / "pert"))
    expected = list(perturb_records(SensorSource(sample_seq.asl_dir), pert))
    assert all(_same(a, b) for a, b in zip(back, expected, strict=True)) and len(back) == len(expected)
    assert not np.array_equal(back[1].image, sample_seq.image(0))
    with pytest.raises(DataError, match="exists already"):
        write_ros2_bag(tmp_path / "pert", [])
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind


def test_unknown_encoding_in_a_bag_is_named(tmp_path):
    msg = image_message(ros2_store(), 1_000, "cam0", np.zeros((4, 6), np.uint8), "mono8")
    msg.encoding = "bayer_rggb8"
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_image("/cam0/image_raw", 500, np.zeros((4, 6), np.uint8), "cam0")
        bag.write_message("/cam0/image_raw", IMAGE, 1_000, msg)
    got = []
    with pytest.raises(DataError, match="/cam0/image_raw: unsupported image encoding 'bayer_rggb8'"):
        got.extend(SensorSource(tmp_path / "bag"))
    assert len(got) == 1


def test_uma_vi_layouts(sample_seq, tmp_path):
    # ASL with an exposure column in camN/data.csv; its IMU requested by UMA-VI's bag name.
    asl = tmp_path / "uma"
    shutil.copytree(sample_seq.asl_dir, asl)
    csv = asl / "mav0" / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join([lines[0] + ",exposure [ns]"] + [ln + ",2000000" for ln in lines[1:]]) + "\n")
    recs = list(read_records(asl, topics=["/cam0/image_raw", "/imu0/data"], duration=0.1))
    assert {r.topic for r in recs} == {"/cam0/image_raw", "/imu0/data"}
    assert sum(isinstance(r, ImageRecord) for r in recs) == 2
    # A bag with /imu0/data: the default topics find it.
    with BagWriter(tmp_path / "uma.bag", ros1=True) as bag:
        bag.write_imu("/imu0/data", 10, [0, 0, 0], [9.8, 0, 0])
        bag.write_image("/cam0/image_raw", 20, np.zeros((3, 4), np.uint16), "cam0", "mono16")
    recs = list(read_records(tmp_path / "uma.bag"))
    assert [r.topic for r in recs] == ["/imu0/data", "/cam0/image_raw"] and recs[1].encoding == "mono16"
