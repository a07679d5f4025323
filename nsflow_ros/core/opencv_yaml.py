"""Safe reading of OpenCV FileStorage YAML files (the format of VINS configs and camodocal camera files).

PyYAML rejects their ``%YAML:1.0`` header and ``!!opencv-matrix`` maps, so they are parsed with
``cv2.FileStorage`` as VINS does; its binding is fragile on bad input (``SystemError``, stderr output,
asserts), so the file is checked first, parsed from memory and every failure becomes one
:class:`OpenCVYamlError` naming the file.

Values become ``int``, ``float``, ``str``, ``list`` and ``dict`` (duplicate keys are an error), and
``!!opencv-matrix`` maps float64 arrays of shape (rows, cols); a file holding only the header gives {}.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.core.errors import CoreError

__all__ = ["OpenCVYamlError", "read_opencv_yaml"]

_HEADER = "%YAML"
_MATRIX_KEYS = frozenset({"rows", "cols", "dt", "data"})
_MAX_BYTES = 16 * 1024 * 1024  # VINS configs are a few kB; anything this big is not one

# cv::FileNode type codes (cv2.FileNode_* constants, stable since OpenCV 3).
_NONE, _INT, _REAL, _STR, _SEQ, _MAP = 0, 1, 2, 3, 4, 5


class OpenCVYamlError(CoreError):
    """An OpenCV YAML file is missing, unreadable or malformed; the message names the file."""


def _cv_reason(err: BaseException) -> str:
    """Shorten a cv2.error text to its reason, e.g. ``line 3: Incorrect indentation``."""
    text = str(err.__cause__ or err).strip()
    found = re.search(r"in function '[^']*\((\d+)\): (.*)'", text)
    if found:
        return f"line {found.group(1)}: {found.group(2)}"
    found = re.search(r"error: \(-?\d+:[^)]*\) (.*)", text)
    return found.group(1) if found else text


def _read_text(path: Path) -> str:
    if not path.exists():
        raise OpenCVYamlError(f"{path}: file does not exist")
    if not path.is_file():
        raise OpenCVYamlError(f"{path}: not a regular file")
    try:
        size = path.stat().st_size
        if size > _MAX_BYTES:
            raise OpenCVYamlError(f"{path}: file is {size} bytes, too large for an OpenCV YAML config")
        raw = path.read_bytes()
    except OSError as err:
        raise OpenCVYamlError(f"{path}: cannot read file: {err.strerror or err}") from err
    if not raw:
        raise OpenCVYamlError(f"{path}: file is empty")
    if b"\0" in raw:
        raise OpenCVYamlError(f"{path}: binary data, not an OpenCV YAML file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise OpenCVYamlError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from err
    text = text.lstrip("\ufeff")
    first = text.split("\n", 1)[0].strip()
    if not first.startswith(_HEADER):
        shown = first if len(first) <= 40 else first[:37] + "..."
        raise OpenCVYamlError(f"{path}: first line must be '%YAML:1.0' (OpenCV FileStorage), got {shown!r}")
    return text


def _convert(node: cv2.FileNode, where: str, path: Path) -> Any:
    kind = node.type()
    if kind == _NONE:
        return None
    if kind == _INT:
        return round(node.real())
    if kind == _REAL:
        return float(node.real())
    if kind == _STR:
        return node.string()
    if kind == _SEQ:
        return [_convert(node.at(i), f"{where}[{i}]", path) for i in range(node.size())]
    if kind == _MAP:
        keys = list(node.keys())
        if set(keys) == _MATRIX_KEYS:
            try:
                mat = node.mat()
            except (cv2.error, SystemError) as err:
                raise OpenCVYamlError(f"{path}: key '{where}': malformed matrix: {_cv_reason(err)}") from err
            if mat is None:
                raise OpenCVYamlError(f"{path}: key '{where}': malformed matrix")
            return np.array(mat, dtype=np.float64).reshape(mat.shape[0], -1)
        out: dict[str, Any] = {}
        for key in keys:
            child = f"{where}/{key}" if where else key
            if key in out:
                raise OpenCVYamlError(f"{path}: duplicate key '{child}'")
            out[key] = _convert(node.getNode(key), child, path)
        return out
    raise OpenCVYamlError(f"{path}: key '{where}': unsupported FileStorage node type {kind}")


def read_opencv_yaml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read an OpenCV FileStorage YAML file's top-level mapping into plain Python values.

    Raises:
        OpenCVYamlError: the file is missing, not a file, unreadable, binary, lacks the ``%YAML`` header,
            does not parse, has a duplicate key or a malformed matrix, or its top level is not a mapping.
    """
    path = Path(path)
    text = _read_text(path)
    try:
        storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as err:
        raise OpenCVYamlError(f"{path}: cannot parse: {_cv_reason(err)}") from err
    try:
        if not storage.isOpened():
            raise OpenCVYamlError(f"{path}: cannot parse (OpenCV did not open it)")
        root = storage.root()
        if root.type() == _NONE:
            return {}
        if root.type() != _MAP:
            raise OpenCVYamlError(f"{path}: top level must be a mapping of keys, got a sequence or a scalar")
        try:
            return _convert(root, "", path)
        except (cv2.error, SystemError) as err:
            raise OpenCVYamlError(f"{path}: cannot read: {_cv_reason(err)}") from err
    finally:
        storage.release()
