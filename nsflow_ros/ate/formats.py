"""Trajectory files: reading, writing and detecting EuRoC, TUM and VINS formats.

Formats (``fmt`` names):

``euroc``
    EuRoC / ASL ground truth ``mav0/state_groundtruth_estimate0/data.csv``: a ``#`` header line, then
    rows ``t_ns, px, py, pz, qw, qx, qy, qz[, ...]`` (the first eight columns are used). An ASL sequence
    folder is accepted wherever a trajectory file is.
``tum``
    TUM RGB-D: space-separated ``t x y z qx qy qz qw`` with ``t`` in seconds, ``#`` comments allowed.
``vins``
    VINS-Fusion ``vio.csv`` / ``vio_loop.csv`` and VINS-Mono ``vins_result_*.csv``: no header, rows
    ``t_ns, px, py, pz, qw, qx, qy, qz[, vx, vy, vz],`` with integer nanoseconds and a trailing comma.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from nsflow_ros.ate.errors import ATEError
from nsflow_ros.ate.trajectory import Trajectory

__all__ = [
    "ASL_GROUND_TRUTH",
    "ESTIMATE_NAMES",
    "FORMATS",
    "detect_format",
    "read_trajectory",
    "resolve_trajectory_path",
    "write_trajectory",
]

FORMATS: tuple[str, ...] = ("euroc", "tum", "vins")
"""Names accepted for ``fmt`` (``None`` or ``"auto"``: detect)."""

ASL_GROUND_TRUTH: tuple[str, ...] = (
    "mav0/state_groundtruth_estimate0/data.csv",
    "state_groundtruth_estimate0/data.csv",
)
"""Ground-truth files looked for, in this order, when a directory is given (an ASL sequence or its mav0/)."""

ESTIMATE_NAMES: tuple[str, ...] = (
    "vio.csv",
    "vins_result_no_loop.csv",
    "trajectory.tum",
    "trajectory.txt",
    "trajectory.csv",
)
"""Estimate files looked for, in this order, in a run directory; then a single vins_result_*.csv."""

_EUROC_HEADER = (
    "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],"
    "v_RS_R_x [m s^-1],v_RS_R_y [m s^-1],v_RS_R_z [m s^-1],b_w_RS_S_x [rad s^-1],b_w_RS_S_y [rad s^-1],"
    "b_w_RS_S_z [rad s^-1],b_a_RS_S_x [m s^-2],b_a_RS_S_y [m s^-2],b_a_RS_S_z [m s^-2]"
)
_BINARY = re.compile(r"[\x00-\x08\x0e-\x1f\x7f]")
"""Control characters no text trajectory holds (tab, newlines, form feed and vertical tab are allowed)."""
_NS_FIELDS = ("t_ns", "px", "py", "pz", "qw", "qx", "qy", "qz")
_TUM_FIELDS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _split(text: str) -> list[str]:
    """Split a data line: on commas (dropping one trailing empty field) or else on whitespace."""
    if "," in text:
        parts = [p.strip() for p in text.split(",")]
        if parts and parts[-1] == "":
            parts.pop()
        return parts
    return text.split()


def resolve_trajectory_path(path: str | Path) -> Path:
    """The trajectory file a path names: the file itself, or in a directory the first of
    :data:`ASL_GROUND_TRUTH`, then :data:`ESTIMATE_NAMES`, then the one ``vins_result_*.csv``.

    Raises:
        ATEError: when the path does not exist, or a directory holds no known trajectory file, or several
            ``vins_result_*.csv`` files (named, so the caller can pick one).
    """
    path = Path(path)
    if path.is_file():
        return path
    if not path.exists():
        raise ATEError(f"{path}: no such file or directory", reason="missing")
    if not path.is_dir():
        raise ATEError(f"{path}: not a regular file or directory")
    for rel in (*ASL_GROUND_TRUTH, *ESTIMATE_NAMES):
        if (path / rel).is_file():
            return path / rel
    results = sorted(path.glob("vins_result_*.csv"))
    if len(results) == 1:
        return results[0]
    if len(results) > 1:
        names = ", ".join(p.name for p in results)
        raise ATEError(f"{path}: several VINS result files ({names}); name the one to score")
    tried = ", ".join((*ASL_GROUND_TRUTH, *ESTIMATE_NAMES, "vins_result_*.csv"))
    raise ATEError(f"{path}: directory holds no trajectory file (looked for {tried})", reason="missing")


def _read_lines(path: Path) -> tuple[list[str], list[tuple[int, str]]]:
    """(header lines, numbered data lines): ``#`` lines and a first line of non-numbers are headers."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ATEError(
            f"{path}: cannot parse it as a trajectory: not a text file ({exc.reason} at byte {exc.start})",
            reason="malformed",
        ) from exc
    except OSError as exc:
        raise ATEError(f"{path}: cannot read ({exc.strerror})") from exc
    binary = _BINARY.search(text)
    if binary is not None:  # random bytes can decode as UTF-8; text files hold no control characters
        raise ATEError(
            f"{path}: cannot parse it as a trajectory: not a text file (control character "
            f"{binary.group()!r} at character {binary.start()})",
            reason="malformed",
        )
    headers: list[str] = []
    data: list[tuple[int, str]] = []
    plain_header = False
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            headers.append(line)
            continue
        # one header line without '#' is allowed; a second line of non-numbers is a bad data row
        if not data and not plain_header and not any(_is_number(p) for p in _split(line) if p):
            headers.append(line)
            plain_header = True
            continue
        data.append((lineno, line))
    return headers, data


