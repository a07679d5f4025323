"""Small training data sets the training tests make themselves: a TartanAir-layout folder and a short bag."""

from __future__ import annotations

import cv2
import numpy as np
import skimage.data


def _homography(rng: np.random.Generator, w: int, h: int, k: int) -> np.ndarray:
    """Frame k's map from frame pixels to photo pixels: a drifting similarity plus a little perspective."""
    s = 1.6 + 0.05 * k
    a = np.deg2rad(2.0 * k)
    return np.array(
        [[s * np.cos(a), -s * np.sin(a), 40 + 3.5 * k], [s * np.sin(a), s * np.cos(a), 30 + 2.0 * k],
         [1e-5 * k, 0.0, 1.0]]
    )


def write_tartanair(root, envs=("abandonedfactory", "hospital"), frames=3, w=160, h=120, occluded=(40, 80)):
    """A TartanAir-layout folder rendered from a photo through known homographies: exact flow.

    Frame k is the photo seen through the homography M_k (frame pixel -> photo pixel); the flow of pixel x
    from frame k to k + 1 is M_{k+1}^-1 M_k x - x. The mask marks targets outside frame 2 (1) and, as an
    'occluded' block, the columns ``occluded`` (10). Returns {(env, k): (flow, mask)}.
    """
    from pathlib import Path

    photo = skimage.data.astronaut()[..., ::-1].copy()  # BGR, as cv2.imwrite expects
    truth = {}
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([xx, yy, np.ones_like(xx)], -1).reshape(-1, 3).T
    for e, env in enumerate(envs):
        traj = Path(root) / env / "Easy" / "P000"
        (traj / "image_left").mkdir(parents=True)
        (traj / "flow").mkdir()
        ms = [_homography(rng, w, h, k + 3 * e) for k in range(frames)]
        for k, m in enumerate(ms):
            img = cv2.warpPerspective(photo, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            cv2.imwrite(str(traj / "image_left" / f"{k:06d}_left.png"), img)
        for k in range(frames - 1):
            q = np.linalg.inv(ms[k + 1]) @ ms[k] @ pix
            q = (q[:2] / q[2]).T.reshape(h, w, 2)
            flow = (q - np.stack([xx, yy], -1)).astype(np.float32)
            mask = np.zeros((h, w), np.uint8)
            out = (q[..., 0] < 0) | (q[..., 0] > w - 1) | (q[..., 1] < 0) | (q[..., 1] > h - 1)
            mask[out] = 1
            mask[:, occluded[0] : occluded[1]] = 10
            np.save(traj / "flow" / f"{k:06d}_{k + 1:06d}_flow.npy", flow)
            np.save(traj / "flow" / f"{k:06d}_{k + 1:06d}_mask.npy", mask)
            truth[(env, k)] = (flow, mask)
    return truth


def write_footage_bag(path, frames=6, w=200, h=150, topic="/cam0/image_raw"):
    """A short ROS 2 bag of gray camera frames (crops of a photo drifting right)."""
    from nsflow_ros.data.writers import BagWriter

    photo = cv2.cvtColor(skimage.data.coffee(), cv2.COLOR_RGB2GRAY)
    with BagWriter(path) as bag:
        for k in range(frames):
            img = np.ascontiguousarray(photo[50 : 50 + h, 20 + 7 * k : 20 + 7 * k + w])
            bag.write_image(topic, 1_000_000_000 + k * 50_000_000, img, "cam0")
    return path
