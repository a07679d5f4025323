"""Camera models: camodocal semantics, agreement with OpenCV, guards and camodocal files.

Tolerances used below (all float64):
* converged round trips project(lift(p)) == p: 1e-9 px over the whole image grid;
* PINHOLE / MEI with camodocal's 8 undistortion iterations: the residual is camodocal's own, bounded
  (EuRoC cam0: < 0.2 px in the worst corner, < 1e-3 px within 250 px of the principal point);
* agreement with cv2.undistortPoints / cv2.fisheye.undistortPoints: 1e-12 in normalised coordinates;
* agreement with cv2.projectPoints / cv2.fisheye.projectPoints: 1e-9 px.
"""

from __future__ import annotations

import dataclasses
import math
import re
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest

from nsflow_ros.core.camera import (
    CAMERA_MODELS,
    CameraError,
    CameraModel,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    camera_from_dict,
    load_camera,
)
from nsflow_ros.core.errors import CoreError

CONFIG = Path(__file__).resolve().parents[2] / "config"

# REFERENCE.md section 5: EuRoC cam0, pinhole-radtan.
EUROC_CAM0 = PinholeCamera(
    fx=458.654,
    fy=457.296,
    cx=367.215,
    cy=248.375,
    k1=-0.28340811,
    k2=0.07395907,
    p1=0.00019359,
    p2=1.76187114e-05,
    width=752,
    height=480,
    name="cam0",
)
# A wide equidistant lens (about 75 degrees off-axis in the image corners).
FISHEYE = KannalaBrandtCamera(
    k2=0.0127,
    k3=-0.0065,
    k4=0.0028,
    k5=-0.0008,
    mu=350.0,
    mv=349.0,
    u0=376.0,
    v0=240.0,
    width=752,
    height=480,
)
# An omnidirectional lens with mild distortion.
OMNI = MeiCamera(
    xi=1.5,
    k1=-0.1,
    k2=0.02,
    p1=1e-4,
    p2=-2e-4,
    gamma1=700.0,
    gamma2=698.0,
    u0=370.0,
    v0=245.0,
    width=752,
    height=480,
)
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def image_grid(camera: CameraModel, step: float = 4.0) -> np.ndarray:
    """Every ``step`` pixels across the whole image, the last row and column (corners) included."""
    us = np.unique(np.append(np.arange(0.0, camera.width, step), camera.width - 1.0))
    vs = np.unique(np.append(np.arange(0.0, camera.height, step), camera.height - 1.0))
    u, v = np.meshgrid(us, vs)
    return np.stack([u.ravel(), v.ravel()], axis=1)


def with_plane(normalised: np.ndarray) -> np.ndarray:
    return np.hstack([normalised, np.ones((len(normalised), 1))])