def _detect(path: Path, headers: list[str], data: list[tuple[int, str]]) -> str:
    """The format of the first data line: 8 space-separated fields are TUM; comma-separated ones EuRoC
    after a header with commas or with 17 or more fields, else VINS (whose first eight fields agree)."""
    if not data:
        raise ATEError(f"{path}: empty trajectory file (no data rows)", reason="empty")
    lineno, first = data[0]
    if "," in first:
        if any("," in h for h in headers) or len(_split(first)) >= 17:
            return "euroc"
        return "vins"
    n = len(first.split())
    if n == 8:
        return "tum"
    raise ATEError(
        f"{path}, line {lineno}: cannot detect the trajectory format: {n} space-separated fields "
        f"(TUM needs 8: t x y z qx qy qz qw) and no commas (EuRoC / VINS csv); name the format "
        f"(one of {', '.join(FORMATS)})",
        reason="malformed",
    )


def _check_format(fmt: str | None) -> str | None:
    if fmt is None or fmt == "auto":
        return None
    if fmt not in FORMATS:
        raise ATEError(f"unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)} or auto")
    return fmt


def detect_format(path: str | Path) -> str:
    """The :data:`FORMATS` name of a trajectory file (or of the file a directory resolves to).

    Raises:
        ATEError: when the file is missing, empty, or its first data line fits no format.
    """
    file = resolve_trajectory_path(path)
    headers, data = _read_lines(file)
    return _detect(file, headers, data)


