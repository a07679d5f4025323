"""A textured indoor scene (a room with boxes), rendered by vectorised ray casting, with exact flow.

Every face carries a scikit-image photograph (mirror-tiled) under Lambertian point lights; shading depends
on the surface point only, never on the viewpoint, so brightness constancy holds between frames as optical
flow assumes. A pixel's ray comes from undistorting it through EuRoC's pinhole-radtan model, so images carry
the real lens distortion; depth is the hit point's z in the camera frame. Ground-truth flow backprojects
with a fresh ray cast (no interpolated depth map), projects with distortion into the other view, and marks
a point not visible outside the image or behind a nearer surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from nsflow_ros.data.camera import PinholeRadtan, as_points
from nsflow_ros.data.errors import DataError
from nsflow_ros.optional import require

__all__ = [
    "TEXTURES",
    "Box",
    "Material",
    "Rendered",
    "Renderer",
    "Scene",
    "flow_between",
    "ray_depth",
    "texture_dir",
]

# Photographs shipped with scikit-image (skimage/data); graphics and near-empty images left out.
TEXTURES = (
    "brick.png", "grass.png", "gravel.png", "camera.png", "astronaut.png", "coffee.png",
    "chelsea.png", "rocket.jpg", "motorcycle_left.png", "moon.png", "coins.png", "ihc.png",
)
_FLOOR_TEXTURES = ("brick.png", "grass.png", "gravel.png", "coins.png")
_CEILING_TEXTURES = ("moon.png", "gravel.png", "brick.png")
TILE = 512  # texels per texture tile side
_MIP_SIGMAS = (0.0, 1.0, 2.0)  # Gaussian prefilter per level: footprint 1, 2, 4 texels
_ATLAS_COLS = 4
_NO_HIT = -1


def texture_dir() -> Path:
    """The folder holding scikit-image's sample photographs."""
    skimage = require("skimage", "the sample renderer (its textures are scikit-image's photos)")
    return Path(skimage.__file__).resolve().parent / "data"


def _load_tile(name: str) -> np.ndarray:
    """One texture as a square float32 tile in [0, 1], contrast-normalised. Shape: (TILE, TILE)."""
    path = texture_dir() / name
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DataError(f"cannot read texture {path} (is scikit-image installed with its sample data?)")
    h, w = img.shape
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    interp = cv2.INTER_AREA if s > TILE else cv2.INTER_CUBIC
    tile = cv2.resize(img, (TILE, TILE), interpolation=interp).astype(np.float32) / 255.0
    # Same contrast for every photo, so that no face is featureless or saturated.
    std = float(tile.std()) or 1.0
    return np.clip((tile - tile.mean()) / std * 0.17 + 0.5, 0.03, 0.97).astype(np.float32)


@dataclass(frozen=True)
class Material:
    """How one face looks.

    Attributes:
        texture: index into the scene's texture list.
        scale: metres covered by one texture tile.
        offset: (2,) tile offset in tiles (shifts the texture on the face).
        orient: 0..7, swap/flip of the face's (u, v) axes (rotations and mirrors of the texture).
        gain: albedo multiplier.
        contrast: texture contrast multiplier around mid-gray.
    """

    texture: int
    scale: float
    offset: tuple[float, float]
    orient: int
    gain: float
    contrast: float


@dataclass(frozen=True)
class Box:
    """A box: centre (m), half extents (m) and yaw (rad, about world z); one material per face.

    Faces are ordered -x, +x, -y, +y, -z, +z in the box's own frame.
    """

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    materials: tuple[Material, ...]


def _material_dict(m: Material) -> dict[str, Any]:
    return {"texture": m.texture, "scale": m.scale, "offset": list(m.offset), "orient": m.orient,
            "gain": m.gain, "contrast": m.contrast}


def _material_from(d: dict[str, Any]) -> Material:
    return Material(int(d["texture"]), float(d["scale"]), (float(d["offset"][0]), float(d["offset"][1])),
                    int(d["orient"]), float(d["gain"]), float(d["contrast"]))


