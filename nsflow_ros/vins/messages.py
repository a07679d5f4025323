"""The feature message of the VINS estimators (sensor_msgs/PointCloud), as plain arrays: encode and decode.

Two layouts, both with ``points[i] = (x, y, 1)``, the undistorted normalised coordinates:

* VINS-Fusion: nine channels [id, camera_id, u, v, velocity_x, velocity_y, 0, 0, 0]. The estimator reads
  channels 6-8 whenever more than five exist, so the three zero channels must be there. Points are sorted
  by id and, within an id, camera 0 comes before camera 1 (the estimator asserts that order).
* VINS-Mono: five channels [id * num_of_cam + camera_id, u, v, velocity_x, velocity_y], only points tracked
  for more than one frame, camera by camera.

A frame whose features carry covariances (the tracker's ``publish_covariance``) adds three channels after
these, [sigma_uu, sigma_uv, sigma_vv] in px^2 (:data:`COVARIANCE_CHANNELS`): channels 9-11 of the
VINS-Fusion layout, 5-7 of the VINS-Mono one. Neither stock estimator reads them (VINS-Fusion reads
channels 0-8, VINS-Mono 0-4); docs/vins_fusion.md has a patch that weights its factors by them.

Feature ids travel as float32 channel values, exact only below 2^24, so both encoders publish them modulo
:data:`ID_MODULUS` (VINS-Mono: modulo ``ID_MODULUS // num_of_cam``, so that ``id * num_of_cam + camera``
stays below 2^24 too), which keeps ids unique within any window an estimator holds however long the run.

The decoders mirror the estimators' feature callbacks (channels by position, never by name) and return what
the estimator builds: ``{feature_id: [(camera_id, [x, y, z, u, v, vx, vy]), ...]}``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from nsflow_ros.core.tracker import FrameFeatures
from nsflow_ros.errors import NSFlowError

__all__ = [
    "COVARIANCE_CHANNELS",
    "FUSION_CHANNELS",
    "ID_MODULUS",
    "LAYOUTS",
    "MONO_CHANNELS",
    "FeatureCloud",
    "FeatureMessageError",
    "Layout",
    "decode",
    "decode_covariances",
    "decode_fusion",
    "decode_mono",
    "encode",
    "encode_fusion",
    "encode_mono",
    "published_ids",
]

Layout = Literal["fusion", "mono"]
LAYOUTS: tuple[str, ...] = ("fusion", "mono")

FUSION_CHANNELS: tuple[str, ...] = (
    "id_of_point",
    "camera_id",
    "u_of_point",
    "v_of_point",
    "velocity_x_of_point",
    "velocity_y_of_point",
    "unused_6",
    "unused_7",
    "unused_8",
)
"""Channel names of the VINS-Fusion layout (the estimator ignores names; the order is what matters)."""

MONO_CHANNELS: tuple[str, ...] = (
    "id_of_point",
    "u_of_point",
    "v_of_point",
    "velocity_x_of_point",
    "velocity_y_of_point",
)
"""Channel names of the VINS-Mono layout, as its feature_tracker node names them."""

COVARIANCE_CHANNELS: tuple[str, ...] = ("sigma_uu", "sigma_uv", "sigma_vv")
"""Channels a frame with covariances adds after its layout's own: the pixel covariance in px^2."""

ID_MODULUS = 2**24
"""Published ids are taken modulo this: float32, the channels' type, holds every integer below it exactly."""

FeatureFrame = dict[int, list[tuple[int, np.ndarray]]]


class FeatureMessageError(NSFlowError):
    """A feature message does not have the layout the decoder expects."""


@dataclass(frozen=True)
class FeatureCloud:
    """The content of one sensor_msgs/PointCloud as arrays.

    Shape:
        points: (N, 3) float32, (x, y, 1). channels: (C, N) float32, named by ``names``.
    """

    points: np.ndarray
    channels: np.ndarray
    names: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _cloud(un: np.ndarray, columns: list[np.ndarray], names: tuple[str, ...]) -> FeatureCloud:
    n = un.shape[0]
    points = np.ones((n, 3), np.float32)
    points[:, :2] = un
    chans = np.zeros((len(names), n), np.float32)
    for k, col in enumerate(columns):
        chans[k] = col
    return FeatureCloud(points, chans, names)


