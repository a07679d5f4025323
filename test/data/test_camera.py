"""EuRoC pinhole-radtan camera: exact undistortion, projection validity, descriptions."""

from __future__ import annotations

import numpy as np
import pytest

from nsflow_ros.core.camera import radtan_distort
from nsflow_ros.data.camera import EUROC_CAM0, EUROC_CAM1, PinholeRadtan
from nsflow_ros.data.errors import DataError


@pytest.mark.parametrize("cam", [EUROC_CAM0, EUROC_CAM1])
def test_undistort_inverts_distort_over_the_whole_image(cam):
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 60), np.linspace(0, cam.height - 1, 40))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    back = cam.normalized_to_pixels(cam.pixels_to_normalized(pix))
    assert np.abs(back - pix).max() < 1e-9


def test_ray_grid_matches_pixel_centres():
    grid = EUROC_CAM0.ray_grid
    assert grid.shape == (480, 752, 2)
    pix = EUROC_CAM0.normalized_to_pixels(grid[[0, 240, 479], [0, 367, 751]])
    assert np.allclose(pix, [[0, 0], [367, 240], [751, 479]], atol=1e-9)


def test_project_flags_points_behind_or_outside_the_model():
    cam = EUROC_CAM0
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [10.0, 0.0, 1.0]])
    uv, valid = cam.project(pts)
    assert valid.tolist() == [True, False, False]
    assert np.isnan(uv[1]).all() and np.isnan(uv[2]).all()
    # 10 normalised units off-axis would fold back into the image under radtan; it must not.
    assert np.allclose(uv[0], [cam.cx, cam.cy])


def test_description_round_trip_and_scaling():
    cam = PinholeRadtan.from_dict(EUROC_CAM1.to_dict())
    assert cam.to_dict() == EUROC_CAM1.to_dict()
    half = EUROC_CAM0.scaled(0.5)
    assert (half.width, half.height) == (376, 240)
    # The same ray lands on the corresponding pixel of the half-size image.
    xn = EUROC_CAM0.pixels_to_normalized([[100.0, 50.0]])
    assert np.allclose(half.normalized_to_pixels(xn), [[(100.5) / 2 - 0.5, (50.5) / 2 - 0.5]], atol=1e-9)


def test_shape_guards_name_expected_and_actual():
    with pytest.raises(DataError, match=r"expected shape \(N, 2\), got \(3, 3\)"):
        EUROC_CAM0.pixels_to_normalized(np.zeros((3, 3)))
    with pytest.raises(DataError, match=r"T_BS of cam9: expected shape \(4, 4\), got \(3, 3\)"):
        PinholeRadtan(10, 10, 1, 1, 5, 5, T_BS=np.eye(3), name="cam9")
    with pytest.raises(DataError, match="intrinsics"):
        PinholeRadtan.from_dict({"width": 1})


def test_camera_model_projects_like_the_data_camera():
    cam = EUROC_CAM0.scaled(0.5)
    model = cam.camera_model()
    pts = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 3.0], [0.0, 0.0, 1.0]])
    uv, valid = cam.project(pts)
    assert valid.all() and (model.width, model.height, model.name) == (cam.width, cam.height, cam.name)
    np.testing.assert_allclose(model.project(pts), uv, atol=1e-9)


def test_projection_is_the_tracker_models_to_the_bit():
    rng = np.random.default_rng(3)
    xn = rng.uniform(-0.8, 0.8, (500, 2))
    for cam in (EUROC_CAM0, EUROC_CAM1):
        xd = radtan_distort(xn, cam.dist)
        by_hand = np.stack([cam.fx * xd[:, 0] + cam.cx, cam.fy * xd[:, 1] + cam.cy], axis=1)
        assert np.array_equal(cam.normalized_to_pixels(xn), by_hand)
        points = np.column_stack([xn * 2.5, np.full(len(xn), 2.5)])
        uv, valid = cam.project(points)
        assert valid.all()
        assert np.array_equal(uv, cam.camera_model().project(points))