def reprojection_error(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    return np.linalg.norm(camera.project(camera.lift_rays(pixels)) - pixels, axis=1)


# ---------------------------------------------------------------------------------------------- PINHOLE


def camodocal_pinhole_lift(camera: PinholeCamera, u: float, v: float) -> tuple[float, float]:
    """PinholeCamera::liftProjective transcribed one scalar at a time, as an independent reference."""

    def offset(x: float, y: float) -> tuple[float, float]:
        r2 = x * x + y * y
        rad = camera.k1 * r2 + camera.k2 * r2 * r2
        return (
            x * rad + 2.0 * camera.p1 * x * y + camera.p2 * (r2 + 2.0 * x * x),
            y * rad + 2.0 * camera.p2 * x * y + camera.p1 * (r2 + 2.0 * y * y),
        )

    xd = (1.0 / camera.fx) * u + (-camera.cx / camera.fx)
    yd = (1.0 / camera.fy) * v + (-camera.cy / camera.fy)
    dx, dy = offset(xd, yd)
    x, y = xd - dx, yd - dy
    for _ in range(1, 8):
        dx, dy = offset(x, y)
        x, y = xd - dx, yd - dy
    return x, y


def test_pinhole_lift_is_camodocal_eight_iterations() -> None:
    pixels = np.array([[0.0, 0.0], [751.0, 479.0], [367.215, 248.375], [100.5, 400.25], [700.0, 20.0]])
    expected = np.array([camodocal_pinhole_lift(EUROC_CAM0, u, v) for u, v in pixels])
    np.testing.assert_allclose(EUROC_CAM0.lift(pixels), expected, rtol=0, atol=1e-15)
    rays = EUROC_CAM0.lift_rays(pixels)
    assert rays.dtype == np.float64 and rays.shape == (5, 3)
    np.testing.assert_array_equal(rays[:, 2], 1.0)


def test_pinhole_round_trip_converged_whole_image() -> None:
    camera = dataclasses.replace(EUROC_CAM0, undistort_iterations=50)
    pixels = image_grid(camera)
    assert reprojection_error(camera, pixels).max() < 1e-9
    # lift() and lift_rays() agree (z = 1), and project() accepts the normalised plane directly.
    np.testing.assert_allclose(camera.project(with_plane(camera.lift(pixels))), pixels, rtol=0, atol=1e-9)


def test_pinhole_round_trip_camodocal_residual_is_bounded() -> None:
    pixels = image_grid(EUROC_CAM0)
    error = reprojection_error(EUROC_CAM0, pixels)
    # Eight fixed-point iterations do not converge in the strongly distorted corners; VINS lives with it.
    assert 0.1 < error.max() < 0.2
    central = np.hypot(pixels[:, 0] - EUROC_CAM0.cx, pixels[:, 1] - EUROC_CAM0.cy) < 250.0
    assert error[central].max() < 1e-3


def test_pinhole_lift_matches_cv2_undistort_points() -> None:
    pixels = image_grid(EUROC_CAM0)
    reference = cv2.undistortPoints(
        pixels.reshape(-1, 1, 2), EUROC_CAM0.camera_matrix, EUROC_CAM0.dist_coeffs, criteria=CRIT
    ).reshape(-1, 2)
    converged = dataclasses.replace(EUROC_CAM0, undistort_iterations=50)
    np.testing.assert_allclose(converged.lift(pixels), reference, rtol=0, atol=1e-12)
    # camodocal's 8 iterations: within 0.4 px (times fx) of the converged answer, everywhere.
    assert np.abs(EUROC_CAM0.lift(pixels) - reference).max() * EUROC_CAM0.fx < 0.4


def test_pinhole_project_matches_cv2_project_points() -> None:
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.7, 0.7, 500), rng.uniform(-0.5, 0.5, 500), np.ones(500)])
    points *= rng.uniform(0.5, 20.0, (500, 1))
    reference, _ = cv2.projectPoints(
        points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), EUROC_CAM0.camera_matrix, EUROC_CAM0.dist_coeffs
    )
    np.testing.assert_allclose(EUROC_CAM0.project(points), reference.reshape(-1, 2), rtol=0, atol=1e-9)


def test_pinhole_without_distortion_is_exact_inverse_k() -> None:
    camera = PinholeCamera(fx=400.0, fy=300.0, cx=320.0, cy=240.0, width=640, height=480)
    np.testing.assert_allclose(camera.lift([[720.0, 540.0], [320.0, 240.0]]), [[1.0, 1.0], [0.0, 0.0]])
    np.testing.assert_allclose(camera.project([[2.0, -1.0, 4.0]]), [[520.0, 165.0]])


# ---------------------------------------------------------------------------------------- KANNALA_BRANDT


def test_kannala_brandt_round_trip_whole_image() -> None:
    pixels = image_grid(FISHEYE)
    rays = FISHEYE.lift_rays(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-15)
    assert reprojection_error(FISHEYE, pixels).max() < 1e-9
    assert np.linalg.norm(FISHEYE.project(with_plane(FISHEYE.lift(pixels))) - pixels, axis=1).max() < 1e-9


def test_kannala_brandt_matches_cv2_fisheye() -> None:
    pixels = image_grid(FISHEYE)
    reference = cv2.fisheye.undistortPoints(
        pixels.reshape(-1, 1, 2), FISHEYE.camera_matrix, FISHEYE.dist_coeffs, criteria=CRIT
    ).reshape(-1, 2)
    np.testing.assert_allclose(FISHEYE.lift(pixels), reference, rtol=0, atol=1e-12)

    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-2.0, 2.0, 500), rng.uniform(-2.0, 2.0, 500), np.ones(500)])
    points *= rng.uniform(0.5, 20.0, (500, 1))
    projected, _ = cv2.fisheye.projectPoints(
        points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), FISHEYE.camera_matrix, FISHEYE.dist_coeffs
    )
    np.testing.assert_allclose(FISHEYE.project(points), projected.reshape(-1, 2), rtol=0, atol=1e-9)