def published_ids(ids: np.ndarray, layout: Layout, num_of_cam: int = 1) -> np.ndarray:
    """The int64 ids a message of ``layout`` carries for tracker ids (before VINS-Mono's camera packing).

    Args:
        layout: "fusion" (modulo :data:`ID_MODULUS`) or "mono" (modulo ``ID_MODULUS // num_of_cam``).

    Shape:
        ids: (N,) -> (N,).

    Raises:
        FeatureMessageError: an unknown layout or a num_of_cam below 1.
    """
    if layout not in LAYOUTS:
        raise FeatureMessageError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if num_of_cam < 1:
        raise FeatureMessageError(f"num_of_cam must be >= 1, got {num_of_cam}")
    modulus = ID_MODULUS if layout == "fusion" else ID_MODULUS // num_of_cam
    return np.asarray(ids, np.int64) % modulus


def _covariances(frame: FrameFeatures) -> bool:
    """Whether the frame's features carry covariances (all cameras do or none: one tracker setting)."""
    return any(c.covariance is not None for c in frame.cameras)


def encode_fusion(frame: FrameFeatures) -> FeatureCloud:
    """Encode a frame in the VINS-Fusion layout: nine channels, published ids ascending, camera 0 first;
    twelve with the features' covariances (channels 9-11)."""
    cams = frame.cameras
    ids = published_ids(np.concatenate([c.ids for c in cams]), "fusion")
    cam_ids = np.concatenate([np.full(len(c), c.camera_id, np.int64) for c in cams])
    order = np.lexsort((cam_ids, ids))  # by id, then camera
    px = np.concatenate([c.pixels for c in cams])[order]
    un = np.concatenate([c.undistorted for c in cams])[order]
    vel = np.concatenate([c.velocities for c in cams])[order]
    columns = [ids[order], cam_ids[order], px[:, 0], px[:, 1], vel[:, 0], vel[:, 1]]
    if not _covariances(frame):
        return _cloud(un, columns, FUSION_CHANNELS)
    cov = np.concatenate([c.covariance for c in cams])[order]  # type: ignore[misc]
    zeros = np.zeros(len(ids))
    columns += [zeros, zeros, zeros, cov[:, 0], cov[:, 1], cov[:, 2]]
    return _cloud(un, columns, FUSION_CHANNELS + COVARIANCE_CHANNELS)


def encode_mono(frame: FrameFeatures, num_of_cam: int = 1) -> FeatureCloud:
    """Encode a frame in the VINS-Mono layout: five channels, points with track count > 1, camera by camera;
    eight with the features' covariances (channels 5-7).

    Args:
        num_of_cam: VINS ``NUM_OF_CAM``, the multiplier of the id channel (1 for VINS-Mono).
    """
    if num_of_cam < len(frame.cameras):
        n = len(frame.cameras)
        raise FeatureMessageError(f"num_of_cam {num_of_cam} is less than the frame's {n} cameras")
    parts = []
    for c in frame.cameras:
        keep = c.track_counts > 1
        wrapped = published_ids(c.ids[keep], "mono", num_of_cam)
        cov = c.covariance[keep] if c.covariance is not None else np.zeros((int(keep.sum()), 3))
        parts.append((wrapped * num_of_cam + c.camera_id, c.pixels[keep], c.undistorted[keep],
                      c.velocities[keep], cov))
    ids = np.concatenate([p[0] for p in parts])
    px = np.concatenate([p[1] for p in parts])
    un = np.concatenate([p[2] for p in parts])
    vel = np.concatenate([p[3] for p in parts])
    columns = [ids, px[:, 0], px[:, 1], vel[:, 0], vel[:, 1]]
    if not _covariances(frame):
        return _cloud(un, columns, MONO_CHANNELS)
    cov = np.concatenate([p[4] for p in parts])
    return _cloud(un, [*columns, cov[:, 0], cov[:, 1], cov[:, 2]], MONO_CHANNELS + COVARIANCE_CHANNELS)


def encode(frame: FrameFeatures, layout: Layout, num_of_cam: int = 1) -> FeatureCloud:
    """Encode a frame in ``layout`` ("fusion" or "mono")."""
    if layout == "fusion":
        return encode_fusion(frame)
    if layout == "mono":
        return encode_mono(frame, num_of_cam)
    raise FeatureMessageError(f"layout must be one of {LAYOUTS}, got {layout!r}")


