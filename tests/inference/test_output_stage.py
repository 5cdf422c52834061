"""The output stage on the network's grid: blend, then calibrated sigma."""

from __future__ import annotations

import numpy as np

from deltar.inference.blend import ConfidenceBlend, RegionBlend, blend_with_fill
from deltar.inference.output_stage import apply_output_stage
from deltar.inference.uncertainty import RegionCalibration, UncertaintyCalibration

BLEND = ConfidenceBlend(RegionBlend(-1.0, -2.0), RegionBlend(-2.0, -2.0))
CALIBRATION = UncertaintyCalibration(RegionCalibration(2.0, 0.05, 1.0),
                                     RegionCalibration(3.0, 0.1, 0.5))


def _maps(rng: np.random.Generator, shape=(12, 16)):
    depth = rng.uniform(1.0, 3.0, shape).astype(np.float32)
    spread = rng.uniform(0.01, 0.5, shape).astype(np.float32)
    fill = rng.uniform(1.0, 3.0, shape).astype(np.float32)
    rects = np.array([[2.0, 3.0, 8.0, 11.0]], np.float32)  # the zone grid's box
    return depth, spread, fill, rects


def test_blend_then_sigma_of_the_blended_depth(rng):
    depth, spread, fill, rects = _maps(rng)
    out, sigma, network = apply_output_stage(depth, spread, fill, rects, BLEND, CALIBRATION,
                                             image_only=False)
    np.testing.assert_array_equal(out, blend_with_fill(depth, spread, fill, rects, BLEND))
    assert network is depth
    moved = np.abs(depth - out)
    inside = np.zeros(depth.shape, bool)
    inside[2:8, 3:11] = True
    expected = np.where(inside, np.sqrt((2.0 * spread) ** 2 + (0.05 * out) ** 2 + moved ** 2),
                        np.sqrt((3.0 * spread) ** 2 + (0.1 * out) ** 2 + (0.5 * moved) ** 2))
    np.testing.assert_allclose(sigma, expected, rtol=1e-5)


def test_without_a_fill_the_network_depth_is_returned(rng):
    depth, spread, _, rects = _maps(rng)
    out, sigma, network = apply_output_stage(depth, spread, None, rects, BLEND, None,
                                             image_only=False)
    assert out is depth and sigma is spread and network is None


def test_a_fill_for_another_grid_is_resized(rng):
    depth, spread, _, rects = _maps(rng)
    coarse = np.full((6, 8), 2.0, np.float32)
    out, _, _ = apply_output_stage(depth, spread, coarse, rects, BLEND, None, image_only=False)
    np.testing.assert_allclose(out, blend_with_fill(depth, spread, np.full_like(depth, 2.0),
                                                    rects, BLEND), rtol=1e-6)


def test_image_only_sigma_is_at_least_the_depth(rng):
    depth, spread, _, rects = _maps(rng)
    for calibration in (None, CALIBRATION):
        _, sigma, _ = apply_output_stage(depth, spread, None, rects, BLEND, calibration,
                                         image_only=True)
        assert np.all(sigma >= depth)
