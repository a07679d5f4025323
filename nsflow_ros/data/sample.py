"""The built-in sample sequence: a synthetic EuRoC-like stereo-inertial flight, written in EuRoC's forms.

:func:`make_sample_sequence` renders a seeded flight through a textured room (:mod:`.scene`) with a
synthetic IMU (:mod:`.motion`) and writes under ``out_dir``:

* ``asl/mav0/``: EuRoC's ASL layout, ``cam0/`` and ``cam1/`` (``data.csv``, ``data/<ns>.png`` mono8
  752x480, ``sensor.yaml``), ``imu0/`` (200 Hz) and ``state_groundtruth_estimate0/data.csv``;
* ``ros2/`` (mcap) and ``sample.bag`` (ROS 1) with EuRoC's topics ``/cam0/image_raw``, ``/cam1/image_raw``,
  ``/imu0`` and ``/leica/position`` (geometry_msgs/PointStamped, body position at the camera rate);
* ``sequence.json``, ``poses.npz`` and ``groundtruth.csv`` (EuRoC's ground-truth layout at the IMU rate),
  from which :class:`SampleSequence` recomputes exact depth and flow for any pixel of any frame;
* ``done``, written last: the sequence is built in a hidden folder beside ``out_dir`` and renamed into
  place, so an interrupted run never leaves something that looks complete.

The outputs are a pure function of the parameters: the same ones again return the existing sequence.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import uuid
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from nsflow_ros.data.camera import EUROC_CAM0, EUROC_CAM1, PinholeRadtan
from nsflow_ros.data.errors import DataError
from nsflow_ros.data.motion import (
    EUROC_IMU_NOISE,
    NO_IMU_NOISE,
    ImuNoise,
    Trajectory,
    rotation_to_quaternion,
    synthesize_imu,
)
from nsflow_ros.data.scene import Rendered, Renderer, Scene, flow_between, ray_depth
from nsflow_ros.data.writers import (
    ASL_GROUNDTRUTH_HEADER,
    AslWriter,
    BagWriter,
    groundtruth_row,
    temp_sibling,
)
from nsflow_ros.progress import progress_bar

__all__ = [
    "FORMATS",
    "GROUNDTRUTH_TOPIC",
    "IMAGE_TOPIC",
    "IMU_TOPIC",
    "SAMPLE_VERSION",
    "SampleSequence",
    "is_sample",
    "make_sample_sequence",
]

SAMPLE_VERSION = 2  # bump whenever the generator's output changes, so stale copies are not reused
FORMATS = ("asl", "ros2", "ros1")
IMAGE_TOPIC = "/cam{}/image_raw"
IMU_TOPIC = "/imu0"
GROUNDTRUTH_TOPIC = "/leica/position"
T0_NS = 1_700_000_000_000_000_000  # first stamp: 2023-11-14T22:13:20Z, EuRoC-like 19-digit stamps


@dataclass(frozen=True)
class _Params:
    seed: int
    duration: float
    rate_hz: float
    imu_rate_hz: float
    stereo: bool
    image_noise: float
    imu_noise: bool
    rest: float = 0.0

    def key(self) -> dict[str, Any]:
        # A flight without rest keeps the key it had before rests existed, so its rendered copies stay valid.
        fields = {k: v for k, v in self.__dict__.items() if k != "rest" or v}
        return {"version": SAMPLE_VERSION, **fields}


class SampleSequence:
    """A generated sample sequence on disk, with exact ground truth on demand.

    Attributes:
        root: the sequence folder.
        params: generation parameters (seed, duration, rates, stereo, noise).
        formats: formats present (subset of ``asl``, ``ros2``, ``ros1``).
        stamps_ns: (N,) int64 image stamps.
        cameras: the cameras (cam0, and cam1 if stereo).
        scene: the rendered scene.
        trajectory: the body trajectory (time zero at ``stamps_ns[0]``).
    """

    def __init__(self, root: Path, meta: dict[str, Any], poses: dict[str, np.ndarray]) -> None:
        self.root = Path(root)
        self.meta = meta
        self.params: dict[str, Any] = meta["params"]
        self.formats: tuple[str, ...] = tuple(meta["formats"])
        self.t0_ns = int(meta["t0_ns"])
        self.stamps_ns = np.asarray(poses["stamps_ns"], dtype=np.int64)
        self.cameras = [PinholeRadtan.from_dict(c) for c in meta["cameras"]]
        self.scene = Scene.from_dict(meta["scene"])
        self.trajectory = Trajectory.from_dict(meta["trajectory"])
        self._poses = poses

    @classmethod
    def load(cls, root: str | Path) -> SampleSequence:
        """Open a sequence made by :func:`make_sample_sequence`.

        Raises:
            DataError: when ``root`` lacks the ``done`` marker or its sidecar files are unreadable.
        """
        root = Path(root)
        if not (root / "done").is_file():
            raise DataError(f"{root} is not a complete sample sequence (no 'done' marker)")
        try:
            meta = json.loads((root / "sequence.json").read_text())
            with np.load(root / "poses.npz") as npz:
                poses = {k: npz[k] for k in npz.files}
            return cls(root, meta, poses)
        except (OSError, ValueError, KeyError) as err:
            raise DataError(f"cannot read the sample sequence sidecar in {root}: {err}") from None

    # -- layout -----------------------------------------------------------------------------------------

    @property
    def asl_dir(self) -> Path:
        """The ASL folder (holding ``mav0``)."""
        return self.root / "asl"

    @property
    def ros2_dir(self) -> Path:
        """The ROS 2 bag folder (mcap)."""
        return self.root / "ros2"

    @property
    def ros1_path(self) -> Path:
        """The ROS 1 bag file."""
        return self.root / "sample.bag"

    @property
    def groundtruth_csv(self) -> Path:
        """Body (IMU) ground truth at the IMU rate in EuRoC's csv layout, whatever the formats."""
        return self.root / "groundtruth.csv"

    def path(self, fmt: str) -> Path:
        """Location of one format (``asl``, ``ros2`` or ``ros1``)."""
        return {"asl": self.asl_dir, "ros2": self.ros2_dir, "ros1": self.ros1_path}[fmt]

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def __repr__(self) -> str:
        return f"SampleSequence({str(self.root)!r}, frames={len(self)}, cameras={len(self.cameras)})"

    # -- ground truth -----------------------------------------------------------------------------------

    def _check(self, i: int, cam: int) -> None:
        if not 0 <= i < len(self):
            raise DataError(f"frame index {i} outside 0..{len(self) - 1}")
        if not 0 <= cam < len(self.cameras):
            raise DataError(f"camera index {cam} outside 0..{len(self.cameras) - 1}")

    def time(self, i: int) -> float:
        """Seconds from the first frame to frame ``i``."""
        return float(self.stamps_ns[i] - self.t0_ns) * 1e-9

    def pose(self, i: int, cam: int = 0) -> np.ndarray:
        """Camera-to-world transform ``T_wc`` of camera ``cam`` at frame ``i``. Shape: (4, 4)."""
        self._check(i, cam)
        return self._poses[f"T_w_cam{cam}"][i].copy()

    def body_pose(self, i: int) -> np.ndarray:
        """Body (IMU)-to-world transform at frame ``i``. Shape: (4, 4)."""
        self._check(i, 0)
        return self._poses["T_w_body"][i].copy()

    @cached_property
    def _renderers(self) -> list[Renderer]:
        return [Renderer(self.scene, c) for c in self.cameras]

    def render(self, i: int, cam: int = 0) -> Rendered:
        """Render frame ``i`` of camera ``cam`` again (identical to the stored image) with its depth."""
        self._check(i, cam)
        return _render(self._renderers[cam], self.pose(i, cam), self.params, cam, i)

    def image(self, i: int, cam: int = 0) -> np.ndarray:
        """The stored image (re-rendered when there is no ASL copy). Shape: (H, W) uint8."""
        self._check(i, cam)
        png = self.asl_dir / "mav0" / f"cam{cam}" / "data" / f"{int(self.stamps_ns[i])}.png"
        if png.is_file():
            import cv2

            img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
            if img is not None:
                return img
        return self.render(i, cam).image

    def depth(self, i: int, cam: int = 0) -> np.ndarray:
        """z-depth (m) of every pixel of frame ``i``. Shape: (H, W) float32."""
        return self.render(i, cam).depth

    def depth_at(self, i: int, pixels: Any, cam: int = 0) -> np.ndarray:
        """Exact z-depth (m) at sub-pixel positions of frame ``i``. Shape: (N, 2) -> (N,) float64."""
        self._check(i, cam)
        return ray_depth(self.scene, self.cameras[cam], self.pose(i, cam), pixels)

    def flow(self, i: int, j: int, pixels: Any, cam: int = 0, cam_j: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Exact optical flow of ``pixels`` (N, 2) of frame ``i`` (camera ``cam``) to frame ``j``.

        Args:
            cam_j: camera of frame j (default ``cam``; ``i == j, cam=0, cam_j=1`` is stereo matching).

        Returns:
            ``(flow, visible)`` as :func:`nsflow_ros.data.scene.flow_between` returns them.
        """
        cj = cam if cam_j is None else cam_j
        self._check(i, cam)
        self._check(j, cj)
        return flow_between(self.scene, self.cameras[cam], self.pose(i, cam), self.cameras[cj],
                            self.pose(j, cj), pixels)


def _render(renderer: Renderer, T_wc: np.ndarray, params: dict[str, Any], cam: int, i: int) -> Rendered:
    seed = np.random.SeedSequence([int(params["seed"]), 0x1316, cam, int(i)]).generate_state(1)[0]
    return renderer.render(T_wc, noise_sigma=float(params["image_noise"]), noise_seed=int(seed))


def _is_complete(root: Path, key: dict[str, Any], formats: Sequence[str]) -> bool:
    try:
        meta = json.loads((root / "sequence.json").read_text())
    except (OSError, ValueError):
        return False
    have = set(meta.get("formats", []))
    return (root / "done").is_file() and meta.get("params") == key and set(formats) <= have


def is_sample(root: Path) -> bool:
    """Whether ``root`` holds a complete sample sequence (its metadata and its completion mark)."""
    return (root / "sequence.json").is_file() and (root / "done").is_file()


def make_sample_sequence(out_dir: str | Path, *, seed: int = 0, duration: float = 10.0, rate_hz: float = 20.0,
                         stereo: bool = True, formats: Sequence[str] = FORMATS, imu_rate_hz: float = 200.0,
                         image_noise: float = 1.0, imu_noise: bool = True, progress: bool | None = None,
                         overwrite: bool = False, workers: int = 2, rest: float = 0.0) -> SampleSequence:
    """Make (or reuse) a synthetic EuRoC-like sequence; see the module docstring for the layout.

    Args:
        out_dir: folder to create.
        seed: seed of scene, trajectory, IMU noise and image noise.
        duration: seconds of images (IMU and ground truth cover ``[0, duration]``).
        formats: any of :data:`FORMATS`.
        imu_rate_hz: IMU and ground-truth rate.
        image_noise: standard deviation of the images' Gaussian noise in gray levels.
        imu_noise: add EuRoC-like IMU noise and bias random walk (False: exact kinematics, zero bias).
        progress: show progress; None shows it only when stderr is a terminal.
        overwrite: replace a non-empty ``out_dir`` that is not a sample sequence (a sample sequence with
            other parameters is always replaced, one with these parameters reused).
        workers: render threads (NumPy and OpenCV release the GIL in the heavy parts).
        rest: seconds the body holds its first pose before it flies, as EuRoC's flights start
            (:attr:`~nsflow_ros.data.motion.Trajectory.rest`); 0 = in flight from the first frame.

    Raises:
        DataError: on bad parameters, when ``out_dir`` holds other files and ``overwrite`` is false,
            or when it cannot be created.
    """
    root = Path(out_dir)
    fmts = tuple(dict.fromkeys(formats))
    bad = [f for f in fmts if f not in FORMATS]
    if bad:
        raise DataError(f"unknown format(s) {', '.join(map(repr, bad))}; "
                        f"expected any of {', '.join(FORMATS)}")
    if not (math.isfinite(rest) and rest >= 0):
        raise DataError(f"rest must be a finite number of seconds >= 0, got {rest}")
    if not (duration > 0 and rate_hz > 0 and imu_rate_hz > 0):
        raise DataError("duration, rate_hz and imu_rate_hz must be positive, "
                        f"got {duration}, {rate_hz}, {imu_rate_hz}")
    n_frames = round(duration * rate_hz)
    if n_frames < 1:
        raise DataError(f"duration {duration} s at {rate_hz} Hz gives no frame")
    params = _Params(int(seed), float(duration), float(rate_hz), float(imu_rate_hz), bool(stereo),
                     float(image_noise), bool(imu_noise), float(rest))
    key = params.key()
    if _is_complete(root, key, fmts):
        return SampleSequence.load(root)
    empty_dir = root.is_dir() and not any(root.iterdir())
    if root.exists() and not empty_dir and not is_sample(root) and not overwrite:
        raise DataError(f"{root} exists and is not a sample sequence; choose another folder or overwrite it")

    tmp = temp_sibling(root)
    try:
        tmp.mkdir(parents=True)
    except OSError as err:  # name the folder asked for, not the temporary sibling
        raise DataError(f"cannot create {root}: {err.strerror}") from None
    try:
        _generate(tmp, params, key, fmts, n_frames, progress, workers)
        # Another process may have finished the same sequence meanwhile: keep its copy then.
        if not _is_complete(root, key, fmts):
            _replace(tmp, root)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return SampleSequence.load(root)


def _replace(tmp: Path, root: Path) -> None:
    """Move the finished ``tmp`` to ``root``, replacing what is there with as short a gap as possible."""
    if root.exists() or root.is_symlink():
        old = root.with_name(f".{root.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        root.rename(old)
        tmp.rename(root)
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink()
    else:
        tmp.rename(root)


def _generate(out: Path, p: _Params, key: dict[str, Any], fmts: tuple[str, ...], n_frames: int,
              progress: bool | None, workers: int) -> None:
    scene = Scene.from_seed(p.seed)
    traj = Trajectory.from_seed(p.seed, rest=p.rest)
    cams = [EUROC_CAM0, EUROC_CAM1] if p.stereo else [EUROC_CAM0]
    frame_ns = (np.arange(n_frames) * (1e9 / p.rate_hz)).round().astype(np.int64)
    stamps = T0_NS + frame_ns
    n_imu = int(np.floor(p.duration * p.imu_rate_hz + 1e-9)) + 1
    imu_stamps = T0_NS + (np.arange(n_imu) * (1e9 / p.imu_rate_hz)).round().astype(np.int64)
    noise: ImuNoise = EUROC_IMU_NOISE if p.imu_noise else NO_IMU_NOISE
    imu = synthesize_imu(traj, imu_stamps, T0_NS, noise=noise, seed=p.seed)
    t_imu = (imu_stamps - T0_NS) * 1e-9
    gt_q = rotation_to_quaternion(traj.rotation(t_imu))
    gt_p, gt_v = traj.position(t_imu), traj.velocity(t_imu)

    t_frames = frame_ns * 1e-9
    poses = {"stamps_ns": stamps, "T_w_body": traj.pose(t_frames)}
    for k, cam in enumerate(cams):
        poses[f"T_w_cam{k}"] = traj.camera_pose(t_frames, cam)
        bad = [i for i in range(n_frames) if not scene.contains(poses[f"T_w_cam{k}"][i, :3, 3], margin=0.3)]
        if bad:
            raise DataError(f"seed {p.seed}: camera {cam.name} comes within 0.3 m of a surface "
                            f"at frame {bad[0]}")

    asl = AslWriter(out / "asl" / "mav0") if "asl" in fmts else None
    bags = []
    if "ros2" in fmts:
        bags.append(BagWriter(out / "ros2", storage="mcap"))
    if "ros1" in fmts:
        bags.append(BagWriter(out / "sample.bag", ros1=True))
    if asl:
        for k, cam in enumerate(cams):
            asl.add_camera(f"cam{k}", cam, p.rate_hz)
        asl.add_imu(p.imu_rate_hz, noise)
    for bag in bags:
        bag.open()

    def write_imu_until(stamp: int, m: int) -> int:
        # IMU (and ground truth) up to and including ``stamp``, before the images of that stamp.
        while m < n_imu and imu_stamps[m] <= stamp:
            s = int(imu_stamps[m])
            if asl:
                asl.write_imu(s, imu.gyro[m], imu.accel[m])
                asl.write_groundtruth(s, gt_p[m], gt_q[m], gt_v[m], imu.gyro_bias[m], imu.accel_bias[m])
            for bag in bags:
                bag.write_imu(IMU_TOPIC, s, imu.gyro[m], imu.accel[m], "imu0")
            m += 1
        return m

    renderers = [Renderer(scene, cam) for cam in cams]
    _ = scene.atlas  # built here once, not raced for by the render threads
    params = key

    def render_frame(i: int) -> list[tuple[np.ndarray, bytes | None]]:
        # Rendering and PNG encoding both run here, in the worker threads.
        images = [_render(r, poses[f"T_w_cam{k}"][i], params, k, i).image for k, r in enumerate(renderers)]
        return [(img, asl.encode(img) if asl else None) for img in images]

    show = sys.stderr.isatty() if progress is None else progress
    bar = progress_bar(total=n_frames, desc="sample sequence", unit="frame", enabled=show)
    m = 0
    try:
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            pending: deque[Future[list[tuple[np.ndarray, bytes | None]]]] = deque()
            nxt = 0
            for i in range(n_frames):
                # Keep a few frames in flight: parallel, but with bounded memory.
                while nxt < n_frames and len(pending) < 2 * max(1, workers):
                    pending.append(pool.submit(render_frame, nxt))
                    nxt += 1
                images = pending.popleft().result()
                s = int(stamps[i])
                m = write_imu_until(s, m)
                for k, (img, png) in enumerate(images):
                    if asl and png is not None:
                        asl.write_image(f"cam{k}", s, png)
                    for bag in bags:
                        bag.write_image(IMAGE_TOPIC.format(k), s, img, f"cam{k}", "mono8")
                for bag in bags:
                    bag.write_point(GROUNDTRUTH_TOPIC, s, poses["T_w_body"][i, :3, 3], "world")
                bar.update(1)
        write_imu_until(int(imu_stamps[-1]), m)
    except BaseException:
        for bag in bags:
            bag.abort()
        raise
    finally:
        bar.close()
        if asl:
            asl.close()
    for bag in bags:
        bag.close()

    meta = {
        "version": SAMPLE_VERSION,
        "params": key,
        "formats": list(fmts),
        "t0_ns": T0_NS,
        "image_stamps_ns": stamps.tolist(),
        "imu": {"rate_hz": p.imu_rate_hz, "count": n_imu, "noise": noise.__dict__},
        "topics": {
            "images": [IMAGE_TOPIC.format(k) for k in range(len(cams))],
            "imu": IMU_TOPIC,
            "groundtruth": GROUNDTRUTH_TOPIC,
        },
        "cameras": [c.to_dict() for c in cams],
        "scene": scene.to_dict(),
        "trajectory": traj.to_dict(),
    }
    np.savez(out / "poses.npz", **poses)
    # Ground truth for trajectory evaluation whatever the formats (EuRoC csv layout, IMU rate).
    with (out / "groundtruth.csv").open("w", newline="\n") as f:
        f.write(ASL_GROUNDTRUTH_HEADER + "\n")
        for m in range(n_imu):
            f.write(groundtruth_row(int(imu_stamps[m]), gt_p[m], gt_q[m], gt_v[m], imu.gyro_bias[m],
                                    imu.accel_bias[m]))
    (out / "sequence.json").write_text(json.dumps(meta, indent=1))
    (out / "done").write_text(json.dumps(key) + "\n")
