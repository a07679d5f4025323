"""Scene renderer: determinism, exact depth, and ground-truth flow checked by warping."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from nsflow_ros.data.camera import EUROC_CAM0, EUROC_CAM1, PinholeRadtan
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.motion import Trajectory
from nsflow_ros.data.scene import Box, Material, Renderer, Scene, flow_between, ray_depth

# Camera looking along world +x: camera z = world x, camera x = -world y, camera y = -world z.
R_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rz(a: float) -> np.ndarray:
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def scene():
    return Scene.from_seed(11)


@pytest.fixture(scope="module")
def renderers(scene):
    return Renderer(scene, EUROC_CAM0), Renderer(scene, EUROC_CAM1)


def _plain_scene(boxes=()) -> Scene:
    mat = Material(0, 1.0, (0.0, 0.0), 0, 1.0, 1.0)
    return Scene((-5, -50, -50), (2, 50, 50), list(boxes), [mat] * 6)


def test_scene_is_deterministic_and_round_trips(scene):
    assert Scene.from_seed(11).to_dict() == scene.to_dict()
    assert Scene.from_seed(12).to_dict() != scene.to_dict()
    again = Scene.from_dict(scene.to_dict())
    T = Trajectory.from_seed(11).camera_pose(1.0, EUROC_CAM0)[0]
    a = Renderer(scene, EUROC_CAM0).render(T, noise_sigma=1.0, noise_seed=4)
    b = Renderer(again, EUROC_CAM0).render(T, noise_sigma=1.0, noise_seed=4)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)


def test_render_output_and_speed(renderers):
    r0, _ = renderers
    poses = Trajectory.from_seed(11).camera_pose(np.linspace(0.0, 4.0, 4), EUROC_CAM0)
    r0.render(poses[0])  # texture atlas built once
    t0 = time.perf_counter()
    outs = [r0.render(T) for T in poses]
    per_frame = (time.perf_counter() - t0) / len(poses)
    img = outs[0].image
    assert img.shape == (480, 752) and img.dtype == np.uint8
    assert outs[0].depth.shape == (480, 752) and outs[0].depth.dtype == np.float32
    # Textured everywhere, not saturated.
    assert 40 < img.mean() < 200 and img.std() > 15
    assert (img == 0).mean() < 0.01 and (img == 255).mean() < 0.01
    assert np.isfinite(outs[0].depth).all() and outs[0].depth.min() > 0.3
    assert per_frame < 0.5, f"{per_frame:.3f} s per 752x480 frame"


def test_depth_is_exact_on_a_known_plane():
    # All rays of a camera at the origin facing +x hit the wall x = 2: z-depth 2 for a frontal camera.
    scene = _plain_scene()
    cam = EUROC_CAM0.scaled(0.25)
    r = Renderer(scene, cam)
    assert np.allclose(r.render(_pose(R_FORWARD, [0, 0, 0])).depth, 2.0, atol=1e-5)
    # Turned by 0.3 rad about z: depth along (x, y, 1) is 2 / d_x, d_x the ray's world x component.
    R = _rz(0.3) @ R_FORWARD
    depth = r.render(_pose(R, [0, 0, 0])).depth
    grid = cam.ray_grid.reshape(-1, 2)
    dirs = R @ np.vstack([grid.T, np.ones(grid.shape[0])])
    assert np.allclose(depth.ravel(), 2.0 / dirs[0], rtol=1e-5)


def test_depth_map_matches_exact_ray_depth(scene, renderers):
    T = Trajectory.from_seed(11).camera_pose(2.0, EUROC_CAM0)[0]
    depth = renderers[0].render(T).depth
    rng = np.random.default_rng(0)
    pix = np.stack([rng.integers(0, 752, 200), rng.integers(0, 480, 200)], axis=1).astype(float)
    exact = ray_depth(scene, EUROC_CAM0, T, pix)
    assert np.allclose(depth[pix[:, 1].astype(int), pix[:, 0].astype(int)], exact, rtol=1e-4)


def _warp_error(img_i, img_j, flow, visible, grid_shape):
    h, w = grid_shape
    tgt = flow.reshape(h, w, 2).astype(np.float32)
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    warped = cv2.remap(img_j.astype(np.float32), u + tgt[..., 0], v + tgt[..., 1], cv2.INTER_LINEAR)
    m = visible.reshape(h, w)
    return np.abs(warped - img_i.astype(np.float32))[m], np.abs(img_j.astype(np.float32) - img_i)[m]


@pytest.mark.parametrize("dt, cam_j", [(0.05, 0), (0.15, 0), (0.0, 1)])
def test_ground_truth_flow_warps_frame_j_onto_frame_i(scene, renderers, dt, cam_j):
    traj = Trajectory.from_seed(11)
    cams = (EUROC_CAM0, EUROC_CAM1)
    Ti = traj.camera_pose(3.0, EUROC_CAM0)[0]
    Tj = traj.camera_pose(3.0 + dt, cams[cam_j])[0]
    img_i = renderers[0].render(Ti).image
    img_j = renderers[cam_j].render(Tj).image
    u, v = np.meshgrid(np.arange(752.0), np.arange(480.0))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    flow, visible = flow_between(scene, EUROC_CAM0, Ti, cams[cam_j], Tj, pix)
    assert visible.mean() > 0.7
    assert np.isfinite(flow[visible]).all()
    err, no_flow = _warp_error(img_i, img_j, flow, visible, (480, 752))
    # Only sampling differences remain (texture level, silhouettes): about one gray level on average.
    assert err.mean() < 2.0 and np.median(err) < 1.0
    assert err.mean() < 0.15 * no_flow.mean()
    assert np.median(np.linalg.norm(flow[visible], axis=1)) > 2.0  # the frames really differ


def test_flow_flags_occlusion_and_leaving_the_image():
    box = Box((1.0, 0.0, 0.0), (0.2, 0.2, 0.2), 0.0, tuple([Material(1, 1.0, (0.0, 0.0), 0, 1.0, 1.0)] * 6))
    scene = _plain_scene([box])
    cam = EUROC_CAM0
    Ti = _pose(R_FORWARD, [0.0, -0.6, 0.0])
    Tj = _pose(R_FORWARD, [0.0, 0.0, 0.0])
    # The wall point (2, 0, 0) is seen from i but hidden behind the box from j;
    # (2, -0.6, 0.5) is seen by both.
    pts_w = np.array([[2.0, 0.0, 0.0], [2.0, -0.6, 0.5]])
    pts_i = (Ti[:3, :3].T @ (pts_w - Ti[:3, 3]).T).T
    uv, ok = cam.project(pts_i)
    assert ok.all()
    flow, visible = flow_between(scene, cam, Ti, cam, Tj, uv)
    assert visible.tolist() == [False, True]
    assert np.isfinite(flow).all()
    # Turning j away by 90 degrees puts everything outside its image.
    flow, visible = flow_between(scene, cam, Ti, cam, _pose(_rz(np.pi / 2) @ R_FORWARD, [0, 0, 0]), uv)
    assert not visible.any()


def test_render_and_flow_guards(renderers):
    with pytest.raises(DataError, match=r"T_wc: expected shape \(4, 4\), got \(3, 4\)"):
        renderers[0].render(np.eye(4)[:3])
    with pytest.raises(DataError, match="outside the room"):
        renderers[0].render(_pose(np.eye(3), [100.0, 0.0, 1.0]))
    with pytest.raises(DataError, match="texture index 99"):
        Scene((0, 0, 0), (1, 1, 1), [], [Material(99, 1.0, (0.0, 0.0), 0, 1.0, 1.0)] * 6)
    cam = PinholeRadtan(64, 48, 50.0, 50.0, 31.5, 23.5)
    with pytest.raises(DataError, match=r"pixels: expected shape \(N, 2\)"):
        flow_between(_plain_scene(), cam, np.eye(4), cam, np.eye(4), np.zeros((4, 3)))
