"""Procedural indoor scenes: a small CPU ray caster for RGB-D frames with exact depth.

A scene is a room (floor, ceiling, four walls) with furniture-like boxes, spheres and
upright cylinders, each with a procedural solid texture (checker, wood-like stripes, value
noise or plain) and Lambert + ambient shading from one point light, with hard shadows cast
by the objects. Everything is drawn from one seed, so a seed always gives the same frame.

World frame: x right, y up, z forward (metres); the room spans
``[-W/2, W/2] x [0, H] x [0, D]``. Rays are cast through every pixel with unnormalised
camera-frame directions ``((u - cx) / fx, (v - cy) / fy, 1)``, so the hit distance along
a ray is directly the z-depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.camera import CameraIntrinsics
from deltar.data.rgbd import RGBDFrame
from deltar.data.sequence import checked_index

#: Focal length as a fraction of the image width (NYU's Kinect: 518.9 px at 640 px).
FOCAL_PER_WIDTH = 0.81
TEXTURES: tuple[str, ...] = ("checker", "wood", "noise", "plain")
_AMBIENT = 0.3
#: Fraction of direct light left in shadows (stands in for indirect light).
_SHADOW = 0.25


@dataclass(frozen=True)
class _Primitive:
    """One scene object. ``kind``: room, box, sphere or cylinder.

    ``lo`` / ``hi`` are the (3,) corners of boxes and the room; a sphere has ``center`` and
    ``radius``; a cylinder stands on ``center`` (its base centre) with ``radius`` and
    ``height``.
    """

    kind: str
    color: np.ndarray
    texture: str
    texture_scale: float
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    center: np.ndarray | None = None
    radius: float = 0.0
    height: float = 0.0
    floor: _Primitive | None = None  # the room's floor material (colour, texture)


# ---------------------------------------------------------------------- intersections
# Ray directions come as (3, N) arrays (one row per axis): element-wise work on whole rows
# is much faster in numpy than reductions over a short trailing axis. Origins are (3,) for
# camera rays or (3, N) for shadow rays. Each function returns (N,) hit distances in units
# of the direction's length, inf where the ray misses.
def _hit_room(p: _Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance to the inside of an axis-aligned box seen from within it."""
    o = o.reshape(3, -1)
    t = np.full(d.shape[1], np.inf, dtype=d.dtype)
    for axis in range(3):
        da = d[axis]
        bound = np.where(da > 0, p.hi[axis], p.lo[axis]).astype(d.dtype)
        # A zero direction component never reaches that pair of walls.
        ta = np.where(da != 0, (bound - o[axis]) / da, np.inf)
        np.minimum(t, ta, out=t)
    return t