class Scene:
    """The room, its boxes, lights and textures; ray casting against them.

    Surfaces are numbered: room faces 0..5 (-x, +x, -y, +y, floor, ceiling), then 6 per box.

    Args:
        room_min, room_max: opposite corners of the room (m), floor at ``room_min[2]``.
        room_materials: 6 materials for -x, +x, -y, +y walls, floor, ceiling.
        textures: texture file names in scikit-image's data folder (see :data:`TEXTURES`).
        lights: (L, 3) point-light positions (m).
        ambient: shading floor in [0, 1].
        seed: the seed the scene was drawn from (informative only), or None.

    Raises:
        DataError: on inconsistent sizes (room corners, material counts, texture indices).
    """

    def __init__(self, room_min: Any, room_max: Any, boxes: list[Box], room_materials: list[Material],
                 textures: tuple[str, ...] = TEXTURES, lights: Any = ((0.0, 0.0, 2.9),),
                 ambient: float = 0.45, seed: int | None = None) -> None:
        self.room_min = np.asarray(room_min, dtype=np.float64).reshape(3)
        self.room_max = np.asarray(room_max, dtype=np.float64).reshape(3)
        if not np.all(self.room_max > self.room_min):
            raise DataError(f"room corners must satisfy min < max, got {self.room_min} and {self.room_max}")
        if len(room_materials) != 6:
            raise DataError(f"room needs 6 materials, got {len(room_materials)}")
        self.boxes = list(boxes)
        self.room_materials = list(room_materials)
        self.textures = tuple(textures)
        self.lights = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
        self.ambient = float(ambient)
        self.seed = seed
        for b in self.boxes:
            if len(b.materials) != 6:
                raise DataError(f"box at {b.center} needs 6 materials, got {len(b.materials)}")
        for m in self.materials:
            if not 0 <= m.texture < len(self.textures):
                raise DataError(f"material texture index {m.texture} outside 0..{len(self.textures) - 1}")
        self._build_surfaces()

    # -- construction ------------------------------------------------------------------------------------

    @classmethod
    def from_seed(cls, seed: int = 0, *, n_boxes: int = 8) -> Scene:
        """Draw a room of 9 x 7 x 3.2 m with ``n_boxes`` boxes near the walls, deterministically.

        The central region ``|x| < 2.2, |y| < 1.7`` stays free of boxes so that trajectories from
        :mod:`nsflow_ros.data.motion` keep at least about 0.5 m from every surface.
        """
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE7E]))
        lo, hi = np.array([-4.5, -3.5, 0.0]), np.array([4.5, 3.5, 3.2])
        tex = {name: i for i, name in enumerate(TEXTURES)}

        def material(choices: tuple[str, ...], scale: tuple[float, float]) -> Material:
            return Material(tex[str(rng.choice(choices))], float(rng.uniform(*scale)),
                            (float(rng.uniform(0, 2)), float(rng.uniform(0, 2))), int(rng.integers(8)),
                            float(rng.uniform(0.75, 1.1)), float(rng.uniform(0.7, 1.0)))

        # Four different photos on the walls, so that no two walls look alike.
        walls = [material((name,), (1.8, 3.0)) for name in rng.permutation(TEXTURES)[:4]]
        room = [*walls, material(_FLOOR_TEXTURES, (1.2, 2.2)), material(_CEILING_TEXTURES, (2.0, 3.0))]
        boxes = []
        for k in range(n_boxes):
            half = rng.uniform([0.2, 0.2, 0.2], [0.6, 0.6, 0.6])
            # Alternate between the x-ends and the y-sides of the room, clear of the central region.
            if k % 2 == 0:
                x = rng.choice([-1, 1]) * rng.uniform(2.2 + 0.85, 4.5)
                y = rng.uniform(-3.5, 3.5)
            else:
                x = rng.uniform(-4.5, 4.5)
                y = rng.choice([-1, 1]) * rng.uniform(1.7 + 0.85, 3.5)
            on_floor = rng.random() < 0.6
            z = half[2] if on_floor else rng.uniform(0.8, 2.6)
            yaw = float(rng.uniform(-np.pi, np.pi))
            mats = tuple(material(TEXTURES, (0.7, 1.5)) for _ in range(6))
            boxes.append(Box((float(x), float(y), float(z)), tuple(float(h) for h in half), yaw, mats))
        lights = [(-2.0, rng.uniform(-1, 1), 3.0), (2.0, rng.uniform(-1, 1), 3.0)]
        return cls(lo, hi, boxes, room, TEXTURES, lights, 0.42, seed=int(seed))

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON description that :meth:`from_dict` reads back."""
        return {
            "room_min": self.room_min.tolist(),
            "room_max": self.room_max.tolist(),
            "room_materials": [_material_dict(m) for m in self.room_materials],
            "boxes": [{"center": list(b.center), "half": list(b.half), "yaw": b.yaw,
                       "materials": [_material_dict(m) for m in b.materials]} for b in self.boxes],
            "textures": list(self.textures),
            "lights": self.lights.tolist(),
            "ambient": self.ambient,
            "seed": self.seed,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Scene:
        """Rebuild a scene from :meth:`to_dict` output.

        Raises:
            DataError: when a key is missing or malformed.
        """
        try:
            boxes = [Box(tuple(b["center"]), tuple(b["half"]), float(b["yaw"]),
                         tuple(_material_from(m) for m in b["materials"])) for b in d["boxes"]]
            return cls(d["room_min"], d["room_max"], boxes, [_material_from(m) for m in d["room_materials"]],
                       tuple(d["textures"]), d["lights"], float(d["ambient"]), d.get("seed"))
        except (KeyError, TypeError, ValueError, IndexError) as err:
            raise DataError(f"invalid scene description: {type(err).__name__}: {err}") from None

    @property
    def materials(self) -> list[Material]:
        """Materials of all surfaces, in surface order."""
        return [*self.room_materials, *(m for b in self.boxes for m in b.materials)]

    def _build_surfaces(self) -> None:
        """Per-surface tables (gathered per pixel): origin, u/v axes, normal, material terms."""
        origins, uaxes, vaxes, normals = [], [], [], []
        eye = np.eye(3)

        def face(center: np.ndarray, R: np.ndarray, axis: int, sign: int, normal_sign: int) -> None:
            # Axes of the face plane in the frame R (columns = frame axes in world).
            a, b = [i for i in range(3) if i != axis]
            origins.append(center)
            uaxes.append(R[:, a])
            vaxes.append(R[:, b])
            normals.append(normal_sign * sign * R[:, axis])

        for axis in range(3):
            for sign, bound in ((-1, self.room_min), (1, self.room_max)):
                c = np.zeros(3)
                c[axis] = bound[axis]
                face(c, eye, axis, sign, -1)  # walls face into the room
        for b in self.boxes:
            cy, sy = np.cos(b.yaw), np.sin(b.yaw)
            R = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
            for axis in range(3):
                for sign in (-1, 1):
                    c = np.asarray(b.center) + sign * b.half[axis] * R[:, axis]
                    face(c, R, axis, sign, 1)
        mats = self.materials
        U, V = np.array(uaxes), np.array(vaxes)
        # Texture orientation: optional swap of u and v, then optional flips.
        orient = np.array([m.orient for m in mats])
        swap = (orient & 4).astype(bool)
        U2, V2 = np.where(swap[:, None], V, U), np.where(swap[:, None], U, V)
        U2 *= np.where(orient & 1, -1.0, 1.0)[:, None]
        V2 *= np.where(orient & 2, -1.0, 1.0)[:, None]
        scale = np.array([m.scale for m in mats])
        self._origin = np.array(origins)
        self._uax = U2 / scale[:, None]  # so that (P - origin) . uax is in tiles
        self._vax = V2 / scale[:, None]
        self._normal = np.array(normals)
        self._offset = np.array([m.offset for m in mats])
        self._texel = scale / TILE  # metres per texel
        self._gain = np.array([m.gain for m in mats])
        self._contrast = np.array([m.contrast for m in mats])
        tex = np.array([m.texture for m in mats])
        self._tile_x = (tex % _ATLAS_COLS) * TILE
        self._tile_y = (tex // _ATLAS_COLS) * TILE
        # float32 per-component copies for fast per-pixel gathers; u0/v0 fold origin and offset in.
        f32 = np.float32
        self._tables = {
            "ux": self._uax[:, 0].astype(f32), "uy": self._uax[:, 1].astype(f32),
            "uz": self._uax[:, 2].astype(f32),
            "vx": self._vax[:, 0].astype(f32), "vy": self._vax[:, 1].astype(f32),
            "vz": self._vax[:, 2].astype(f32),
            "u0": (self._offset[:, 0] - (self._origin * self._uax).sum(axis=1)).astype(f32),
            "v0": (self._offset[:, 1] - (self._origin * self._vax).sum(axis=1)).astype(f32),
            "nx": self._normal[:, 0].astype(f32), "ny": self._normal[:, 1].astype(f32),
            "nz": self._normal[:, 2].astype(f32),
            "tile_x": self._tile_x.astype(f32), "tile_y": self._tile_y.astype(f32),
            "inv_texel": (1.0 / self._texel).astype(f32),
            "gain": self._gain.astype(f32), "contrast": self._contrast.astype(f32),
        }
        # Box parameters for the slab test, plus a bounding sphere for a cheap per-pixel cull.
        self._box_center = np.array([b.center for b in self.boxes]).reshape(-1, 3)
        self._box_half = np.array([b.half for b in self.boxes]).reshape(-1, 3)
        self._box_cs = np.array([[np.cos(b.yaw), np.sin(b.yaw)] for b in self.boxes]).reshape(-1, 2)
        self._box_radius = np.linalg.norm(self._box_half, axis=1)

    @cached_property
    def atlas(self) -> np.ndarray:
        """Texture tiles on a grid, one grid per prefilter level, levels stacked vertically.

        Shape: (levels * rows * TILE, cols * TILE) float32; level ``l`` starts at row ``l * rows * TILE``.
        """
        tiles = [_load_tile(name) for name in self.textures]
        rows = (len(tiles) + _ATLAS_COLS - 1) // _ATLAS_COLS
        atlas = np.zeros((len(_MIP_SIGMAS) * rows * TILE, _ATLAS_COLS * TILE), np.float32)
        for lvl, sigma in enumerate(_MIP_SIGMAS):
            for k, tile in enumerate(tiles):
                # Reflect-101 borders match the mirror tiling used when sampling: seamless blur.
                t = tile if not sigma else cv2.GaussianBlur(tile, (0, 0), sigma,
                                                            borderType=cv2.BORDER_REFLECT_101)
                r, c = divmod(k, _ATLAS_COLS)
                r += lvl * rows
                atlas[r * TILE:(r + 1) * TILE, c * TILE:(c + 1) * TILE] = t
        return atlas

    # -- geometry ----------------------------------------------------------------------------------------

    def contains(self, point: Any, margin: float = 0.0) -> bool:
        """Whether a point is inside the room and outside every box, with ``margin`` metres to spare."""
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if np.any(p < self.room_min + margin) or np.any(p > self.room_max - margin):
            return False
        for c, h, (cy, sy) in zip(self._box_center, self._box_half, self._box_cs, strict=True):
            d = p - c
            local = np.array([cy * d[0] + sy * d[1], -sy * d[0] + cy * d[1], d[2]])
            if np.all(np.abs(local) < h + margin):
                return False
        return True

    def cast(self, origin: Any, dirs: np.ndarray, dnorm: np.ndarray | None = None,
             windows: list[tuple[slice, ...] | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Intersect rays from one origin with the scene.

        Args:
            origin: (3,) ray origin in the world frame, inside the room.
            dirs: (3, ...) ray directions in the world frame (need not be unit); float32 or float64.
            dnorm: the norms of ``dirs``, if known.
            windows: per box, slices of the trailing axes of ``dirs`` outside which no ray can hit it
                (:class:`Renderer`'s screen-space bounds); None culls by each box's bounding cone.

        Returns:
            ``(t, surface)``: the hit is ``origin + t * dir``; int32 surface index, -1 where nothing is hit.

        Raises:
            DataError: when ``dirs`` is not (3, ...).

        Shape:
            dirs: (3, ...) -> t, surface: ``dirs.shape[1:]``.
        """
        if dirs.ndim < 2 or dirs.shape[0] != 3:
            raise DataError(f"ray directions: expected shape (3, N), got {dirs.shape}")
        dtype = dirs.dtype
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # Room: seen from inside, each axis' slab is left through exactly one of its two planes, the
            # one with positive t; the room is left through the slab exited first.
            t_axis = []
            for axis in range(3):
                inv = dtype.type(1.0) / dirs[axis]
                t_axis.append(np.maximum(dtype.type(self.room_max[axis] - o[axis]) * inv,
                                         dtype.type(self.room_min[axis] - o[axis]) * inv))
            t_best = np.minimum(np.minimum(t_axis[0], t_axis[1]), t_axis[2])
            # Face 2 * axis (min side) or 2 * axis + 1 (max side, when the ray runs towards +axis).
            side = [(dirs[a] > 0).astype(np.int32) for a in range(3)]
            surf = np.where(t_axis[0] == t_best, side[0],
                            np.where(t_axis[1] == t_best, 2 + side[1], 4 + side[2]))
            surf[~np.isfinite(t_best)] = _NO_HIT
            for k in range(len(self.boxes)):
                win = None if windows is None else windows[k]
                if win is not None:
                    self._cast_box(k, o, dirs[(slice(None), *win)], t_best[win], surf[win])
                    continue
                flat = dirs.reshape(3, -1)
                norm = np.sqrt((flat * flat).sum(axis=0)) if dnorm is None else dnorm.reshape(-1)
                idx = self._cone_cull(k, o, flat, norm)
                if idx is None:
                    self._cast_box(k, o, flat, t_best.reshape(-1), surf.reshape(-1))
                elif idx.size:
                    tb, sb = t_best.reshape(-1), surf.reshape(-1)
                    sub_t, sub_s = tb[idx], sb[idx]
                    self._cast_box(k, o, flat[:, idx], sub_t, sub_s)
                    tb[idx], sb[idx] = sub_t, sub_s
        return t_best, surf

    def _cone_cull(self, k: int, o: np.ndarray, dirs: np.ndarray, dnorm: np.ndarray) -> np.ndarray | None:
        """Indices of the rays inside box ``k``'s bounding cone; None when the origin is too close."""
        dtype = dirs.dtype.type
        to_c = self._box_center[k] - o
        dist = float(np.linalg.norm(to_c))
        r = self._box_radius[k]
        if dist <= r * 1.001:
            return None
        u = to_c / dist
        dot = dirs[0] * dtype(u[0]) + dirs[1] * dtype(u[1]) + dirs[2] * dtype(u[2])
        return np.flatnonzero(dot >= dnorm * dtype(np.sqrt(1.0 - (r / dist) ** 2)))

    def _cast_box(self, k: int, o: np.ndarray, D: np.ndarray, t_best: np.ndarray, surf: np.ndarray) -> None:
        """Slab test of rays ``D`` (3, ...) against box ``k``; updates the views ``t_best`` / ``surf``."""
        if D[0].size == 0:
            return
        dtype = D.dtype.type
        to_c = self._box_center[k] - o
        h = self._box_half[k]
        cy, sy = self._box_cs[k]
        # Ray in the box's frame (rotation by -yaw about z).
        dl = (D[0] * dtype(cy) + D[1] * dtype(sy), D[1] * dtype(cy) - D[0] * dtype(sy), D[2])
        ol = (cy * -to_c[0] + sy * -to_c[1], cy * -to_c[1] - sy * -to_c[0], -to_c[2])
        tmin, tmax = [], []
        for a in range(3):
            inv = dtype(1.0) / dl[a]
            t1 = dtype(-h[a] - ol[a]) * inv
            t2 = dtype(h[a] - ol[a]) * inv
            tmin.append(np.minimum(t1, t2))
            tmax.append(np.maximum(t1, t2))
        tnear = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        tfar = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        hit = (tnear <= tfar) & (tnear > 0) & (tnear < t_best)
        if not hit.any():
            return
        # The entry face is on the slab that tnear came from, on the side the ray comes from.
        base = 6 + 6 * k
        face = np.where(tmin[0] == tnear, base + (dl[0] < 0),
                        np.where(tmin[1] == tnear, base + 2 + (dl[1] < 0), base + 4 + (dl[2] < 0)))
        np.copyto(t_best, tnear, where=hit)
        np.copyto(surf, face, where=hit, casting="unsafe")

    # -- appearance --------------------------------------------------------------------------------------

    def shade(self, points: np.ndarray, surf: np.ndarray, footprint: np.ndarray,
              normal: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(N,) float32 intensity in [0, ~1] of surface points.

        Args:
            points: (3, N) float32 hit points in the world frame.
            surf: (N,) surface indices (all valid).
            footprint: (N,) size of a pixel on the surface in metres; picks the texture's prefilter level.
            normal: the surfaces' normals per point as three (N,) arrays, if already gathered.
        """
        f32 = np.float32
        tb = self._tables
        surf = surf.astype(np.intp, copy=False)  # gathers with native indices are faster
        px, py, pz = points[0], points[1], points[2]
        # Texture coordinates in tiles: P . axis + constant, per surface (see _build_tables).
        tu = px * tb["ux"][surf] + py * tb["uy"][surf] + pz * tb["uz"][surf] + tb["u0"][surf]
        tv = px * tb["vx"][surf] + py * tb["vy"][surf] + pz * tb["vz"][surf] + tb["v0"][surf]
        # Mirror tiling: a triangle wave keeps the texture continuous across tile borders.
        tu = f32(1.0) - np.abs(f32(1.0) - (tu - f32(2.0) * np.floor(tu * f32(0.5))))
        tv = f32(1.0) - np.abs(f32(1.0) - (tv - f32(2.0) * np.floor(tv * f32(0.5))))
        # Texture level: log2 of the footprint in texels, blended between the two adjacent levels.
        n_lvl = len(_MIP_SIGMAS)
        level = np.log2(np.maximum(footprint * tb["inv_texel"][surf], f32(1e-6)))
        np.clip(level, f32(0.0), f32(n_lvl - 1), out=level)
        lo = np.minimum(np.floor(level), f32(n_lvl - 2))
        frac = level - lo
        n = tu.size
        # remap wants 2-D maps with sides below 32767: fold the pixel list into rows of 1024.
        rows = -(-n // 1024)
        mx = np.zeros(rows * 1024, f32)
        my = np.zeros(rows * 1024, f32)
        mx[:n] = tu * f32(TILE - 1) + tb["tile_x"][surf]
        level_rows = f32(self.atlas.shape[0] // n_lvl)
        my[:n] = tv * f32(TILE - 1) + tb["tile_y"][surf] + lo * level_rows
        mx, my = mx.reshape(rows, 1024), my.reshape(rows, 1024)
        sample_lo = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR).reshape(-1)[:n]
        my += level_rows
        sample_hi = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR).reshape(-1)[:n]
        tex = sample_lo + frac * (sample_hi - sample_lo)
        albedo = tb["gain"][surf] * (f32(0.5) + tb["contrast"][surf] * (tex - f32(0.5)))
        # Lambertian point lights with soft distance falloff; viewpoint independent.
        nx, ny, nz = normal if normal is not None else (tb["nx"][surf], tb["ny"][surf], tb["nz"][surf])
        light = np.zeros(n, f32)
        for L in self.lights.astype(f32):
            lx, ly, lz = L[0] - px, L[1] - py, L[2] - pz
            d2 = lx * lx + ly * ly + lz * lz
            lam = np.maximum(lx * nx + ly * ny + lz * nz, f32(0.0)) / np.sqrt(d2)
            light += lam / (f32(1.0) + d2 * f32(1.0 / 16.0))
        return albedo * (f32(self.ambient) + f32(0.75) * light)


@dataclass(frozen=True)
class Rendered:
    """A rendered frame: (H, W) uint8 image and (H, W) float32 z-depth in metres (inf: nothing hit)."""

    image: np.ndarray
    depth: np.ndarray


class Renderer:
    """Renders a scene through one camera, whose distorted rays are computed once.

    Args:
        psf_sigma: Gaussian blur (pixels) standing for the lens' point-spread function, which also softens
            aliasing at silhouettes; 0 disables it.
    """

    def __init__(self, scene: Scene, camera: PinholeRadtan, psf_sigma: float = 0.6) -> None:
        self.scene = scene
        self.camera = camera
        self.psf_sigma = float(psf_sigma)
        grid = camera.ray_grid.reshape(-1, 2)
        self._rays = np.vstack([grid.T, np.ones((1, grid.shape[0]))]).astype(np.float32)  # (3, N), z = 1
        self._rnorm2 = (self._rays.astype(np.float64) ** 2).sum(axis=0).astype(np.float32)
        self._rnorm = np.sqrt(self._rnorm2)
        # Footprint of a pixel on a fronto-parallel surface at unit depth, per pixel (the lens
        # compresses the periphery, so pixels there cover more).
        J = _pixel_jacobian_area(camera, grid)
        self._pix_size = np.sqrt(J).astype(np.float32)
        # Per column / row, the range of normalised x / y its pixels cover (monotonic in the index):
        # turns a box's bounds in the normalised plane into a rectangle of pixels to test.
        g = camera.ray_grid
        self._col_x = (g[:, :, 0].min(axis=0), g[:, :, 0].max(axis=0))
        self._row_y = (g[:, :, 1].min(axis=1), g[:, :, 1].max(axis=1))

    def _windows(self, T: np.ndarray) -> list[tuple[slice, ...] | None]:
        """Per box, the rectangle of pixels that can see it (None: let the cone test decide)."""
        scene, H, W = self.scene, self.camera.height, self.camera.width
        centers = (scene._box_center - T[:3, 3]) @ T[:3, :3]  # box centres in the camera frame
        out: list[tuple[slice, ...] | None] = []
        for (x, y, z), r in zip(centers, scene._box_radius, strict=True):
            if z + r <= 0.0:
                out.append((slice(0, 0), slice(0, 0)))  # entirely behind the camera
                continue
            if z - r < 0.05:
                out.append(None)  # the bounding sphere reaches behind the camera
                continue
            # Bounds of X/Z and Y/Z over the sphere's bounding cube (Z > 0 there).
            xs = ((x - r) / (z - r), (x - r) / (z + r), (x + r) / (z - r), (x + r) / (z + r))
            ys = ((y - r) / (z - r), (y - r) / (z + r), (y + r) / (z - r), (y + r) / (z + r))
            c0 = int(np.searchsorted(self._col_x[1], min(xs), "left"))
            c1 = int(np.searchsorted(self._col_x[0], max(xs), "right"))
            r0 = int(np.searchsorted(self._row_y[1], min(ys), "left"))
            r1 = int(np.searchsorted(self._row_y[0], max(ys), "right"))
            out.append((slice(min(r0, H), max(r0, min(r1, H))), slice(min(c0, W), max(c0, min(c1, W)))))
        return out

    def render(self, T_wc: Any, *, noise_sigma: float = 0.0, noise_seed: int | None = None) -> Rendered:
        """Render the view of a camera at pose ``T_wc`` (4x4 camera-to-world).

        Args:
            noise_sigma: standard deviation of additive Gaussian pixel noise (gray levels).
            noise_seed: seed of that noise.

        Raises:
            DataError: when ``T_wc`` is not 4x4 or the camera is outside the free space of the room.
        """
        T = np.asarray(T_wc, dtype=np.float64)
        if T.shape != (4, 4):
            raise DataError(f"T_wc: expected shape (4, 4), got {T.shape}")
        o = T[:3, 3]
        if not self.scene.contains(o):
            raise DataError(f"camera position {o.round(3).tolist()} is outside the room or inside a box")
        cam = self.camera
        f32 = np.float32
        # Rotate the rays (z = 1) by hand: a 3x3 BLAS product over 361k columns is slower.
        R = T[:3, :3].astype(f32)
        rx, ry = self._rays[0], self._rays[1]
        dirs = np.empty_like(self._rays)
        for i in range(3):
            np.multiply(rx, R[i, 0], out=dirs[i])
            dirs[i] += ry * R[i, 1]
            dirs[i] += R[i, 2]
        t, surf = self.scene.cast(o, dirs.reshape(3, cam.height, cam.width), self._rnorm,
                                  windows=self._windows(T))
        t, surf = t.reshape(-1), surf.reshape(-1).astype(np.intp)
        hit = surf >= 0
        all_hit = bool(hit.all())  # always, in a closed room: skip the masking copies
        inten = np.zeros(t.shape, f32)
        if hit.any():
            th, sh = (t, surf) if all_hit else (t[hit], surf[hit])
            dh = dirs if all_hit else dirs[:, hit]
            rn, ps = (self._rnorm, self._pix_size) if all_hit else (self._rnorm[hit], self._pix_size[hit])
            points = dh * th
            points += o.astype(f32)[:, None]
            tb = self.scene._tables
            nx, ny, nz = tb["nx"][sh], tb["ny"][sh], tb["nz"][sh]
            cos = np.abs(dh[0] * nx + dh[1] * ny + dh[2] * nz) / rn
            # Footprint on the surface: depth x angular pixel size, stretched by the incidence.
            fp = th * ps / np.maximum(cos, f32(0.25))
            shaded = self.scene.shade(points, sh, fp, (nx, ny, nz))
            if all_hit:
                inten = shaded
            else:
                inten[hit] = shaded
        img = (inten * f32(255.0)).reshape(cam.height, cam.width)
        if self.psf_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.psf_sigma)
        if noise_sigma > 0:
            rng = np.random.default_rng(noise_seed)
            img = img + rng.standard_normal(img.shape, dtype=np.float32) * f32(noise_sigma)
        image = np.clip(img + f32(0.5), 0, 255).astype(np.uint8)
        depth = (t if all_hit else np.where(hit, t, np.inf)).astype(f32, copy=False)
        depth = depth.reshape(cam.height, cam.width)
        return Rendered(image, depth)


def _pixel_jacobian_area(camera: PinholeRadtan, grid: np.ndarray) -> np.ndarray:
    """Area in normalised coordinates covered by each pixel (|det d xn / d uv|). Shape: (N,)."""
    eps = 1e-4
    du, dv = np.array([eps, 0.0]), np.array([0.0, eps])
    dxu = (camera.distort(grid + du) - camera.distort(grid - du)) / (2 * eps)
    dxv = (camera.distort(grid + dv) - camera.distort(grid - dv)) / (2 * eps)
    det = np.abs(dxu[:, 0] * dxv[:, 1] - dxu[:, 1] * dxv[:, 0]) * camera.fx * camera.fy
    return 1.0 / det


def ray_depth(scene: Scene, camera: PinholeRadtan, T_wc: Any, pixels: Any) -> np.ndarray:
    """Exact z-depth (m) at sub-pixel positions of a camera at ``T_wc``, inf where nothing is hit.

    A fresh ray cast per pixel: no interpolation across edges.

    Shape:
        pixels: (N, 2) (u, v) -> (N,) float64.
    """
    T = np.asarray(T_wc, dtype=np.float64)
    xn = camera.pixels_to_normalized(pixels)
    rays = np.vstack([xn.T, np.ones((1, xn.shape[0]))])
    t, surf = scene.cast(T[:3, 3], T[:3, :3] @ rays)
    return np.where(surf >= 0, t, np.inf)


def flow_between(scene: Scene, cam_i: PinholeRadtan, T_w_ci: Any, cam_j: PinholeRadtan, T_w_cj: Any,
                 pixels: Any, *, occlusion_tol: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Exact optical flow of pixels from view i to view j, with a visibility flag.

    Args:
        cam_i, cam_j: cameras of the two views (the same one for temporal flow, cam0/cam1 for stereo).
        T_w_ci, T_w_cj: 4x4 camera-to-world poses of the views.
        pixels: (N, 2) pixel coordinates (u, v) in view i.
        occlusion_tol: relative depth tolerance of the occlusion test.

    Returns:
        ``(flow, visible)``: (N, 2) float64 flow, NaN where the point cannot be projected, and (N,) bool,
        true where the point is inside both images and not hidden behind another surface in view j.

    Raises:
        DataError: when ``pixels`` is not (N, 2) or a pose is not 4x4.
    """
    uv = as_points(pixels, 2, "pixels")
    Ti, Tj = np.asarray(T_w_ci, dtype=np.float64), np.asarray(T_w_cj, dtype=np.float64)
    if Ti.shape != (4, 4) or Tj.shape != (4, 4):
        raise DataError(f"poses: expected shape (4, 4), got {Ti.shape} and {Tj.shape}")
    xn = cam_i.pixels_to_normalized(uv)
    rays_i = np.vstack([xn.T, np.ones((1, xn.shape[0]))])
    dirs_i = Ti[:3, :3] @ rays_i
    t, surf = scene.cast(Ti[:3, 3], dirs_i)
    ok = (surf >= 0) & cam_i.in_image(uv)
    Xw = Ti[:3, 3:4] + dirs_i * np.where(ok, t, 1.0)
    Xj = (Tj[:3, :3].T @ (Xw - Tj[:3, 3:4])).T
    uv_j, valid = cam_j.project(Xj)
    visible = ok & valid & cam_j.in_image(uv_j)
    if visible.any():
        # Occlusion: cast the ray of view j towards the point; something nearer hides it.
        z = Xj[visible, 2]
        rays_j = np.vstack([(Xj[visible, :2] / z[:, None]).T, np.ones((1, z.size))])
        tj, sj = scene.cast(Tj[:3, 3], Tj[:3, :3] @ rays_j)
        visible[np.flatnonzero(visible)] = (sj >= 0) & (tj >= z * (1.0 - occlusion_tol) - 1e-6)
    flow = uv_j - uv
    flow[~(ok & valid)] = np.nan
    return flow, visible
