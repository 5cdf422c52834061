"""Classical baselines: zone placement, invalid zones, extrapolation, filters, real frames."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from deltar.evaluation.baselines import (
    BASELINES,
    DEFAULT_FALLBACK_DEPTH_M,
    guided_filter,
    joint_bilateral_filter,
    run_baseline,
)
from deltar.evaluation.metrics import depth_metrics
from deltar.inference.colorization import colorization_fill


def grid_rects(grid: int, zone: float, top: float = 0.0, left: float = 0.0) -> np.ndarray:
    """Aligned zone rectangles (y0, x0, y1, x1), row-major."""
    return np.array([[top + r * zone, left + c * zone, top + (r + 1) * zone,
                      left + (c + 1) * zone] for r in range(grid) for c in range(grid)])


def flat_image(height: int, width: int, value: int = 128) -> np.ndarray:
    return np.full((height, width, 3), value, dtype=np.uint8)


def test_nearest_places_zone_values_in_their_rectangles() -> None:
    rects = grid_rects(2, 4.0)
    means = np.array([1.0, 2.0, 3.0, 4.0])
    depth = run_baseline("nearest", flat_image(8, 8), means, np.ones(4, bool), rects)
    expected = np.block([[np.full((4, 4), 1.0), np.full((4, 4), 2.0)],
                         [np.full((4, 4), 3.0), np.full((4, 4), 4.0)]])
    np.testing.assert_array_equal(depth, expected)
    assert depth.dtype == np.float32


def test_nearest_uses_pixel_centres_for_fractional_rects() -> None:
    # Zone 0 spans x in [0, 2.5): pixel centres 0, 1, 2 are inside, 3 is in zone 1.
    rects = np.array([[0, 0, 2.5, 2.5], [0, 2.5, 2.5, 5], [2.5, 0, 5, 2.5], [2.5, 2.5, 5, 5]])
    depth = run_baseline("nearest", flat_image(5, 5), np.array([1.0, 2.0, 3.0, 4.0]),
                         np.ones(4, bool), rects)
    np.testing.assert_array_equal(depth[0], [1, 1, 1, 2, 2])
    np.testing.assert_array_equal(depth[:, 0], [1, 1, 1, 3, 3])


def test_nearest_fills_invalid_zone_from_nearest_valid_pixel() -> None:
    rects = grid_rects(2, 4.0)
    means = np.array([1.0, 2.0, 3.0, 50.0])  # zone 3 invalid; its value must not appear
    valid = np.array([True, True, True, False])
    depth = run_baseline("nearest", flat_image(8, 8), means, valid, rects)
    # Pixel (7, 4): 1 px from zone 2's pixel (7, 3), 4 px from zone 1's pixel (3, 4).
    assert depth[7, 4] == 3.0
    assert depth[4, 7] == 2.0
    assert set(np.unique(depth[4:, 4:])) <= {2.0, 3.0}


def test_zones_beyond_the_image_and_outside_the_fov() -> None:
    # Zones run past the top and bottom of a 20 x 40 image and leave its sides uncovered.
    rects = grid_rects(2, 15.0, top=-5.0, left=5.0)
    means = np.array([1.0, 2.0, 3.0, 4.0])
    for name in BASELINES:
        depth = run_baseline(name, flat_image(20, 40), means, np.ones(4, bool), rects)
        assert depth.shape == (20, 40)
        assert np.all(np.isfinite(depth)) and depth.min() >= 1.0 - 1e-6, name
        assert depth.max() <= 4.0 + 1e-6, name
    nearest = run_baseline("nearest", flat_image(20, 40), means, np.ones(4, bool), rects)
    # Left border outside the FoV: nearest zone is zone 0 (top) or zone 2 (bottom).
    assert nearest[0, 0] == 1.0 and nearest[19, 0] == 3.0
    assert nearest[0, 39] == 2.0 and nearest[19, 39] == 4.0


def test_bilinear_matches_linear_interpolation_between_zone_centres() -> None:
    # Values vary along columns only: bilinear = 1D interpolation between column centres,
    # constant beyond the first and last centre.
    rects = grid_rects(4, 10.0, top=0.0, left=0.0)
    column_values = np.array([1.0, 1.5, 3.0, 2.0])
    means = np.tile(column_values, 4)
    depth = run_baseline("bilinear", flat_image(40, 40), means, np.ones(16, bool), rects)
    expected = np.interp(np.arange(40), [5.0, 15.0, 25.0, 35.0], column_values)
    np.testing.assert_allclose(depth, np.broadcast_to(expected, (40, 40)), atol=1e-3)


def test_bicubic_hits_zone_values_at_zone_centres() -> None:
    rng = np.random.default_rng(1)
    rects = grid_rects(4, 10.0)
    means = rng.uniform(1.0, 3.0, 16)
    depth = run_baseline("bicubic", flat_image(40, 40), means, np.ones(16, bool), rects)
    centres = np.arange(4) * 10 + 5
    np.testing.assert_allclose(depth[np.ix_(centres, centres)], means.reshape(4, 4), atol=1e-4)
    assert depth.min() >= means.min() - 1e-6 and depth.max() <= means.max() + 1e-6


def test_median_baseline() -> None:
    means = np.array([1.0, 2.0, 9.0, 4.0])
    valid = np.array([True, True, False, True])
    depth = run_baseline("median", flat_image(6, 6), means, valid, grid_rects(2, 3.0))
    np.testing.assert_array_equal(depth, np.full((6, 6), 2.0))


@pytest.mark.parametrize("name", BASELINES)
def test_invalid_zone_values_never_leak(name: str) -> None:
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    rects = grid_rects(4, 12.0, top=0.0, left=8.0)
    means = rng.uniform(1.0, 2.0, 16)
    valid = rng.random(16) > 0.3
    means[~valid] = 40.0
    depth = run_baseline(name, image, means, valid, rects)
    assert np.all(np.isfinite(depth))
    assert depth.min() >= means[valid].min() - 1e-4
    assert depth.max() <= means[valid].max() + 1e-4


@pytest.mark.parametrize("name", BASELINES)
def test_no_valid_zone_returns_constant_fallback(name: str) -> None:
    with pytest.warns(RuntimeWarning, match="fallback"):
        depth = run_baseline(name, flat_image(8, 8), np.zeros(4), np.zeros(4, bool),
                             grid_rects(2, 4.0))
    np.testing.assert_array_equal(depth, np.full((8, 8), DEFAULT_FALLBACK_DEPTH_M))


def test_invalid_zones_may_hold_nan() -> None:
    means = np.array([1.0, np.nan, 2.0, 2.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        depth = run_baseline("bilinear", flat_image(8, 8), means,
                             np.array([True, False, True, True]), grid_rects(2, 4.0))
    assert np.all(np.isfinite(depth))


def test_bad_inputs_raise_clear_errors() -> None:
    image, rects, valid = flat_image(8, 8), grid_rects(2, 4.0), np.ones(4, bool)
    means = np.ones(4)
    with pytest.raises(ValueError, match="bilinear, bicubic"):
        run_baseline("nope", image, means, valid, rects)
    with pytest.raises(ValueError, match="image_rgb"):
        run_baseline("nearest", image.astype(np.float32), means, valid, rects)
    with pytest.raises(ValueError, match="square number"):
        run_baseline("nearest", image, np.ones(5), np.ones(5, bool), np.zeros((5, 4)))
    with pytest.raises(ValueError, match="zone_valid"):
        run_baseline("nearest", image, means, np.ones(3, bool), rects)
    with pytest.raises(ValueError, match="zone_rects"):
        run_baseline("nearest", image, means, valid, rects[:, :3])
    with pytest.raises(ValueError, match="zone_mean_m"):
        run_baseline("nearest", image, np.array([1.0, np.nan, 1.0, 1.0]), valid, rects)
    with pytest.raises(ValueError, match="y1 > y0"):
        run_baseline("nearest", image, means, valid, rects[:, [2, 1, 0, 3]])


def reference_guided_filter(p: np.ndarray, guide: np.ndarray, r: int, eps: float) -> np.ndarray:
    """He et al.'s colour guided filter written out pixel by pixel (symmetric borders)."""
    h, w = p.shape
    pad_p = np.pad(p, r, mode="symmetric")
    pad_i = np.pad(guide, ((r, r), (r, r), (0, 0)), mode="symmetric")
    a = np.zeros((h, w, 3))
    b = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            win_i = pad_i[y:y + 2 * r + 1, x:x + 2 * r + 1].reshape(-1, 3)
            win_p = pad_p[y:y + 2 * r + 1, x:x + 2 * r + 1].reshape(-1)
            mu, mp = win_i.mean(0), win_p.mean()
            cov = (win_i * win_p[:, None]).mean(0) - mu * mp
            sigma = win_i.T @ win_i / len(win_i) - np.outer(mu, mu)
            a[y, x] = np.linalg.solve(sigma + eps * np.eye(3), cov)
            b[y, x] = mp - a[y, x] @ mu
    pad_a = np.pad(a, ((r, r), (r, r), (0, 0)), mode="symmetric")
    pad_b = np.pad(b, r, mode="symmetric")
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            mean_a = pad_a[y:y + 2 * r + 1, x:x + 2 * r + 1].reshape(-1, 3).mean(0)
            out[y, x] = mean_a @ guide[y, x] + pad_b[y:y + 2 * r + 1, x:x + 2 * r + 1].mean()
    return out