def _hit_box(p: _Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Slab test against an axis-aligned box seen from outside; inf where missed."""
    o = o.reshape(3, -1)
    t_near = np.full(d.shape[1], -np.inf, dtype=d.dtype)
    t_far = np.full(d.shape[1], np.inf, dtype=d.dtype)
    for axis in range(3):
        inv = 1.0 / d[axis]
        t1, t2 = (p.lo[axis] - o[axis]) * inv, (p.hi[axis] - o[axis]) * inv
        np.maximum(t_near, np.minimum(t1, t2), out=t_near)
        np.minimum(t_far, np.maximum(t1, t2), out=t_far)
    return np.where((t_far >= t_near) & (t_near > 0), t_near, np.inf)


def _hit_sphere(p: _Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    oc = o.reshape(3, -1) - p.center[:, None]
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = d[0] * oc[0] + d[1] * oc[1] + d[2] * oc[2]
    c = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - p.radius**2
    disc = b * b - a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _hit_cylinder(p: _Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Upright cylinder with a top cap (the bottom stands on something)."""
    o = o.reshape(3, -1)
    ox, oz = o[0] - p.center[0], o[2] - p.center[2]
    dx, dy, dz = d[0], d[1], d[2]
    a = dx * dx + dz * dz
    b = dx * ox + dz * oz
    c = ox * ox + oz * oz - p.radius**2
    disc = b * b - a * c
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    y_side = o[1] + t_side * dy
    y0, y1 = p.center[1], p.center[1] + p.height
    side_ok = (disc >= 0) & (t_side > 0) & (y_side >= y0) & (y_side <= y1)
    t_cap = (y1 - o[1]) / dy
    cx, cz = ox + t_cap * dx, oz + t_cap * dz
    cap_ok = (t_cap > 0) & (cx * cx + cz * cz <= p.radius**2)
    return np.minimum(np.where(side_ok, t_side, np.inf), np.where(cap_ok, t_cap, np.inf))


_HIT = {"room": _hit_room, "box": _hit_box, "sphere": _hit_sphere, "cylinder": _hit_cylinder}


def _box_normal(p: _Primitive, points: np.ndarray, inside: bool) -> np.ndarray:
    """Normal of the box face nearest to each point (into the room when ``inside``)."""
    dist = np.concatenate([np.abs(points - p.lo), np.abs(points - p.hi)], axis=1)  # (N, 6)
    face = np.argmin(dist, axis=1)
    axis = face % 3
    sign = np.where(face < 3, -1.0, 1.0) * (-1.0 if inside else 1.0)
    normal = np.zeros_like(points)
    normal[np.arange(points.shape[0]), axis] = sign
    return normal


def _normals(p: _Primitive, points: np.ndarray) -> np.ndarray:
    if p.kind in ("room", "box"):
        return _box_normal(p, points, inside=p.kind == "room")
    if p.kind == "sphere":
        return (points - p.center) / p.radius
    normal = points - p.center
    normal[:, 1] = 0.0
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    on_cap = np.abs(points[:, 1] - (p.center[1] + p.height)) < 1e-4
    normal[on_cap] = (0.0, 1.0, 0.0)
    return normal


# ---------------------------------------------------------------------- textures
class _ValueNoise:
    """3-D value noise on an integer lattice (smooth, deterministic per seed)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.perm = rng.permutation(256)
        self.values = rng.random(256)

    def _lattice(self, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        h = self.perm[(self.perm[(self.perm[i & 255] + j) & 255] + k) & 255]
        return self.values[h]

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points -> (N,) values in [0, 1]."""
        base = np.floor(points)
        f = points - base
        f = f * f * (3.0 - 2.0 * f)  # smoothstep: no visible lattice creases
        i, j, k = (base[:, a].astype(np.int64) for a in range(3))
        out = np.zeros(points.shape[0])
        for di in (0, 1):
            wx = f[:, 0] if di else 1.0 - f[:, 0]
            for dj in (0, 1):
                wy = f[:, 1] if dj else 1.0 - f[:, 1]
                for dk in (0, 1):
                    wz = f[:, 2] if dk else 1.0 - f[:, 2]
                    out += wx * wy * wz * self._lattice(i + di, j + dj, k + dk)
        return out


def _texture(p: _Primitive, points: np.ndarray, noise: _ValueNoise) -> np.ndarray:
    """(N,) brightness factor of the primitive's solid texture at world ``points``."""
    scaled = points / p.texture_scale
    if p.texture == "checker":
        parity = np.floor(scaled + 1e-4).astype(np.int64).sum(axis=1) % 2
        return np.where(parity == 0, 1.0, 0.65)
    if p.texture == "wood":
        warp = 0.6 * noise(points * 2.0)
        return 0.8 + 0.2 * np.sin(2.0 * np.pi * (scaled[:, 0] + scaled[:, 2] + warp))
    if p.texture == "noise":
        return 0.6 + 0.25 * noise(scaled) + 0.15 * noise(scaled * 4.0)
    return np.ones(points.shape[0])


# ---------------------------------------------------------------------- scene sampling
def _random_color(rng: np.random.Generator) -> np.ndarray:
    # Muted interior colours: mix a random hue with grey.
    return 0.45 * rng.random(3) + 0.35 * rng.random() + 0.15


def _textured(rng: np.random.Generator, kind: str, **shape) -> _Primitive:
    return _Primitive(kind=kind, color=_random_color(rng), texture=str(rng.choice(TEXTURES)),
                      texture_scale=float(rng.uniform(0.1, 0.5)), **shape)


def _far_enough(lo: np.ndarray, hi: np.ndarray, cam: np.ndarray, clearance: float) -> bool:
    nearest = np.clip(cam, lo, hi)
    return float(np.linalg.norm(nearest - cam)) > clearance


def _sample_scene(rng: np.random.Generator) -> tuple[list[_Primitive], np.ndarray,
                                                     np.ndarray, np.ndarray]:
    """Room, objects, camera position (3,), camera rotation (3, 3) and light (3,)."""
    size = np.array([rng.uniform(3.0, 5.5), rng.uniform(2.4, 3.0), rng.uniform(3.0, 6.0)])
    lo, hi = np.array([-size[0] / 2, 0.0, 0.0]), np.array([size[0] / 2, size[1], size[2]])
    floor = _textured(rng, "room")
    room = _Primitive("room", _random_color(rng) * 0.3 + 0.6, str(rng.choice(TEXTURES)),
                      float(rng.uniform(0.2, 0.6)), lo=lo, hi=hi, floor=floor)
    cam = np.array([rng.uniform(lo[0] + 0.9, hi[0] - 0.9), rng.uniform(1.0, 1.7),
                    rng.uniform(0.3, 1.0)])
    yaw, pitch, roll = np.deg2rad([rng.uniform(-25, 25), rng.uniform(-25, 0),
                                   rng.uniform(-3, 3)])
    prims = [room]
    for _ in range(int(rng.integers(2, 6))):  # furniture-like boxes on the floor
        extent = np.array([rng.uniform(0.4, 1.6), rng.uniform(0.3, 1.4), rng.uniform(0.4, 1.0)])
        corner = np.array([rng.uniform(lo[0], hi[0] - extent[0]), 0.0,
                           rng.uniform(cam[2] + 0.8, max(cam[2] + 0.9, hi[2] - extent[2]))])
        if _far_enough(corner, corner + extent, cam, 0.8):
            prims.append(_textured(rng, "box", lo=corner, hi=np.minimum(corner + extent, hi)))
    boxes = [p for p in prims if p.kind == "box"]
    for _ in range(int(rng.integers(0, 3))):  # spheres, resting on a box top or the floor
        radius = float(rng.uniform(0.12, 0.35))
        if boxes and rng.random() < 0.6:
            box = boxes[int(rng.integers(len(boxes)))]
            top = (box.lo + box.hi) / 2
            center = np.array([top[0], box.hi[1] + radius, top[2]])
        else:
            center = np.array([rng.uniform(lo[0] + radius, hi[0] - radius), radius,
                               rng.uniform(cam[2] + 1.0, hi[2] - radius)])
        if float(np.linalg.norm(center - cam)) > radius + 0.8:
            prims.append(_textured(rng, "sphere", center=center, radius=radius))
    for _ in range(int(rng.integers(0, 3))):  # upright cylinders: bins, pots, lamps
        radius = float(rng.uniform(0.08, 0.3))
        base = np.array([rng.uniform(lo[0] + radius, hi[0] - radius), 0.0,
                         rng.uniform(cam[2] + 1.0, hi[2] - radius)])
        height = float(rng.uniform(0.4, min(2.0, size[1] - 0.2)))
        if np.hypot(*(base - cam)[[0, 2]]) > radius + 0.8:
            prims.append(_textured(rng, "cylinder", center=base, radius=radius, height=height))
    light = np.array([rng.uniform(lo[0] + 0.5, hi[0] - 0.5), hi[1] - 0.2,
                      rng.uniform(lo[2] + 0.5, hi[2] - 0.5)])
    return prims, cam, _camera_rotation(yaw, pitch, roll), light


def _camera_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-from-camera rotation; camera frame x right, y down, z forward."""
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    forward = np.array([sy * cp, sp, cy * cp])  # pitch > 0 looks up
    right = np.array([cy, 0.0, -sy])
    up = np.cross(forward, right)
    # Roll turns the right/up pair about the viewing direction.
    right, up = cr * right + sr * up, cr * up - sr * right
    return np.stack([right, -up, forward], axis=1)


# ---------------------------------------------------------------------- rendering
def _in_shadow(prims: list[_Primitive], points: np.ndarray, normals: np.ndarray,
               light: np.ndarray) -> np.ndarray:
    """(N,) bool: an object lies between each lit point and the light."""
    lit = np.flatnonzero(np.einsum("ij,ij->i", normals, light - points) > 0)
    # Start a little off the surface so a point does not shadow itself.
    origins = (points[lit] + 1e-3 * normals[lit]).T.astype(np.float32)
    to_light = (light[:, None] - origins).astype(np.float32)  # t in (0, 1): before the light
    blocked = np.zeros(lit.size, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for prim in prims:
            if prim.kind != "room":  # the light hangs inside the room
                blocked |= _HIT[prim.kind](prim, origins, to_light) < 1.0
    out = np.zeros(points.shape[0], dtype=bool)
    out[lit[blocked]] = True
    return out


def scene_intrinsics(height: int, width: int) -> CameraIntrinsics:
    """Intrinsics used for procedural frames: square pixels, centred principal point."""
    focal = FOCAL_PER_WIDTH * width
    return CameraIntrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)


def render_scene(seed: int, height: int = 480, width: int = 640) -> RGBDFrame:
    """Render one random room from ``seed``.

    Args:
        seed: any integer; the same seed always gives the same frame.
        height, width: image size in pixels (at least 8 each).

    Returns:
        An :class:`RGBDFrame`: image (height, width, 3) uint8 RGB, depth_m
        (height, width) float32 exact z-depth in metres (every pixel valid), intrinsics
        from :func:`scene_intrinsics`, name ``"procedural-<seed>"``.
    """
    if int(height) < 8 or int(width) < 8:
        raise ValueError(f"height and width must be at least 8 pixels, got {height}x{width}")
    rng = np.random.default_rng(int(seed))
    prims, cam, rotation, light = _sample_scene(rng)
    noise = _ValueNoise(rng)
    intr = scene_intrinsics(int(height), int(width))
    x = ((np.arange(width) - intr.cx) / intr.fx).astype(np.float32)
    y = ((np.arange(height) - intr.cy) / intr.fy).astype(np.float32)
    rot = rotation.astype(np.float32)
    # (3, N) world directions of all pixels, row-major, with unit camera-z component.
    rays = (rot[:, 0, None, None] * x[None, None, :] + rot[:, 1, None, None] * y[None, :, None]
            + rot[:, 2, None, None]).reshape(3, -1)
    origin = cam.astype(np.float32)

    with np.errstate(divide="ignore", invalid="ignore"):
        hits = np.stack([_HIT[p.kind](p, origin, rays) for p in prims])  # (P, N)
    winner = np.argmin(hits, axis=0)
    depth = np.take_along_axis(hits, winner[None], axis=0)[0]
    points = (cam[:, None] + depth * rays).T.astype(np.float64)  # (N, 3) hit points

    normals = np.zeros_like(points)
    for k, prim in enumerate(prims):
        sel = winner == k
        normals[sel] = _normals(prim, points[sel])
    to_light = light - points
    dist = np.linalg.norm(to_light, axis=1)
    lambert = np.clip(np.einsum("ij,ij->i", normals, to_light) / dist, 0.0, None)
    lambert[_in_shadow(prims, points, normals, light)] *= _SHADOW
    shade = _AMBIENT + (1.0 - _AMBIENT) * lambert * 6.0 / (4.0 + dist**2)

    color = np.zeros((rays.shape[1], 3))
    for k, prim in enumerate(prims):
        sel = np.flatnonzero(winner == k)
        if sel.size == 0:
            continue
        material = np.full(sel.size, -1)
        if prim.floor is not None:
            material[normals[sel, 1] > 0.5] = 0
        for mat, part in ((prim, material < 0), (prim.floor, material == 0)):
            if mat is not None and part.any():
                idx = sel[part]
                color[idx] = mat.color * (_texture(mat, points[idx], noise) * shade[idx])[:, None]
    image = (np.clip(color, 0.0, 1.0) ** (1 / 2.2) * 255.0 + 0.5).astype(np.uint8)
    return RGBDFrame(image=image.reshape(height, width, 3),
                     depth_m=depth.reshape(height, width).astype(np.float32),
                     intrinsics=intr, name=f"procedural-{int(seed)}")


class ProceduralReader(Sequence):
    """A sequence of procedural frames: frame ``i`` is ``render_scene(seed + i)``.

    Args:
        num_frames: number of frames.
        seed: seed of frame 0.
        height, width: image size in pixels.
    """

    def __init__(self, num_frames: int, seed: int = 0, height: int = 480,
                 width: int = 640) -> None:
        if int(num_frames) < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        if not (8 <= int(height) <= 4096 and 8 <= int(width) <= 4096):
            raise ValueError(f"procedural scenes are 8 to 4096 pixels a side, got "
                             f"{height}x{width}")
        self.num_frames, self.seed = int(num_frames), int(seed)
        self.height, self.width = int(height), int(width)
        self.intrinsics = scene_intrinsics(self.height, self.width)

    def __len__(self) -> int:
        return self.num_frames

    def __getitem__(self, index: int) -> RGBDFrame:  # type: ignore[override]
        index = checked_index(index, len(self))
        return render_scene(self.seed + index % len(self), self.height, self.width)