def _parse_float(path: Path, lineno: int, field: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ATEError(
            f"{path}, line {lineno}: field {field} is not a number: {text!r}", reason="malformed"
        ) from None
    if not math.isfinite(value):
        raise ATEError(
            f"{path}, line {lineno}: field {field} is {text} (NaN/inf; diverged estimator?)", reason="nan"
        )
    return value


def _parse_ns(path: Path, lineno: int, text: str) -> float:
    """Nanosecond stamp -> seconds; integers are divided exactly (no rounding to float first)."""
    try:
        return int(text) / 1_000_000_000
    except ValueError:
        return _parse_float(path, lineno, "t_ns", text) / 1e9


def _parse(path: Path, fmt: str, data: list[tuple[int, str]], name: str) -> Trajectory:
    if not data:
        raise ATEError(f"{path}: empty trajectory file (no data rows)", reason="empty")
    n = len(data)
    stamps = np.empty(n)
    positions = np.empty((n, 3))
    quats = np.empty((n, 4))
    for row, (lineno, line) in enumerate(data):
        if fmt == "tum":
            parts = line.split()
            if len(parts) != 8:
                raise ATEError(
                    f"{path}, line {lineno}: expected 8 space-separated fields (t x y z qx qy qz qw), "
                    f"got {len(parts)}: {line!r}",
                    reason="malformed",
                )
            vals = [_parse_float(path, lineno, f, p) for f, p in zip(_TUM_FIELDS, parts, strict=True)]
            stamps[row] = vals[0]
            positions[row] = vals[1:4]
            quats[row] = (vals[7], vals[4], vals[5], vals[6])
        else:
            parts = [p.strip() for p in line.split(",")]
            if len(parts) > 1 and parts[-1] == "":
                parts.pop()
            if len(parts) < 8 or "" in parts[:8]:
                raise ATEError(
                    f"{path}, line {lineno}: expected at least 8 comma-separated fields "
                    f"(t_ns, px, py, pz, qw, qx, qy, qz), got {len(parts)}: {line!r}",
                    reason="malformed",
                )
            stamps[row] = _parse_ns(path, lineno, parts[0])
            vals = [_parse_float(path, lineno, f, p) for f, p in zip(_NS_FIELDS[1:], parts[1:8], strict=True)]
            positions[row] = vals[0:3]
            quats[row] = vals[3:7]
        if np.linalg.norm(quats[row]) < 1e-9:
            raise ATEError(f"{path}, line {lineno}: zero quaternion: {line!r}", reason="malformed")
    return Trajectory(stamps, positions, quats, name)


def read_trajectory(path: str | Path, fmt: str | None = None, name: str | None = None) -> Trajectory:
    """Read the poses of a trajectory file in file order, stamps in seconds.

    Args:
        path: a trajectory file or a folder holding one (:func:`resolve_trajectory_path`).
        fmt: one of :data:`FORMATS`, or ``None`` / ``"auto"`` to detect it.
        name: label of the trajectory; default: the resolved file path.

    Raises:
        ATEError: for a missing or empty file, an unknown format name, an undetectable format, or a
            malformed row (the message names the file, the line and the text), NaN/inf values or a zero
            quaternion.
    """
    fmt = _check_format(fmt)
    file = resolve_trajectory_path(path)
    headers, data = _read_lines(file)
    if fmt is None:
        fmt = _detect(file, headers, data)
    return _parse(file, fmt, data, name if name is not None else str(file))


def _g(value: float) -> str:
    return f"{value:.9f}"


def write_trajectory(trajectory: Trajectory, path: str | Path, fmt: str) -> Path:
    """Write a trajectory in one of :data:`FORMATS` (parent folders are created); returns the path.

    ``euroc`` writes 17 columns and ``vins`` 11 with the trailing comma, velocities and biases zero and
    stamps rounded to whole nanoseconds.

    Raises:
        ATEError: for an unknown format, or when the file cannot be written.
    """
    fmt = _check_format(fmt)
    if fmt is None:
        raise ATEError("write_trajectory needs an explicit format, not auto")
    path = Path(path)
    lines: list[str] = []
    if fmt == "euroc":
        lines.append(_EUROC_HEADER)
    for t, p, q in zip(trajectory.stamps, trajectory.positions, trajectory.quaternions, strict=True):
        if fmt == "tum":
            lines.append(" ".join(_g(v) for v in (t, *p, q[1], q[2], q[3], q[0])))
            continue
        ns = str(round(float(t) * 1e9))
        pose = ",".join(_g(v) for v in (*p, *q))
        if fmt == "euroc":
            lines.append(f"{ns},{pose}" + ",0" * 9)
        else:
            lines.append(f"{ns},{pose},0,0,0,")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise ATEError(f"{path}: cannot write ({exc.strerror})") from exc
    return path
