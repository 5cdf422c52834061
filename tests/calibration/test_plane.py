"""Plane from one zone frame (DELTAR Eq. 1): accuracy, EM constraints, robustness, errors."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.calibration.plane import (
    _closest_in_cell,
    fit_plane_to_zones,
    ransac_plane,
    zone_cells_tan,
)
from deltar.calibration.synthetic import look_at, render_planes_depth, sensor_virtual_camera
from deltar.sensor.simulate import simulate_zone_frame


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def _exact_zone_means(normal: np.ndarray, offset: float, samples: int = 40) -> np.ndarray:
    """Reference: average z-depth of the plane over each zone's cell, by dense sampling
    (uniform in tan space, as a pinhole depth image samples it)."""
    means = []
    for v0, u0, v1, u1 in zone_cells_tan(8):
        u, v = np.meshgrid(np.linspace(u0, u1, samples), np.linspace(v0, v1, samples))
        means.append(np.mean(-offset / (normal[0] * u + normal[1] * v + normal[2])))
    return np.array(means)


@pytest.mark.parametrize("normal", [(0, 0, -1), (0.3, -0.2, -1), (-0.5, 0.1, -1),
                                    (0.1, 0.6, -1)])
def test_noiseless_tilted_planes_are_recovered(normal):
    normal = _unit(normal)
    means = _exact_zone_means(normal, 1.4)
    fit = fit_plane_to_zones(means, np.ones(64, bool))
    assert _angle_deg(fit.normal, normal) < 0.1
    assert fit.offset_m == pytest.approx(1.4, abs=0.005)
    assert fit.inliers.all()
    assert fit.rms_residual_m < 1e-3


def test_points_stay_in_their_cells_at_the_zone_depth(rng):
    normal = _unit((0.2, 0.3, -1))
    means = _exact_zone_means(normal, 1.2) + rng.normal(0, 0.02, 64)
    fit = fit_plane_to_zones(means, np.ones(64, bool))
    cells = zone_cells_tan(8)
    pts = fit.points_m
    np.testing.assert_allclose(pts[:, 2], means, atol=1e-9)  # z equals the zone mean
    u, v = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    assert np.all((u >= cells[:, 1] - 1e-12) & (u <= cells[:, 3] + 1e-12))
    assert np.all((v >= cells[:, 0] - 1e-12) & (v <= cells[:, 2] + 1e-12))
    # Moving inside the cells explains most of the noise: the residual is below it.
    assert fit.rms_residual_m < 0.02


def test_m_step_matches_brute_force_search(rng):
    """The closed-form in-cell move equals a dense grid search (|distance| first, then
    closeness to the cell centre)."""
    cells = zone_cells_tan(8)[[0, 9, 27, 63]]
    for _ in range(5):
        normal, offset = _unit(rng.normal(size=3)), float(rng.uniform(-2, 2))
        mean = rng.uniform(0.5, 3.0, 4)
        uv = _closest_in_cell(cells, mean, normal, offset)
        for k, (v0, u0, v1, u1) in enumerate(cells):
            gu, gv = np.meshgrid(np.linspace(u0, u1, 801), np.linspace(v0, v1, 801))
            dist = np.abs(mean[k] * (normal[0] * gu + normal[1] * gv + normal[2]) + offset)
            best = dist.min()
            got = abs(mean[k] * (normal[0] * uv[k, 0] + normal[1] * uv[k, 1] + normal[2])
                      + offset)
            assert got <= best + 1e-9
            if best < 1e-6:  # the plane crosses the cell and we reached it
                continue
            # Off-plane cells: the grid optimum and ours coincide up to the grid step.
            ij = np.unravel_index(np.argmin(dist), dist.shape)
            step = (u1 - u0) / 800 + (v1 - v0) / 800
            assert abs(gu[ij] - uv[k, 0]) + abs(gv[ij] - uv[k, 1]) < 3 * step or \
                got == pytest.approx(best, abs=1e-9)


def test_simulated_noiseless_frames_recover_the_wall_within_one_degree():
    room = np.array([[-1.0, 0, 0, 2.5], [0, -1.0, 0, 1.3], [0, 1.0, 0, 1.3],
                     [0, 0, -1.0, 3.0], [0, 0, 1.0, 3.0]])
    cam, rects = sensor_virtual_camera(8, (45, 45), 16)
    for eye, target in [((1.0, 0, 0), (2.5, 0.2, 0.3)), ((0.5, 0.3, -0.5), (2.5, -0.1, 0.4)),
                        ((1.7, -0.2, 0.2), (2.5, 0.0, -0.3))]:
        pose = look_at(eye, target)
        frame = simulate_zone_frame(render_planes_depth(room, pose, cam), rects)
        fit = fit_plane_to_zones(frame)
        truth = pose[:3, :3].T @ np.array([-1.0, 0, 0])  # wall normal in the sensor frame
        assert _angle_deg(fit.normal, truth) < 1.0
        assert fit.offset_m == pytest.approx(2.5 - eye[0], abs=0.02)  # sensor-wall distance


def test_zones_on_another_surface_are_dropped():
    normal = _unit((0.1, -0.2, -1))
    means = _exact_zone_means(normal, 1.5)
    clutter = np.zeros(64, bool)
    clutter[[0, 1, 2, 8, 9, 10]] = True  # an object 40 cm in front of the plane
    means[clutter] -= 0.4
    fit = fit_plane_to_zones(means, np.ones(64, bool))
    assert not fit.inliers[clutter].any()
    assert fit.inliers[~clutter].all()
    assert _angle_deg(fit.normal, normal) < 0.1


def test_ransac_plane_finds_the_dominant_plane(rng):
    plane_pts = np.column_stack([rng.uniform(-1, 1, (300, 2)), np.full(300, 2.0)])
    outliers = rng.uniform(-1, 1, (150, 3)) + np.array([0, 0, 1.0])
    normal, offset, inliers = ransac_plane(np.vstack([plane_pts, outliers]), 0.01)
    assert _angle_deg(normal, np.array([0, 0, 1.0])) < 1e-6
    assert offset == pytest.approx(2.0)
    assert inliers[:300].all() and inliers[300:].mean() < 0.05


def test_too_few_valid_zones_says_what_to_record():
    means = _exact_zone_means(_unit((0, 0, -1)), 1.0)
    valid = np.zeros(64, bool)
    valid[:4] = True
    with pytest.raises(ValueError, match=r"only 4 valid zones.*point the sensor at a plane"):
        fit_plane_to_zones(means, valid)


def test_zones_on_one_line_are_rejected():
    means = _exact_zone_means(_unit((0, 0, -1)), 1.0)
    valid = np.zeros(64, bool)
    valid[8:16] = True  # one row of zones
    with pytest.raises(ValueError, match="one line"):
        fit_plane_to_zones(means, valid)


def test_bad_arrays_are_rejected():
    with pytest.raises(ValueError, match="16 or 64"):
        fit_plane_to_zones(np.ones(10), np.ones(10, bool))
    means = np.ones(64)
    means[5] = np.nan
    with pytest.raises(ValueError, match="finite"):
        fit_plane_to_zones(means, np.ones(64, bool))
    with pytest.raises(ValueError, match="valid"):
        fit_plane_to_zones(np.ones(64), np.ones(16, bool))