def test_guided_filter_matches_pixelwise_reference() -> None:
    rng = np.random.default_rng(3)
    guide = rng.random((9, 11, 3))
    source = rng.uniform(1.0, 3.0, (9, 11))
    np.testing.assert_allclose(guided_filter(source, guide, 2, 1e-2),
                               reference_guided_filter(source, guide, 2, 1e-2), atol=1e-8)


def test_guided_filter_moves_depth_edge_to_image_edge() -> None:
    # Image edge at column 10, depth step (blocky zone map) at column 13.
    guide = np.zeros((20, 24, 3))
    guide[:, 10:] = 1.0
    source = np.where(np.arange(24) < 13, 1.0, 3.0)[None].repeat(20, 0)
    out = guided_filter(source, guide, radius=4, eps=1e-4)
    assert abs(out[10, 11] - 3.0) < abs(source[10, 11] - 3.0)  # pulled to the far side
    assert np.ptp(out[10, 11:13]) < 0.2  # the step now sits at the image edge
    # A jump appears at the image edge, where the source had none.
    assert out[10, 10] - out[10, 9] > 0.5


def reference_joint_bilateral(source, guide, radius, sigma_space, sigma_color, step=1):
    h, w = source.shape
    out = np.zeros((h, w))
    taps = [d for d in range(-radius, radius + 1) if d % step == 0]
    for y in range(h):
        for x in range(w):
            num = den = 0.0
            for dy in taps:
                for dx in taps:
                    qy = min(max(y + dy, 0), h - 1)
                    qx = min(max(x + dx, 0), w - 1)
                    weight = np.exp(-(dy * dy + dx * dx) / (2 * sigma_space**2)
                                    - np.sum((guide[qy, qx] - guide[y, x]) ** 2)
                                    / (2 * sigma_color**2))
                    num += weight * source[qy, qx]
                    den += weight
            out[y, x] = num / den
    return out


