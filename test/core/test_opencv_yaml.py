"""Safe OpenCV FileStorage YAML reading: conversion to Python values and one error type for bad files."""

from __future__ import annotations

import contextlib
import random
import re
from pathlib import Path

import numpy as np
import pytest

from nsflow_ros.core.errors import CoreError
from nsflow_ros.core.opencv_yaml import OpenCVYamlError, read_opencv_yaml

CONFIG = Path(__file__).resolve().parents[2] / "config"


def write(tmp_path: Path, content: str | bytes, name: str = "f.yaml") -> Path:
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path


def test_values_are_converted(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "%YAML:1.0\n---\n"
        'count: 150\nneg: -3\nratio: 1.0\nsmall: 1e-3\ntopic: "/cam0/image_raw"\nbare: hello\n'
        "nested:\n   a: 1\n   b: [1, 2.5, x]\n"
        "T: !!opencv-matrix\n   rows: 2\n   cols: 3\n   dt: d\n   data: [1, 2, 3, 4, 5, 6.5]\n",
    )
    data = read_opencv_yaml(path)
    assert data["count"] == 150 and type(data["count"]) is int
    assert data["neg"] == -3
    assert data["ratio"] == 1.0 and type(data["ratio"]) is float
    assert data["small"] == 1e-3
    assert data["topic"] == "/cam0/image_raw" and data["bare"] == "hello"
    assert data["nested"] == {"a": 1, "b": [1, 2.5, "x"]}
    matrix = data["T"]
    assert isinstance(matrix, np.ndarray) and matrix.dtype == np.float64
    np.testing.assert_array_equal(matrix, [[1, 2, 3], [4, 5, 6.5]])


def test_header_only_is_empty(tmp_path: Path) -> None:
    assert read_opencv_yaml(write(tmp_path, "%YAML:1.0\n")) == {}


def test_shipped_config_parses() -> None:
    data = read_opencv_yaml(CONFIG / "euroc" / "euroc_stereo_imu_config.yaml")
    assert data["body_T_cam1"].shape == (4, 4)
    assert data["num_of_cam"] == 2


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "file is empty"),
        ("key: 1\n", "first line must be '%YAML:1.0'"),
        ("hello world\n", "first line must be '%YAML:1.0'"),
        (b"%YAML:1.0\n\x00\x01\x02", "binary data"),
        (b"%YAML:1.0\nkey: \xff\xfe\n", "not UTF-8 text"),
        ("%YAML:1.0\nkey: [1, 2\nfoo: {\n", "cannot parse: line 3"),
        ("%YAML:1.0\n\tkey: 1\n", "cannot parse: line 2: Tabs"),
        ("%YAML:1.0\n- 1\n- 2\n", "top level must be a mapping"),
        ("%YAML:1.0\na: 1\na: 2\n", "duplicate key 'a'"),
        ("%YAML:1.0\nm:\n   x: 1\n   x: 2\n", "duplicate key 'm/x'"),
        (
            "%YAML:1.0\nm: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n   data: [1, 2, 3]\n",
            "key 'm': malformed matrix",
        ),
    ],
)
def test_bad_files_raise_naming_the_file(tmp_path: Path, content: str | bytes, message: str) -> None:
    path = write(tmp_path, content)
    with pytest.raises(OpenCVYamlError, match=re.escape(message)) as info:
        read_opencv_yaml(path)
    assert str(info.value).startswith(f"{path}: ")
    assert isinstance(info.value, CoreError)


def test_missing_and_directory(tmp_path: Path) -> None:
    with pytest.raises(OpenCVYamlError, match="does not exist"):
        read_opencv_yaml(tmp_path / "missing.yaml")
    with pytest.raises(OpenCVYamlError, match="not a regular file"):
        read_opencv_yaml(tmp_path)


def test_damaged_copies_never_crash(tmp_path: Path) -> None:
    # cv2.FileStorage is fragile on bad input; every damaged copy must parse or raise OpenCVYamlError.
    source = (CONFIG / "euroc" / "euroc_stereo_imu_config.yaml").read_bytes()
    rng = random.Random(7)
    path = tmp_path / "damaged.yaml"
    for _ in range(200):
        damaged = bytearray(source)
        if rng.random() < 0.5:
            damaged = damaged[: rng.randrange(len(damaged))]
        else:
            for _ in range(rng.randrange(1, 6)):
                damaged[rng.randrange(len(damaged))] = rng.choice(b" :[]{}-!#\"',\n%&*|>0a")
        path.write_bytes(bytes(damaged))
        with contextlib.suppress(OpenCVYamlError):
            read_opencv_yaml(path)
