"""A plane from one zone frame (DELTAR Eq. 1), in the sensor frame.

Each zone reports the depth of the surface it sees but not where inside the zone that
depth was measured. Following the paper, every zone k gets an unknown point inside its
angular cell whose depth equals the zone mean m_k; the plane and the points are solved
together, EM-like: start at the zone centres, fit a plane robustly (E-step), move each
point inside its cell to the position closest to the plane (M-step), drop zones that
cannot reach the plane, repeat until the plane stops changing.

Depth convention: the zone mean is the **z-depth along the sensor axis** (as
``deltar.sensor.geometry.zone_rects`` and the simulator, which averages pixel z-depths,
use it), so a zone point is ``m_k * (tan ax, tan ay, 1)`` with the angles ``ax, ay``
inside the zone's bounds from ``zone_angles_deg``. Working in ``tan`` space makes each
cell an axis-aligned box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from deltar.sensor.geometry import DEFAULT_FOV_DEG, zone_angles_deg
from deltar.sensor.zone_frame import ZoneFrame

#: Fewest valid zones that can define a plane reliably.
MIN_PLANE_ZONES = 6


@dataclass(frozen=True)
class ZonePlaneFit:
    """Result of ``fit_plane_to_zones``.

    The plane is ``normal . p + offset_m = 0`` for sensor-frame points ``p`` (metres); the
    normal is a unit vector oriented towards the sensor, so ``offset_m`` > 0 is the
    distance from the sensor to the plane.

    Attributes:
        normal: (3,) unit normal in the sensor frame.
        offset_m: plane offset d in metres.
        points_m: (Z, 3) each zone's point inside its cell (sensor frame, metres);
            zeros for invalid zones.
        inliers: (Z,) bool, zones used for the final plane.
        rms_residual_m: RMS point-to-plane distance of the inlier points, metres.
        iterations: EM iterations run.
    """

    normal: np.ndarray
    offset_m: float
    points_m: np.ndarray
    inliers: np.ndarray
    rms_residual_m: float
    iterations: int


def zone_cells_tan(grid: int, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG) -> np.ndarray:
    """Each zone's cell as a box in ``(tan ay, tan ax)`` space.

    Args:
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.

    Returns:
        (grid * grid, 4) float64 ``(v0, u0, v1, u1)`` with ``u = tan(ax)``, ``v = tan(ay)``;
        a point at z-depth ``m`` in the cell is ``m * (u, v, 1)``.
    """
    return np.tan(np.deg2rad(zone_angles_deg(grid, fov_deg)))


def zone_centre_points(mean_m: np.ndarray, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                       ) -> np.ndarray:
    """Sensor-frame point of each zone at its cell centre (the naive measurement).

    Args:
        mean_m: (Z,) zone means in metres (z-depth), Z = 16 or 64.
        fov_deg: (horizontal, vertical) sensor field of view in degrees.

    Returns:
        (Z, 3) float64 points in metres.
    """
    mean = np.asarray(mean_m, dtype=np.float64).reshape(-1)
    grid = math.isqrt(mean.size)
    if grid * grid != mean.size or grid not in (4, 8):
        raise ValueError(f"mean_m must hold 16 or 64 zones, got {mean.size}")
    cells = zone_cells_tan(grid, fov_deg)
    u = 0.5 * (cells[:, 1] + cells[:, 3])
    v = 0.5 * (cells[:, 0] + cells[:, 2])
    return np.stack([u, v, np.ones_like(u)], axis=1) * mean[:, None]


def fit_plane_svd(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through (N, 3) points (N >= 3): unit normal (3,) and offset d.

    The normal is oriented towards the origin (so ``d >= 0``).
    """
    pts = np.asarray(points, dtype=np.float64)
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    normal = vt[-1]
    offset = -float(normal @ centroid)
    if offset < 0:
        normal, offset = -normal, -offset
    return normal, offset