def test_kannala_brandt_root_is_camodocal_companion_root() -> None:
    # The fast path (safeguarded Newton) must pick the same root as camodocal's companion-matrix method,
    # including a polynomial that turns over inside the image (points beyond it take the fallback).
    for camera in (FISHEYE, dataclasses.replace(FISHEYE, k2=-0.2, k3=0.0, k4=0.0, k5=0.0, mu=250.0)):
        pixels = image_grid(camera, step=8.0)
        x = (pixels[:, 0] - camera.u0) / camera.mu
        y = (pixels[:, 1] - camera.v0) / camera.mv
        rho = np.sqrt(x * x + y * y)
        np.testing.assert_allclose(camera._theta(rho), camera._theta_companion(rho), rtol=0, atol=1e-12)


def test_kannala_brandt_beyond_ninety_degrees() -> None:
    camera = KannalaBrandtCamera(mu=200.0, mv=200.0, u0=500.0, v0=500.0, k2=0.01, width=1000, height=1000)
    theta = np.deg2rad(110.0)
    ray = np.array([[math.sin(theta), 0.0, math.cos(theta)]])
    pixel = camera.project(ray)
    expected_r = theta + 0.01 * theta**3
    np.testing.assert_allclose(pixel, [[500.0 + 200.0 * expected_r, 500.0]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(camera.lift_rays(pixel), ray, rtol=0, atol=1e-12)


def test_kannala_brandt_without_polynomial_is_equidistant() -> None:
    camera = KannalaBrandtCamera(mu=100.0, mv=100.0, u0=0.0, v0=0.0, width=10, height=10)
    # r = theta: 45 degrees lands at pi/4 * 100 px.
    np.testing.assert_allclose(camera.project([[1.0, 0.0, 1.0]]), [[25.0 * math.pi, 0.0]], atol=1e-12)
    np.testing.assert_allclose(camera.lift([[25.0 * math.pi, 0.0]]), [[1.0, 0.0]], atol=1e-12)


# ------------------------------------------------------------------------------------------------------ MEI


def test_mei_round_trip_whole_image() -> None:
    pixels = image_grid(OMNI)
    converged = dataclasses.replace(OMNI, undistort_iterations=50)
    assert reprojection_error(converged, pixels).max() < 1e-9
    # Through the normalised plane only where the ray looks forward: this lens sees past 90 degrees in the
    # corners, where x/z, y/z (what VINS publishes) is the mirror image.
    forward = converged.lift_rays(pixels)[:, 2] > 0.0
    assert 0.9 < forward.mean() < 1.0
    plane = converged.lift(pixels[forward])
    assert np.linalg.norm(converged.project(with_plane(plane)) - pixels[forward], axis=1).max() < 1e-9
    # camodocal's 8 iterations are enough for this mild distortion.
    assert reprojection_error(OMNI, pixels).max() < 1e-5


def test_mei_hand_checked_values() -> None:
    # xi = 1 (parabolic), no distortion: (1, 0, 1) -> x = 1 / (1 + sqrt 2) = sqrt 2 - 1 on the plane.
    parabolic = MeiCamera(xi=1.0, gamma1=100.0, gamma2=100.0, u0=50.0, v0=50.0, width=100, height=100)
    pixel = parabolic.project([[1.0, 0.0, 1.0]])
    np.testing.assert_allclose(pixel, [[50.0 + 100.0 * (math.sqrt(2.0) - 1.0), 50.0]], rtol=0, atol=1e-12)
    # camodocal's xi == 1 ray: (x, y, (1 - x^2 - y^2) / 2) = (sqrt 2 - 1, 0, sqrt 2 - 1).
    s = math.sqrt(2.0) - 1.0
    np.testing.assert_allclose(parabolic.lift_rays(pixel), [[s, 0.0, s]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(parabolic.lift(pixel), [[1.0, 0.0]], rtol=0, atol=1e-12)

    # xi = 0.5, k1 = 0.1: P = (0.3, 0.4, 1.2), |P| = 1.3, z' = 1.2 + 0.65 = 1.85 -> (x, y) = (6/37, 8/37),
    # rho^2 = 100/1369, distorted = (x, y) (1 + 0.1 rho^2) = (x, y) 1379/1369;
    # u = 320 + 400 x_d, v = 240 + 400 y_d.
    camera = MeiCamera(xi=0.5, k1=0.1, gamma1=400.0, gamma2=400.0, u0=320.0, v0=240.0, width=640, height=480)
    scale = Fraction(1379, 1369)
    u = 320 + 400 * Fraction(6, 37) * scale
    v = 240 + 400 * Fraction(8, 37) * scale
    np.testing.assert_allclose(camera.project([[0.3, 0.4, 1.2]]), [[float(u), float(v)]], rtol=0, atol=1e-12)
    # And back: the ray through that pixel is parallel to P, so the normalised point is (0.3, 0.4) / 1.2.
    converged = dataclasses.replace(camera, undistort_iterations=60)
    np.testing.assert_allclose(
        converged.lift([[float(u), float(v)]]), [[0.25, 1.0 / 3.0]], rtol=0, atol=1e-12
    )


# --------------------------------------------------------------------------------------------------- guards


@pytest.mark.parametrize("camera", [EUROC_CAM0, FISHEYE, OMNI], ids=lambda c: c.model_type)
def test_guards(camera: CameraModel) -> None:
    with pytest.raises(CameraError, match=r"pixels must have shape \(N, 2\), got \(4, 3\)"):
        camera.lift(np.zeros((4, 3)))
    with pytest.raises(CameraError, match=r"pixels must have shape \(N, 2\), got \(2,\)"):
        camera.lift_rays(np.zeros(2))
    with pytest.raises(CameraError, match=r"points must have shape \(N, 3\), got \(4, 2\)"):
        camera.project(np.zeros((4, 2)))
    with pytest.raises(CameraError, match=r"integer or floating dtype.*got dtype complex128"):
        camera.lift(np.zeros((4, 2), dtype=complex))
    with pytest.raises(CameraError, match="got dtype bool"):
        camera.project(np.zeros((4, 3), dtype=bool))
    with pytest.raises(CameraError, match="got dtype <U1"):
        camera.lift([["a", "b"]])
    with pytest.raises(CoreError):  # the core's error family
        camera.lift([[1.0, 2.0], [3.0]])
    # Empty input and integer pixels are fine; results are float64.
    assert camera.lift(np.zeros((0, 2))).shape == (0, 2)
    assert camera.project(np.zeros((0, 3))).shape == (0, 2)
    lifted = camera.lift(np.array([[300, 200]], dtype=np.int32))
    assert lifted.dtype == np.float64
    np.testing.assert_allclose(lifted, camera.lift([[300.0, 200.0]]), rtol=0, atol=0)
    float32 = camera.lift(np.array([[300.5, 200.25]], dtype=np.float32))
    assert float32.dtype == np.float64


def test_parameter_validation() -> None:
    with pytest.raises(CameraError, match=re.escape("fx must be > 0, got -1.0")):
        PinholeCamera(fx=-1.0, fy=1.0, cx=0.0, cy=0.0, width=10, height=10)
    with pytest.raises(CameraError, match="width must be >= 1, got 0"):
        PinholeCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=0, height=10)
    with pytest.raises(CameraError, match="height must be an integer"):
        PinholeCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=10, height=10.5)
    with pytest.raises(CameraError, match="k1 must be finite"):
        PinholeCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, k1=math.nan, width=10, height=10)
    with pytest.raises(CameraError, match="undistort_iterations must be >= 1"):
        PinholeCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=10, height=10, undistort_iterations=0)
    with pytest.raises(CameraError, match="xi must be >= 0"):
        MeiCamera(xi=-0.1, gamma1=1.0, gamma2=1.0, u0=0.0, v0=0.0, width=10, height=10)
    with pytest.raises(CameraError, match="mu must be a real number, got bool"):
        KannalaBrandtCamera(mu=True, mv=1.0, u0=0.0, v0=0.0, width=10, height=10)
    with pytest.raises(TypeError):  # abstract
        CameraModel(width=10, height=10)  # type: ignore[abstract]
    with pytest.raises(dataclasses.FrozenInstanceError):
        EUROC_CAM0.fx = 1.0  # type: ignore[misc]