@pytest.mark.parametrize(("radius", "step"), [(2, 1), (4, 2)])
def test_joint_bilateral_matches_pixelwise_reference(radius: int, step: int) -> None:
    rng = np.random.default_rng(4)
    guide = rng.random((7, 8, 3)).astype(np.float32)
    source = rng.uniform(1.0, 3.0, (7, 8)).astype(np.float32)
    np.testing.assert_allclose(
        joint_bilateral_filter(source, guide, radius, 1.5, 0.3, step=step),
        reference_joint_bilateral(source, guide, radius, 1.5, 0.3, step=step), rtol=1e-5)


def test_joint_bilateral_does_not_mix_across_colour_edges() -> None:
    guide = np.zeros((10, 10, 3), dtype=np.float32)
    guide[:, 5:] = 1.0
    source = np.where(np.arange(10) < 5, 1.0, 2.0)[None].repeat(10, 0)
    out = joint_bilateral_filter(source, guide, 3, 3.0, 0.05, step=1)
    np.testing.assert_allclose(out, source, atol=1e-6)


def test_colorization_fill_follows_image_regions() -> None:
    gray = np.zeros((12, 12))
    gray[:, 6:] = 1.0
    known = np.zeros((12, 12), dtype=bool)
    values = np.zeros((12, 12))
    known[6, 1], values[6, 1] = True, 1.0
    known[6, 10], values[6, 10] = True, 3.0
    filled = colorization_fill(gray, values, known)
    assert np.all(np.abs(filled[:, :6] - 1.0) < 0.05)
    assert np.all(np.abs(filled[:, 6:] - 3.0) < 0.05)


