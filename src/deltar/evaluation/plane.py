"""Flat-wall metrics: robust plane fit, bias and jitter of a depth map against the plane.

The paper compares against a RealSense on a flat wall at 1-3 m: a plane is fitted to
the wall, ``bias`` is the mean absolute error of the depth map to that plane and
``jitter`` the standard deviation of the error. Here the error of a pixel is its depth
minus the depth of the plane along the pixel's ray (metres), so it is directly the
depth error a user sees.

The plane is fitted robustly: RANSAC (vectorised over hypotheses) for a start, then
iteratively reweighted least squares with Tukey's biweight, so outliers (a poster, a
door frame, flying pixels) neither tilt the plane nor count in the metrics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltar import camera
from deltar.camera import CameraIntrinsics, backproject

__all__ = ["Plane", "PlaneMetrics", "fit_plane", "pixel_rays", "plane_metrics"]

#: Tukey biweight tuning constant (95 % efficiency for Gaussian noise).
_TUKEY_C = 4.685
#: Converts a median absolute deviation to a Gaussian standard deviation.
_MAD_TO_STD = 1.4826


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . p + offset = 0`` in camera coordinates.

    Attributes:
        normal: (3,) unit normal, oriented towards the camera (``offset > 0`` for a plane
            in front of it).
        offset: distance of the plane from the camera centre in metres.
    """

    normal: np.ndarray
    offset: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed point-to-plane distances (metres) of (N, 3) points, shape (N,)."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    def depth_along_rays(self, rays: np.ndarray) -> np.ndarray:
        """Depth z where each ray ``(x/z, y/z, 1)`` meets the plane, shape (N,).

        Args:
            rays: (N, 3) rays with z component 1 (from ``K^-1 (u, v, 1)``).

        Returns:
            (N,) depth in metres; ``inf`` for rays parallel to the plane.
        """
        denominator = np.asarray(rays, dtype=np.float64) @ self.normal
        with np.errstate(divide="ignore"):
            return np.where(np.abs(denominator) > 1e-12, -self.offset / denominator, np.inf)


@dataclass(frozen=True)
class PlaneMetrics:
    """Depth error of a depth map against a plane.

    Attributes:
        bias_m: mean absolute error to the plane over inliers (metres).
        jitter_m: standard deviation of the signed error over inliers (metres).
        mean_error_m: mean signed error over inliers (metres; > 0 = behind the plane).
        inlier_fraction: fraction of the evaluated pixels kept as inliers.
        num_points: number of evaluated pixels (valid depth inside the mask).
        plane: the reference plane.
    """

    bias_m: float
    jitter_m: float
    mean_error_m: float
    inlier_fraction: float
    num_points: int
    plane: Plane

    def to_dict(self) -> dict:
        """JSON-friendly dict (plane as normal list and offset)."""
        return {"bias_m": self.bias_m, "jitter_m": self.jitter_m,
                "mean_error_m": self.mean_error_m, "inlier_fraction": self.inlier_fraction,
                "num_points": self.num_points, "plane_normal": self.plane.normal.tolist(),
                "plane_offset_m": self.plane.offset}