# ----------------------------------------------------------------------------------------------------- files


def test_shipped_euroc_camera_files() -> None:
    cam0 = load_camera(CONFIG / "euroc" / "cam0_pinhole.yaml")
    assert cam0 == EUROC_CAM0
    assert (cam0.model_type, cam0.name, cam0.width, cam0.height) == ("PINHOLE", "cam0", 752, 480)
    cam1 = PinholeCamera.from_yaml(CONFIG / "euroc" / "cam1_pinhole.yaml")
    assert cam1.parameters == {
        "k1": -0.28368365,
        "k2": 0.07451284,
        "p1": -0.00010473,
        "p2": -3.55590700e-05,
        "fx": 457.587,
        "fy": 456.134,
        "cx": 379.999,
        "cy": 255.238,
    }


@pytest.mark.parametrize("camera", [EUROC_CAM0, FISHEYE, OMNI], ids=lambda c: c.model_type)
def test_save_and_load_round_trip(camera: CameraModel, tmp_path: Path) -> None:
    path = tmp_path / "camera.yaml"
    camera.save_yaml(path)
    assert path.read_text().startswith("%YAML:1.0\n")
    loaded = CameraModel.from_yaml(path)
    assert loaded == camera  # 17 significant digits: exact
    assert type(loaded) is type(camera)
    assert camera_from_dict(camera.to_dict()) == camera


