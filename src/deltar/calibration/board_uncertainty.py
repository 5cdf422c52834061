"""How well a board calibration's zones pin the extrinsic down (its expected error).

Each zone reports the mean z-depth over its footprint. Given a view's board plane in the
camera frame and the extrinsic, that mean is predicted by averaging the z-depth of the
plane over a grid of rays inside the zone's cell (the footprint model). The zone noise
is the robust spread of measured minus predicted means, and the Fisher information of
all views' zones about the six extrinsic parameters, with each view's board-plane
uncertainty (:class:`deltar.calibration.board.BoardPose`) folded into its zones'
covariance, gives the covariance of any unbiased estimate: the Cramer-Rao bound. When the
camera intrinsics were calibrated from the same views, their error (which moves every
view's plane together) is propagated to the solution and added. The
board path's estimate is close to it on synthetic rigs (benchmarks/RESULTS.md), so the
bound is the error to expect, and it says when more or steeper views are needed.

The rotation error is dominated by the roll about the viewing axis: it is seen only
through the direction in which each plane is tilted, so it shrinks with the tilt of
the views and with the number of views.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.calibration.plane import zone_cells_tan
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics

#: Floor on the zone noise used for the bound, metres (a perfect fit is not perfect data).
MIN_ZONE_NOISE_M = 0.002


@dataclass(frozen=True)
class ExtrinsicUncertainty:
    """The expected error of a calibrated extrinsic (1 standard deviation).

    Attributes:
        rotation_sd_deg: (3,) about the camera's x, y and z (viewing) axes, degrees.
        translation_sd_m: (3,) along the camera's x, y and z axes, metres.
        zone_noise_m: robust standard deviation of the zones' residuals, metres.
        zones: zone readings used.
        covariance: (6, 6) of (rotation vector in radians, translation in metres), the
            rotation applied on the camera side (``R' = exp([w]) R``).
    """

    rotation_sd_deg: np.ndarray
    translation_sd_m: np.ndarray
    zone_noise_m: float
    zones: int
    covariance: np.ndarray

    @property
    def rotation_rms_deg(self) -> float:
        """Expected rotation error (root of the summed variances), degrees."""
        return float(np.sqrt(np.sum(self.rotation_sd_deg ** 2)))

    @property
    def translation_rms_m(self) -> float:
        """Expected translation error (root of the summed variances), metres."""
        return float(np.sqrt(np.sum(self.translation_sd_m ** 2)))

    def miss_probability(self, rotation_deg: float, translation_m: float,
                         samples: int = 20000, seed: int = 0) -> float:
        """Share of errors drawn from the covariance beyond either bound (degrees, metres)."""
        draws = np.random.default_rng(seed).multivariate_normal(np.zeros(6), self.covariance,
                                                                samples)
        rot = np.degrees(np.linalg.norm(draws[:, :3], axis=1))
        return float(np.mean((rot > rotation_deg) |
                             (np.linalg.norm(draws[:, 3:], axis=1) > translation_m)))


def zone_footprint_rays(grid: int = 8, fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                        samples: int = 4) -> np.ndarray:
    """Rays on a regular ``samples x samples`` grid inside each zone's cell.

    Returns:
        (grid * grid, samples * samples, 3) float64 sensor-frame rays ``(tan ax, tan ay,
        1)``: a point at z-depth ``z`` on a ray is ``z * ray``.
    """
    cells = zone_cells_tan(grid, fov_deg)  # (v0, u0, v1, u1)
    f = (np.arange(samples) + 0.5) / samples
    u = cells[:, 1, None] + (cells[:, 3] - cells[:, 1])[:, None] * f
    v = cells[:, 0, None] + (cells[:, 2] - cells[:, 0])[:, None] * f
    uu = np.repeat(u[:, None, :], samples, axis=1)
    vv = np.repeat(v[:, :, None], samples, axis=2)
    return np.stack([uu, vv, np.ones_like(uu)], axis=-1).reshape(len(cells), -1, 3)


def predicted_zone_depth(normal_cam: np.ndarray, offset_cam_m: float,
                         extrinsics: SensorExtrinsics, rays: np.ndarray) -> np.ndarray:
    """Each zone's mean z-depth (metres) of a camera-frame plane ``n . p + d = 0``.

    Args:
        normal_cam: (3,) unit normal in the camera frame.
        offset_cam_m: offset d, metres.
        extrinsics: sensor-to-camera transform.
        rays: (Z, S, 3) footprint rays (:func:`zone_footprint_rays`).

    Returns:
        (Z,) float64 means over each footprint of the plane's z-depth along its rays.
    """
    normal = np.asarray(normal_cam, dtype=np.float64)
    normal_sensor = extrinsics.rotation.T @ normal
    offset_sensor = float(offset_cam_m) + float(normal @ extrinsics.translation_m)
    return (-offset_sensor / (rays @ normal_sensor)).mean(axis=1)


def _perturbed(extrinsics: SensorExtrinsics, x: np.ndarray) -> SensorExtrinsics:
    from scipy.spatial.transform import Rotation

    return SensorExtrinsics(Rotation.from_rotvec(x[:3]).as_matrix() @ extrinsics.rotation,
                            extrinsics.translation_m + x[3:])


def _tilted(normal: np.ndarray, offset: float, x: np.ndarray) -> tuple[np.ndarray, float]:
    """The plane with its normal turned by x[0], x[1] radians about two axes across it and
    its offset moved by x[2] metres."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    turned = normal + x[0] * a + x[1] * b
    return turned / np.linalg.norm(turned), offset + x[2]


def extrinsic_uncertainty(planes_cam: Sequence[tuple[np.ndarray, float, float, float]],
                          zone_means_m: Sequence[np.ndarray],
                          zone_masks: Sequence[np.ndarray],
                          extrinsics: SensorExtrinsics, *,
                          grid: int = 8,
                          fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                          zone_noise_m: float | None = None,
                          plane_sensitivity: Sequence[np.ndarray] | None = None,
                          camera_covariance: np.ndarray | None = None,
                          ) -> ExtrinsicUncertainty:
    """The covariance of the extrinsic that the views' zone readings allow (Cramer-Rao).

    Args:
        planes_cam: per view, the board's plane in the camera frame and its uncertainty:
            ``(normal (3,), offset d in metres, normal direction sd in radians, offset
            sd in metres)``.
        zone_means_m: per view, (Z,) zone means (z-depth, metres).
        zone_masks: per view, (Z,) bool zones that see the plane.
        extrinsics: the calibrated sensor-to-camera transform.
        grid, fov_deg: zones per side and the sensor's field of view (degrees).
        zone_noise_m: the zones' noise (metres); default: the residuals' robust spread
            (1.4826 x their median absolute deviation), at least ``MIN_ZONE_NOISE_M``.
        plane_sensitivity: per view, (4, P) derivative of its board plane (normal x, y,
            z and offset in metres) with respect to P camera parameters shared by all
            views (e.g. fx, fy, cx, cy in pixels).
        camera_covariance: (P, P) covariance of those parameters. An error in them moves
            every view's plane together, which more views do not average away; its
            effect on the solution is added to the bound (first order).

    Returns:
        ``ExtrinsicUncertainty``.

    Raises:
        ValueError: mismatched lengths, or views that leave the extrinsic undetermined.
    """
    if plane_sensitivity is not None and len(plane_sensitivity) != len(planes_cam):
        raise ValueError(f"plane_sensitivity must have one entry per view, got "
                         f"{len(plane_sensitivity)} for {len(planes_cam)}")
    if not len(planes_cam) == len(zone_means_m) == len(zone_masks):
        raise ValueError(f"planes_cam, zone_means_m and zone_masks must have one entry per "
                         f"view, got {len(planes_cam)}, {len(zone_means_m)}, "
                         f"{len(zone_masks)}")
    rays = zone_footprint_rays(grid, fov_deg)
    step = 1e-6
    per_view = []
    for (normal, offset, normal_sd, offset_sd), mean, mask in zip(
            planes_cam, zone_means_m, zone_masks, strict=True):
        mask = np.asarray(mask, dtype=bool).reshape(-1)
        normal = np.asarray(normal, dtype=np.float64)
        use = rays[mask]

        def depth(x6: np.ndarray, x3: np.ndarray = np.zeros(3), normal=normal,
                  offset=offset, use=use) -> np.ndarray:
            return predicted_zone_depth(*_tilted(normal, offset, x3),
                                        _perturbed(extrinsics, x6), use)

        residual = depth(np.zeros(6)) - np.asarray(mean, dtype=np.float64).reshape(-1)[mask]
        jac = np.stack([(depth(step * e) - depth(-step * e)) / (2 * step)
                        for e in np.eye(6)], axis=1)
        plane_jac = np.stack([(depth(np.zeros(6), step * e) - depth(np.zeros(6), -step * e))
                              / (2 * step) for e in np.eye(3)], axis=1)
        plane_cov = np.diag([normal_sd ** 2 / 2, normal_sd ** 2 / 2, offset_sd ** 2])
        shared = None
        if plane_sensitivity is not None:
            # d(zone means) / d(normal x, y, z, offset), then through the camera parameters.
            raw = np.stack([(predicted_zone_depth(normal + step * e[:3], offset + step * e[3],
                                                  extrinsics, use)
                             - predicted_zone_depth(normal - step * e[:3],
                                                    offset - step * e[3], extrinsics, use))
                            / (2 * step) for e in np.eye(4)], axis=1)
            shared = raw @ np.asarray(plane_sensitivity[len(per_view)], dtype=np.float64)
        per_view.append((residual, jac, plane_jac @ plane_cov @ plane_jac.T, shared))
    residuals = np.concatenate([r for r, *_ in per_view])
    if zone_noise_m is None:
        spread = 1.4826 * np.median(np.abs(residuals - np.median(residuals)))
        zone_noise_m = max(float(spread), MIN_ZONE_NOISE_M)
    information = np.zeros((6, 6))
    coupling = 0.0  # sum of J^T C^-1 (d zone means / d camera parameters), (6, P)
    for residual, jac, plane_part, shared in per_view:
        cov = zone_noise_m ** 2 * np.eye(len(residual)) + plane_part
        information += jac.T @ np.linalg.solve(cov, jac)
        if shared is not None:
            coupling = coupling + jac.T @ np.linalg.solve(cov, shared)
    if np.linalg.cond(information) > 1e12:
        raise ValueError("the views leave the extrinsic undetermined (too few or too "
                         "similar planes)")
    covariance = np.linalg.inv(information)
    if plane_sensitivity is not None and camera_covariance is not None:
        moved = covariance @ coupling  # how the solution follows the camera parameters
        covariance = covariance + moved @ np.asarray(camera_covariance, float) @ moved.T
    sd = np.sqrt(np.diag(covariance))
    return ExtrinsicUncertainty(np.degrees(sd[:3]), sd[3:], float(zone_noise_m),
                                int(residuals.size), covariance)