def ransac_plane(points: np.ndarray, threshold_m: float, *, iterations: int = 256,
                 normal_hint: np.ndarray | None = None, max_angle_deg: float = 90.0,
                 offset_hint_m: float | None = None, max_offset_diff_m: float = 0.15,
                 seed: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane of a point set by RANSAC, refined by least squares on its inliers.

    Args:
        points: (N, 3) points in metres, N >= 3.
        threshold_m: inlier distance in metres.
        iterations: random 3-point hypotheses (all drawn at once, vectorised).
        normal_hint: optional (3,) direction; hypotheses whose normal is more than
            ``max_angle_deg`` away from it (either sign) are rejected.
        max_angle_deg: see ``normal_hint``.
        offset_hint_m: optional expected offset d of the plane ``normal_hint . p + d = 0``
            (needs ``normal_hint``); hypotheses farther than ``max_offset_diff_m`` from it
            are rejected, which tells apart parallel surfaces (a cabinet and the wall).
        max_offset_diff_m: see ``offset_hint_m``.
        seed: random seed (results are deterministic).

    Returns:
        normal (3,), offset d (plane ``n . p + d = 0``, normal towards the origin) and
        (N,) bool inlier mask.

    Raises:
        ValueError: fewer than 3 points or no acceptable plane.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 3:
        raise ValueError(f"points must be (N, 3) with N >= 3, got {pts.shape}")
    rng = np.random.default_rng(seed)
    idx = np.stack([rng.choice(pts.shape[0], 3, replace=False) for _ in range(iterations)])
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12
    normals[ok] /= norms[ok, None]
    if normal_hint is not None:
        hint = np.asarray(normal_hint, dtype=np.float64)
        hint = hint / np.linalg.norm(hint)
        # Orient every hypothesis like the hint so that offsets are comparable.
        normals *= np.where(normals @ hint < 0, -1.0, 1.0)[:, None]
        ok &= normals @ hint >= np.cos(np.deg2rad(max_angle_deg))
    offsets = -np.einsum("ij,ij->i", normals, a)
    if offset_hint_m is not None:
        if normal_hint is None:
            raise ValueError("offset_hint_m needs normal_hint")
        ok &= np.abs(offsets - offset_hint_m) <= max_offset_diff_m
    if not np.any(ok):
        raise ValueError("no plane hypothesis fits the points (degenerate or hint mismatch)")
    # Score all hypotheses against all points in one matrix product.
    dist = np.abs(pts @ normals[ok].T + offsets[ok])
    counts = (dist < threshold_m).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = dist[:, best] < threshold_m
    normal, offset = fit_plane_svd(pts[inliers])
    inliers = np.abs(pts @ normal + offset) < threshold_m
    if inliers.sum() >= 3:
        normal, offset = fit_plane_svd(pts[inliers])
    return normal, offset, inliers


def _closest_in_cell(cells: np.ndarray, mean: np.ndarray, normal: np.ndarray,
                     offset: float) -> np.ndarray:
    """M-step: per zone, the (u, v) in its cell whose point at depth ``mean`` is closest
    to the plane; among points on the plane, the one nearest the cell centre.

    The signed distance ``mean * (nx u + ny v + nz) + d`` is linear in (u, v), so this is
    a point on a line clipped to a box, or the box corner minimising |distance|.
    """
    v0, u0, v1, u1 = cells.T
    uc, vc = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
    a, b = mean * normal[0], mean * normal[1]
    c = mean * normal[2] + offset
    f_centre = a * uc + b * vc + c
    g = a * a + b * b
    safe_g = np.where(g > 1e-18, g, 1.0)
    # Projection of the centre onto the zero line, then the line's feasible segment.
    qu, qv = uc - f_centre * a / safe_g, vc - f_centre * b / safe_g
    root = np.sqrt(safe_g)
    eu, ev = -b / root, a / root
    lo, hi = np.full_like(uc, -np.inf), np.full_like(uc, np.inf)
    for q, e, low, high in ((qu, eu, u0, u1), (qv, ev, v0, v1)):
        moving = np.abs(e) > 1e-12
        e_safe = np.where(moving, e, 1.0)
        s1, s2 = (low - q) / e_safe, (high - q) / e_safe
        lo = np.where(moving, np.maximum(lo, np.minimum(s1, s2)), lo)
        hi = np.where(moving, np.minimum(hi, np.maximum(s1, s2)), hi)
        inside = (q >= low) & (q <= high)
        lo = np.where(~moving & ~inside, np.inf, lo)
    reachable = (lo <= hi) & (g > 1e-18)
    s = np.clip(0.0, lo, hi)
    u_line, v_line = qu + s * eu, qv + s * ev
    # Unreachable: the sign of the distance is the same over the whole cell; move each
    # coordinate to the side that lowers |distance| (stay central where it has no effect).
    sign = np.sign(f_centre)
    u_edge = np.where(sign * a > 0, u0, np.where(sign * a < 0, u1, uc))
    v_edge = np.where(sign * b > 0, v0, np.where(sign * b < 0, v1, vc))
    u = np.where(reachable, u_line, u_edge)
    v = np.where(reachable, v_line, v_edge)
    return np.stack([u, v], axis=1)


def fit_plane_to_zones(
    mean_m: np.ndarray | ZoneFrame,
    valid: np.ndarray | None = None,
    *,
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
    inlier_threshold_m: float = 0.05,
    max_iterations: int = 50,
    tolerance: float = 1e-7,
    min_zones: int = MIN_PLANE_ZONES,
    seed: int = 0,
) -> ZonePlaneFit:
    """Fit a plane to one zone frame of a sensor facing a plane (EM, DELTAR Eq. 1).

    Args:
        mean_m: (Z,) or (n, n) zone means in metres (z-depth along the sensor axis), or a
            ``ZoneFrame`` (then ``valid`` comes from the frame).
        valid: (Z,) or (n, n) bool valid zones (required unless a ZoneFrame is given).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.
        inlier_threshold_m: zones whose cell cannot come closer than this to the plane
            are dropped (metres).
        max_iterations: EM iterations at most.
        tolerance: stop when the plane (normal and offset in metres) changes less.
        min_zones: fewest inlier zones accepted.
        seed: seed of the initial RANSAC over zone centres.

    Returns:
        ``ZonePlaneFit`` in the sensor frame.

    Raises:
        ValueError: wrong shapes, NaN in valid zones, too few valid or inlier zones, or
            inlier zones on one line; the message says what to record instead.
    """
    if isinstance(mean_m, ZoneFrame):
        mean, _, valid_flat = mean_m.flat()
        mean = mean.astype(np.float64)
    else:
        if valid is None:
            raise ValueError("valid is required when mean_m is an array")
        mean = np.asarray(mean_m, dtype=np.float64).reshape(-1)
        valid_flat = np.asarray(valid, dtype=bool).reshape(-1)
        if valid_flat.shape != mean.shape:
            raise ValueError(f"valid has {valid_flat.size} zones, mean_m has {mean.size}")
    grid = math.isqrt(mean.size)
    if grid * grid != mean.size or grid not in (4, 8):
        raise ValueError(f"mean_m must hold 16 or 64 zones, got {mean.size}")
    if not np.all(np.isfinite(mean[valid_flat])) or np.any(mean[valid_flat] <= 0):
        raise ValueError("mean_m must be finite and > 0 in valid zones")
    count = int(valid_flat.sum())
    if count < min_zones:
        raise ValueError(f"only {count} valid zones (need at least {min_zones}): point the "
                         "sensor at a plane that fills its field of view, 0.3-3 m away")
    cells = zone_cells_tan(grid, fov_deg)
    _check_enough(valid_flat, cells, min_zones)
    points = zone_centre_points(mean, fov_deg)
    idx = np.flatnonzero(valid_flat)
    # A robust start: the dominant plane among the zone centres.
    normal, offset, centre_inliers = ransac_plane(points[idx], inlier_threshold_m, seed=seed)
    inliers = np.zeros(mean.size, dtype=bool)
    inliers[idx[centre_inliers]] = True
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        _check_enough(inliers, cells, min_zones)
        normal_new, offset_new = fit_plane_svd(points[inliers])  # E-step
        uv = _closest_in_cell(cells[idx], mean[idx], normal_new, offset_new)  # M-step
        points[idx] = np.column_stack([uv, np.ones(idx.size)]) * mean[idx, None]
        distance = np.abs(points[idx] @ normal_new + offset_new)
        inliers = np.zeros(mean.size, dtype=bool)
        inliers[idx[distance < inlier_threshold_m]] = True
        change = np.linalg.norm(normal_new - normal) + abs(offset_new - offset)
        normal, offset = normal_new, offset_new
        if change < tolerance:
            break
    _check_enough(inliers, cells, min_zones)
    residual = points[inliers] @ normal + offset
    points[~valid_flat] = 0.0
    return ZonePlaneFit(normal=normal, offset_m=float(offset), points_m=points,
                        inliers=inliers, rms_residual_m=float(np.sqrt(np.mean(residual ** 2))),
                        iterations=iterations)


def _check_enough(inliers: np.ndarray, cells: np.ndarray, min_zones: int) -> None:
    count = int(inliers.sum())
    if count < min_zones:
        raise ValueError(f"only {count} zones agree on one plane (need at least {min_zones}): "
                         "record frames where one flat surface fills most of the sensor's view")
    centres = np.column_stack([cells[inliers, 1] + cells[inliers, 3],
                               cells[inliers, 0] + cells[inliers, 2]]) / 2
    spread = np.linalg.svd(centres - centres.mean(0), compute_uv=False)
    if spread[1] < 1e-6:
        raise ValueError("the zones that agree on a plane lie on one line: record frames "
                         "where the plane covers several rows and columns of zones")