def pixel_rays(height: int, width: int, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Rays ``K^-1 (u, v, 1)`` of every pixel, shape (H, W, 3), z component 1.

    :func:`deltar.camera.pixel_rays` with the grid size first.
    """
    return camera.pixel_rays(intrinsics, height, width)


def _fit_plane_lsq(points: np.ndarray, weights: np.ndarray) -> Plane:
    """Weighted total-least-squares plane (smallest principal axis of the weighted cloud)."""
    weights = weights / weights.sum()
    centroid = weights @ points
    centred = (points - centroid) * np.sqrt(weights)[:, None]
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    return _oriented(normal, -float(normal @ centroid))


def _oriented(normal: np.ndarray, offset: float) -> Plane:
    # Orient the normal so the camera centre (origin) lies on the positive side.
    if offset < 0:
        normal, offset = -normal, -offset
    return Plane(normal, float(offset))


def _ransac(points: np.ndarray, threshold_m: float, iterations: int,
            rng: np.random.Generator) -> Plane:
    """Plane with the most points within ``threshold_m``, from random point triples."""
    triples = points[rng.integers(0, len(points), size=(iterations, 3))]  # (I, 3, 3)
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    usable = norms > 1e-12
    if not usable.any():
        raise ValueError("points are degenerate (collinear or identical); cannot fit a plane")
    normals = normals[usable] / norms[usable, None]
    offsets = -np.einsum("ij,ij->i", normals, triples[usable, 0])
    # Score hypotheses on a subset: enough to rank them, cheap on full images.
    subset = points[rng.choice(len(points), size=min(len(points), 2000), replace=False)]
    counts = (np.abs(subset @ normals.T + offsets) < threshold_m).sum(axis=0)
    best = int(np.argmax(counts))
    return _oriented(normals[best], float(offsets[best]))


def fit_plane(points: np.ndarray, *, ransac_threshold_m: float = 0.02,
              ransac_iterations: int = 200, irls_iterations: int = 10,
              seed: int = 0) -> tuple[Plane, np.ndarray]:
    """Robust plane fit: RANSAC start, then IRLS with Tukey's biweight.

    Args:
        points: (N, 3) points in metres, N >= 3.
        ransac_threshold_m: inlier distance for scoring RANSAC hypotheses (metres).
        ransac_iterations: number of random point triples.
        irls_iterations: reweighting rounds after RANSAC.
        seed: seed of the random triples (the fit is deterministic for a seed).

    Returns:
        The plane and an (N,) bool inlier mask (points within Tukey's cut-off of the
        final robust scale).

    Raises:
        ValueError: fewer than 3 points, non-finite points, or a degenerate cloud.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {points.shape}")
    if len(points) < 3:
        raise ValueError(f"need at least 3 points to fit a plane, got {len(points)}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or infinite values")
    rng = np.random.default_rng(seed)
    plane = _ransac(points, ransac_threshold_m, ransac_iterations, rng)
    # A floor on the scale keeps noise-free data from collapsing the weights to zero.
    min_scale = 1e-6
    for _ in range(irls_iterations):
        residual = plane.distance(points)
        scale = max(_MAD_TO_STD * float(np.median(np.abs(residual))), min_scale)
        u = residual / (_TUKEY_C * scale)
        weights = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        if np.count_nonzero(weights) < 3:
            break
        plane = _fit_plane_lsq(points, weights)
    residual = plane.distance(points)
    scale = max(_MAD_TO_STD * float(np.median(np.abs(residual))), min_scale)
    return plane, np.abs(residual) < _TUKEY_C * scale


def plane_metrics(depth_m: np.ndarray, intrinsics: CameraIntrinsics, *,
                  plane: Plane | None = None, mask: np.ndarray | None = None,
                  seed: int = 0) -> PlaneMetrics:
    """Bias and jitter of a depth map of a flat wall.

    Args:
        depth_m: (H, W) depth in metres (0 = invalid), e.g. a prediction.
        intrinsics: intrinsics of the (H, W) image.
        plane: reference plane, e.g. ``fit_plane(backproject(gt, K))[0]``; when None the
            plane is fitted robustly to ``depth_m`` itself.
        mask: optional (H, W) bool region of the wall.
        seed: seed of the robust fit.

    Returns:
        :class:`PlaneMetrics`; inliers are pixels within Tukey's cut-off (4.685 robust
        sigmas) of the plane, the rest are excluded from bias and jitter.
    """
    points = backproject(depth_m, intrinsics, mask)
    count = len(points)
    if count < 3:
        raise ValueError(f"depth_m has {count} valid pixels in the mask; need at least 3")
    z = points[:, 2]
    rays = points / z[:, None]
    if plane is None:
        plane, _ = fit_plane(points, seed=seed)
    plane_z = plane.depth_along_rays(rays)
    hits = np.isfinite(plane_z) & (plane_z > 0)
    if not hits.any():
        raise ValueError("the plane is not in front of the camera for any valid pixel")
    error = z[hits] - plane_z[hits]
    scale = max(_MAD_TO_STD * float(np.median(np.abs(error - np.median(error)))), 1e-6)
    inliers = np.abs(error - np.median(error)) < _TUKEY_C * scale
    kept = error[inliers]
    return PlaneMetrics(bias_m=float(np.mean(np.abs(kept))), jitter_m=float(np.std(kept)),
                        mean_error_m=float(np.mean(kept)),
                        inlier_fraction=float(inliers.sum() / count), num_points=count,
                        plane=plane)
