"""scripts/build_vins_fusion.sh without building: its syntax, its help, and the OpenCV 4 renames it applies
to upstream VINS-Fusion (the lines below are upstream's own, from camera_models and vins_estimator)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "build_vins_fusion.sh"
SED = REPO / "scripts" / "vins_fusion_opencv4.sed"

UPSTREAM = """\
imLeft = cv::imread(leftImagePath, CV_LOAD_IMAGE_GRAYSCALE );
cv::cvtColor(imTrack, imTrack, CV_GRAY2RGB);
cv::cvtColor(image, mSketch, CV_GRAY2BGR);
cv::cvtColor(image, mImage, CV_BGR2GRAY);
CV_CALIB_CB_ADAPTIVE_THRESH + CV_CALIB_CB_NORMALIZE_IMAGE + CV_CALIB_CB_FILTER_QUADS + CV_CALIB_CB_FAST_CHECK,
cv::adaptiveThreshold(img, thresh_img, 255, CV_ADAPTIVE_THRESH_MEAN_C, CV_THRESH_BINARY, blockSize, (k/2)*5);
cv::threshold(black, thresh, threshLevel, 255, CV_THRESH_BINARY_INV);
cv::Mat kernel1 = cv::getStructuringElement(CV_SHAPE_CROSS, cv::Size(3,3), cv::Point(1,1));
cv::Mat kernel2 = cv::getStructuringElement(CV_SHAPE_RECT, cv::Size(3,3), cv::Point(1,1));
cv::TermCriteria(CV_TERMCRIT_EPS + CV_TERMCRIT_ITER, 30, 0.1));
cv::findContours(image, contours, hierarchy, CV_RETR_CCOMP, CV_CHAIN_APPROX_SIMPLE);
5, green, 2, CV_AA, drawShiftBits);
CV_RGB(255,255,255), 3, 8);
cv::Mat m(3, 3, CV_64F); cv::Mat n(1, 1, CV_8UC3);
"""


def _sed(text: str) -> str:
    return subprocess.run(
        ["sed", "-E", "-f", str(SED)], input=text, capture_output=True, text=True, check=True
    ).stdout


def test_the_script_parses_and_answers_help_without_building():
    assert shutil.which("bash")
    subprocess.run(["bash", "-n", str(SCRIPT)], check=True)
    out = subprocess.run([str(SCRIPT), "--help"], capture_output=True, text=True, check=True).stdout
    assert "--src DIR" in out and "--rev REV" in out and "WORKSPACE" in out
    bad = subprocess.run([str(SCRIPT), "--frobnicate"], capture_output=True, text=True)
    assert bad.returncode == 1 and "unknown option --frobnicate" in bad.stderr


def test_opencv4_renames_are_complete_and_idempotent():
    once = _sed(UPSTREAM)
    for old, new in [
        ("CV_LOAD_IMAGE_GRAYSCALE", "cv::IMREAD_GRAYSCALE"),
        ("CV_GRAY2RGB", "cv::COLOR_GRAY2RGB"),
        ("CV_THRESH_BINARY_INV", "cv::THRESH_BINARY_INV"),
        ("CV_SHAPE_CROSS", "cv::MORPH_CROSS"),
        ("CV_TERMCRIT_ITER", "cv::TermCriteria::MAX_ITER"),
        ("CV_AA", "cv::LINE_AA"),
    ]:
        assert old not in once and new in once
    assert "cv::THRESH_BINARY," in once  # the longer name is not cut short
    # what OpenCV 4 still defines stays as it is
    assert "CV_RGB(255,255,255)" in once and "CV_64F" in once and "CV_8UC3" in once
    assert _sed(once) == once


YAW_PATCH = REPO / "scripts" / "vins_fusion_yaw_gauge.patch"


def _side(patch: str, keep: str) -> str:
    """One side of a one-hunk unified diff: context lines and the lines marked ``keep`` ('-' or '+')."""
    body = patch.split("\n@@", 1)[1].split("\n", 1)[1]
    return "".join(line[1:] + "\n" for line in body.splitlines() if line[:1] in (" ", keep) or line == "")


def test_yaw_gauge_patch_applies_to_upstream_and_removes_the_euler_yaw(tmp_path: Path):
    text = YAW_PATCH.read_text()
    assert text.count("\n@@") == 1, "one hunk, in double2vector"
    target = tmp_path / "vins_estimator" / "src" / "estimator" / "estimator.cpp"
    target.parent.mkdir(parents=True)
    target.write_text(_side(text, "-"))
    assert "euler singular point" in target.read_text()  # upstream's own lines
    subprocess.run(["patch", "-d", str(tmp_path), "-p1", "--forward", "--quiet"], input=text, text=True,
                   check=True)
    patched = target.read_text()
    assert patched == _side(text, "+")
    assert "R2ypr" not in patched and "atan2(Rd(1, 0) - Rd(0, 1), Rd(0, 0) + Rd(1, 1))" in patched
    again = subprocess.run(["patch", "-d", str(tmp_path), "-p1", "--forward", "--dry-run"], input=text,
                           text=True, capture_output=True)
    assert again.returncode != 0  # already applied: the script's stage is fresh, so it is never re-applied


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _euler_yaw(r: np.ndarray) -> float:  # upstream's Utility::R2ypr(R).x()
    return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])))


def _closest_z(r_old: np.ndarray, r_new: np.ndarray) -> float:  # the patch's yaw
    d = r_old @ r_new.T
    return float(np.degrees(np.arctan2(d[1, 0] - d[0, 1], d[0, 0] + d[1, 1])))


def test_the_patch_s_yaw_is_the_gauge_and_euler_yaw_amplifies_tilt_near_a_vertical_x_axis():
    """EuRoC's IMU has its x axis near vertical (pitch -75 to -90 degrees in the sample's flights): there
    the Euler yaw difference of a pure 0.05 degree tilt update is a whole-degree turn of the window."""
    body = _rot("z", 30.0) @ _rot("y", -87.0) @ _rot("x", 10.0)
    tilted = _rot("x", 0.05) @ body  # a small tilt (about the world's x), no yaw
    assert abs(_closest_z(body, tilted)) < 0.003
    assert abs(_euler_yaw(body) - _euler_yaw(tilted)) > 0.5
    turned = _rot("z", 2.0) @ body  # a true yaw of the window: both see it
    assert _closest_z(turned, body) == pytest.approx(2.0, abs=1e-9)
    assert _euler_yaw(turned) - _euler_yaw(body) == pytest.approx(2.0, abs=1e-9)
    level = _rot("z", 30.0) @ _rot("y", -10.0)  # far from the singularity both agree to first order
    assert abs(_euler_yaw(level) - _euler_yaw(_rot("x", 0.05) @ level)) < 0.02
