"""scripts/build_vins_fusion.sh without building: its syntax, its help, and the OpenCV 4 renames it applies
to upstream VINS-Fusion (the lines below are upstream's own, from camera_models and vins_estimator)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

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