def _check(points: np.ndarray, channels: np.ndarray, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, dtype=np.float64)
    ch = np.asarray(channels, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FeatureMessageError(f"points must have shape (N, 3), got {pts.shape}")
    if ch.ndim != 2 or ch.shape[1] != pts.shape[0]:
        raise FeatureMessageError(f"channels must have shape (C, {pts.shape[0]}), got {ch.shape}")
    if ch.shape[0] < minimum:
        raise FeatureMessageError(f"expected at least {minimum} channels, got {ch.shape[0]}")
    if np.any(pts[:, 2] != 1.0):
        raise FeatureMessageError("every point must have z == 1 (the estimator asserts it)")
    return pts, ch


def decode_fusion(points: np.ndarray, channels: np.ndarray) -> FeatureFrame:
    """Decode like VINS-Fusion's feature callback: channels by position, ids and camera ids truncated.

    Raises:
        FeatureMessageError: on fewer than six channels, six to eight channels (the stock estimator
            reads channels 6-8 as soon as there are more than five), or a point with z != 1.

    Shape:
        points: (N, 3). channels: (C, N).
    """
    pts, ch = _check(points, channels, 6)
    if 5 < ch.shape[0] < 9:
        raise FeatureMessageError(f"VINS-Fusion reads channels 6-8 when more than 5 exist; got {ch.shape[0]}")
    out: FeatureFrame = {}
    for i in range(pts.shape[0]):
        fid, cam = int(ch[0, i]), int(ch[1, i])  # C++ float -> int conversion truncates
        row = np.array([pts[i, 0], pts[i, 1], pts[i, 2], ch[2, i], ch[3, i], ch[4, i], ch[5, i]])
        out.setdefault(fid, []).append((cam, row))
    return out


def decode_mono(points: np.ndarray, channels: np.ndarray, num_of_cam: int = 1) -> FeatureFrame:
    """Decode like VINS-Mono's estimator: v = int(channel0 + 0.5), id = v / NUM_OF_CAM, cam = v % NUM_OF_CAM.

    Shape:
        points: (N, 3). channels: (C, N), C >= 5.
    """
    pts, ch = _check(points, channels, 5)
    out: FeatureFrame = {}
    for i in range(pts.shape[0]):
        v = int(ch[0, i] + 0.5)
        row = np.array([pts[i, 0], pts[i, 1], pts[i, 2], ch[1, i], ch[2, i], ch[3, i], ch[4, i]])
        out.setdefault(v // num_of_cam, []).append((v % num_of_cam, row))
    return out


def decode_covariances(
    points: np.ndarray, channels: np.ndarray, layout: Layout, num_of_cam: int = 1
) -> dict[int, list[tuple[int, np.ndarray]]]:
    """The covariances a message carries, as the patched estimator of docs/vins_fusion.md reads them:
    ``{feature_id: [(camera_id, [sigma_uu, sigma_uv, sigma_vv]), ...]}`` (ids and cameras decoded as
    :func:`decode` does); empty when the message has no covariance channels.

    Shape:
        points: (N, 3). channels: (C, N).
    """
    if layout not in LAYOUTS:
        raise FeatureMessageError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    first = len(FUSION_CHANNELS) if layout == "fusion" else len(MONO_CHANNELS)
    decode(points, channels, layout, num_of_cam)  # the same checks as the estimator's part
    ch = np.asarray(channels, dtype=np.float64)
    if ch.shape[0] < first + len(COVARIANCE_CHANNELS):
        return {}
    out: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i in range(ch.shape[1]):
        if layout == "fusion":
            fid, cam = int(ch[0, i]), int(ch[1, i])
        else:
            v = int(ch[0, i] + 0.5)
            fid, cam = v // num_of_cam, v % num_of_cam
        out.setdefault(fid, []).append((cam, ch[first:first + len(COVARIANCE_CHANNELS), i].copy()))
    return out


def decode(points: np.ndarray, channels: np.ndarray, layout: Layout, num_of_cam: int = 1) -> FeatureFrame:
    """Decode a message of ``layout`` ("fusion" or "mono")."""
    if layout == "fusion":
        return decode_fusion(points, channels)
    if layout == "mono":
        return decode_mono(points, channels, num_of_cam)
    raise FeatureMessageError(f"layout must be one of {LAYOUTS}, got {layout!r}")