def test_camodocal_file_as_written_by_hand(tmp_path: Path) -> None:
    path = tmp_path / "kb.yaml"
    path.write_text(
        "%YAML:1.0\n---\nmodel_type: kannala_brandt\ncamera_name: fish\n"
        "image_width: 1024\nimage_height: 768\n"
        "projection_parameters:\n   k2: 1.0e-2\n   k3: 0\n   k4: 0\n   k5: 0\n"
        "   mu: 380\n   mv: 380.5\n   u0: 512\n   v0: 384\n"
    )
    camera = load_camera(path)
    assert isinstance(camera, KannalaBrandtCamera)
    assert (camera.model_type, camera.name, camera.mu, camera.k2, camera.k3) == (
        "KANNALA_BRANDT",
        "fish",
        380.0,
        0.01,
        0.0,
    )
    assert set(CAMERA_MODELS) == {"PINHOLE", "KANNALA_BRANDT", "MEI"}


def write_pinhole(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cam.yaml"
    path.write_text("%YAML:1.0\n" + text)
    return path


GOOD = (
    "model_type: PINHOLE\nimage_width: 752\nimage_height: 480\n"
    "distortion_parameters:\n   k1: 0.0\n   k2: 0.0\n   p1: 0.0\n   p2: 0.0\n"
    "projection_parameters:\n   fx: 400.0\n   fy: 400.0\n   cx: 376.0\n   cy: 240.0\n"
)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("model_type: PINHOLE\n", ""), "missing key 'model_type'"),
        (lambda t: t.replace("PINHOLE", "SCARAMUZZA"), "key 'model_type': unsupported model 'SCARAMUZZA'"),
        (lambda t: t.replace("   fx: 400.0\n", ""), "missing key 'projection_parameters/fx'"),
        (lambda t: t.replace("fy: 400.0", "fy: abc"), "key 'projection_parameters/fy' must be a number"),
        (lambda t: t.replace("fx: 400.0", "fx: -400.0"), "fx must be > 0"),
        (lambda t: t.replace("image_width: 752", "image_width: 0"), "key 'image_width' must be a positive"),
        (lambda t: t.replace("image_height: 480\n", ""), "missing key 'image_height'"),
        (
            lambda t: t.split("distortion_parameters")[0] + "distortion_parameters: 3\n",
            "key 'distortion_parameters' must be a map",
        ),
    ],
)
def test_camera_file_errors_name_file_and_key(tmp_path: Path, edit, message: str) -> None:
    path = write_pinhole(tmp_path, edit(GOOD))
    with pytest.raises(CameraError, match=message) as info:
        load_camera(path)
    assert str(path) in str(info.value)


def test_camera_file_unreadable(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    with pytest.raises(CameraError, match="does not exist") as info:
        load_camera(missing)
    assert str(missing) in str(info.value)
    garbage = tmp_path / "garbage.yaml"
    garbage.write_bytes(b"\x89PNG\r\n\x1a\n\0\0\0")
    with pytest.raises(CameraError, match=re.escape(str(garbage))):
        load_camera(garbage)
    path = write_pinhole(tmp_path, GOOD)
    with pytest.raises(CameraError, match="model_type is PINHOLE, expected MEI"):
        MeiCamera.from_yaml(path)


def test_radtan_distort_matches_opencv_and_checks_its_input():
    from nsflow_ros.core.camera import CameraError, radtan_distort

    rng = np.random.default_rng(4)
    xn = rng.uniform(-0.6, 0.6, (50, 2))
    coeffs = np.array([-0.28, 0.07, 2e-4, -1.8e-5])
    pts3 = np.c_[xn, np.ones(len(xn))]
    ref, _ = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), np.eye(3), coeffs)
    np.testing.assert_allclose(radtan_distort(xn, coeffs), ref.reshape(-1, 2), atol=1e-12)
    np.testing.assert_array_equal(radtan_distort(xn, np.zeros(4)), xn)
    with pytest.raises(CameraError, match=r"\(N, 2\)"):
        radtan_distort(np.zeros((3, 3)), coeffs)
    with pytest.raises(CameraError, match="k1, k2, p1, p2"):
        radtan_distort(xn, coeffs[:3])