@pytest.mark.parametrize("shape", [(7, 11), (11, 7), (9, 9)])
def test_colorization_banded_solve_is_the_sparse_solve(shape, monkeypatch) -> None:
    """The grid solver's banded LU (either numbering) and its sparse fallback agree."""
    import scipy.sparse.linalg

    from deltar.inference import colorization, stencil_solver

    rng = np.random.default_rng(3)
    gray = rng.random(shape)
    known = rng.random(shape) < 0.2
    known[0, 0] = True
    values = rng.uniform(0.5, 4.0, shape)
    banded = colorization_fill(gray, values, known)
    system = colorization.colorization_matrix(gray) + scipy.sparse.diags(
        known.ravel().astype(float))
    reference = scipy.sparse.linalg.spsolve(system.tocsc(), (known * values).ravel())
    np.testing.assert_allclose(banded.ravel(), reference, rtol=1e-9, atol=1e-12)
    monkeypatch.setattr(stencil_solver, "_MAX_BANDED_ENTRIES", 0)
    np.testing.assert_allclose(colorization_fill(gray, values, known), banded, rtol=1e-9,
                               atol=1e-12)


def test_colorization_options_are_checked() -> None:
    from deltar.evaluation.baselines import check_baseline_inputs, complete_colorization

    inputs = check_baseline_inputs(np.zeros((16, 16, 3), np.uint8), np.ones(4), np.ones(4, bool),
                               np.array([[0, 0, 8, 8], [0, 8, 8, 16], [8, 0, 16, 8],
                                         [8, 8, 16, 16]], np.float32))
    with pytest.raises(ValueError, match="solve_cells"):
        complete_colorization(inputs, solve_cells=2)
    with pytest.raises(ValueError, match="seed_side"):
        complete_colorization(inputs, seed_side=2)
    np.testing.assert_allclose(complete_colorization(inputs, solve_cells=64), 1.0)


def test_colorization_fill_constant_and_errors() -> None:
    rng = np.random.default_rng(5)
    gray = rng.random((8, 9))
    known = np.zeros((8, 9), dtype=bool)
    known[2, 2] = known[6, 7] = True
    filled = colorization_fill(gray, np.full((8, 9), 2.5), known)
    np.testing.assert_allclose(filled, 2.5, atol=1e-9)
    with pytest.raises(ValueError, match="at least one"):
        colorization_fill(gray, np.zeros((8, 9)), np.zeros((8, 9), bool))


def test_baselines_on_a_real_frame(shared_data: Path) -> None:
    """Zone means from a real 7-Scenes depth map; every baseline must beat one constant."""
    stem = shared_data / "7scenes_redkitchen" / "frame-000100"
    rgb = cv2.cvtColor(cv2.imread(f"{stem}.color.jpg"), cv2.COLOR_BGR2RGB)
    gt = cv2.imread(f"{stem}.depth.png", cv2.IMREAD_UNCHANGED).astype(np.float32)
    gt[gt == 65535] = 0
    gt /= 1000.0
    # The release's simulated layout: 8 x 8 zones of 56 px from (16, 96).
    rects = grid_rects(8, 56.0, top=16.0, left=96.0)
    means, valid = np.zeros(64), np.zeros(64, bool)
    for k, (y0, x0, y1, x1) in enumerate(rects.astype(int)):
        patch = gt[y0:y1, x0:x1]
        patch = patch[patch > 0]
        if patch.size > 500:
            means[k], valid[k] = patch.mean(), True
    assert valid.sum() > 40
    baseline_rmse = depth_metrics(run_baseline("median", rgb, means, valid, rects), gt)["rmse"]
    for name in ("nearest", "bilinear", "guided_filter", "colorization"):
        metrics = depth_metrics(run_baseline(name, rgb, means, valid, rects), gt)
        assert metrics["rmse"] < baseline_rmse, name
        assert metrics["d1"] > 0.7, name
