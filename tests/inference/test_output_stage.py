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


def test_zones_that_reported_no_target_get_sigma_to_the_range_limit(rng):
    """Such a zone says only "beyond the range": its cells' sigma reaches from the depth
    placed there to the range limit; cells put nearer, and other zones, keep theirs."""
    depth, spread, _, _ = _maps(rng)
    rects = np.array([[0.0, 0.0, 6.0, 8.0], [0.0, 8.0, 6.0, 16.0], [6.0, 0.0, 12.0, 16.0]],
                     np.float32)
    depth[:6, :8] = 6.0
    depth[0, 0] = 3.0  # the network put one cell nearer than the range
    plain = apply_output_stage(depth, spread, None, rects, None, CALIBRATION, False)[1]
    _, sigma, _ = apply_output_stage(depth, spread, None, rects, None, CALIBRATION, False,
                                     no_target=(np.array([True, False, False]), 4.0))
    expected = plain.copy()
    expected[:6, :8] = np.maximum(plain[:6, :8], 2.0)
    expected[0, 0] = plain[0, 0]
    np.testing.assert_allclose(sigma, expected, rtol=1e-6)
    assert (sigma[:6, :8][depth[:6, :8] > 4] >= 2.0).all()
    assert (sigma[:6, 8:] == plain[:6, 8:]).all()
    none = apply_output_stage(depth, spread, None, rects, None, CALIBRATION, False,
                              no_target=(np.zeros(3, bool), 4.0))[1]
    np.testing.assert_array_equal(none, plain)
    # Without a calibration the raw spread is returned as it is (the fits read it).
    raw = apply_output_stage(depth, spread, None, rects, None, None, False,
                             no_target=(np.array([True, False, False]), 4.0))[1]
    np.testing.assert_array_equal(raw, spread)
