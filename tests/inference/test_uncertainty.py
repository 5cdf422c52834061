"""Calibrated sigma: the fit, its serialisation and the estimator applying it."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.inference.estimator import DepthEstimator
from deltar.inference.uncertainty import (
    GAUSSIAN_WITHIN_1,
    GAUSSIAN_WITHIN_2,
    CalibrationPixels,
    RegionCalibration,
    UncertaintyCalibration,
    coverage,
    fit_uncertainty_calibration,
)
from deltar.sensor.zone_frame import ZoneFrame


def _pixels(rng, n=40_000, spread_scale=(3.0, 0.5), heavy=False) -> CalibrationPixels:
    """Errors drawn with sigma = k * spread, k differing inside and outside the grid."""
    inside = rng.random(n) < 0.7
    spread = rng.uniform(0.01, 0.2, n)
    depth = rng.uniform(0.5, 4.0, n)
    true_sigma = np.where(inside, spread_scale[0], spread_scale[1]) * spread
    noise = rng.standard_t(4, n) / np.sqrt(2.0) if heavy else rng.standard_normal(n)
    return CalibrationPixels(np.abs(noise * true_sigma), spread, depth, np.zeros(n), inside)


def test_fit_recovers_the_scale_of_gaussian_errors(rng) -> None:
    pixels = _pixels(rng)
    calibration = fit_uncertainty_calibration(pixels)
    assert calibration.inside.spread == pytest.approx(3.0, rel=0.08)
    assert calibration.outside.spread == pytest.approx(0.5, rel=0.08)
    sigma = calibration.sigma(pixels.spread_m, pixels.depth_m, pixels.moved_m, pixels.inside)
    within_1, within_2 = coverage(pixels.error_m, sigma)
    assert within_1 == pytest.approx(GAUSSIAN_WITHIN_1, abs=0.02)
    assert within_2 == pytest.approx(GAUSSIAN_WITHIN_2, abs=0.02)


def test_heavy_tails_land_in_the_coverage_bands(rng) -> None:
    """Student-t errors: no scale gives 68.3 / 95.4 exactly; the fit stays in the bands."""
    pixels = _pixels(rng, heavy=True)
    calibration = fit_uncertainty_calibration(pixels)
    sigma = calibration.sigma(pixels.spread_m, pixels.depth_m, pixels.moved_m, pixels.inside)
    for mask in (pixels.inside, ~pixels.inside):
        within_1, within_2 = coverage(pixels.error_m[mask], sigma[mask])
        assert 0.63 <= within_1 <= 0.75
        assert 0.92 <= within_2 <= 0.97
    # Raw spreads (scale 1) cover far less inside, where the true scale is 3.
    raw_1, _ = coverage(pixels.error_m[pixels.inside], pixels.spread_m[pixels.inside])
    assert raw_1 < 0.35


def test_disagreement_term_is_chosen_where_the_blend_moved_pixels(rng) -> None:
    n = 40_000
    moved = rng.uniform(0.0, 0.5, n)
    spread = np.full(n, 0.01)
    error = np.abs(rng.standard_normal(n) * np.sqrt(0.01**2 + moved**2))
    pixels = CalibrationPixels(error, spread, np.full(n, 2.0), moved, np.ones(n, bool))
    pixels.inside[:2000] = False  # a small outside region, same law
    calibration = fit_uncertainty_calibration(pixels)
    assert calibration.inside.disagreement > 0.5


def test_round_trip_and_invalid_values() -> None:
    calibration = UncertaintyCalibration(RegionCalibration(1.5, 0.02, 0.5),
                                         RegionCalibration(2.0, 0.1, 1.0))
    assert UncertaintyCalibration.from_dict(calibration.to_dict()) == calibration
    with pytest.raises(ValueError, match="regions"):
        UncertaintyCalibration.from_dict({"inside": calibration.to_dict()["inside"]})
    with pytest.raises(ValueError, match="floor must be a finite number >= 0"):
        RegionCalibration(1.0, float("nan"), 0.0)
    with pytest.raises(ValueError, match="all 0"):
        RegionCalibration(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="need at least 1000"):
        fit_uncertainty_calibration(CalibrationPixels(*(np.ones(10),) * 4,
                                                      inside=np.ones(10, bool)))


def _frame_inputs(rng):
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    means = rng.uniform(1.0, 3.0, (8, 8)).astype(np.float32)
    frame = ZoneFrame(means, np.full((8, 8), 0.02, np.float32), np.ones((8, 8), bool))
    return image, frame


def test_estimator_applies_the_calibration_the_weights_carry(lite_model, rng) -> None:
    image, frame = _frame_inputs(rng)
    raw = DepthEstimator(lite_model, fold_batch_norms=False).predict(image, frame)
    assert not raw.uncertainty_calibrated
    calibration = UncertaintyCalibration(RegionCalibration(2.0, 0.05, 1.0),
                                         RegionCalibration(3.0, 0.1, 1.0))
    lite_model.set_output_contract(uncertainty_calibration=calibration.to_dict())
    try:
        result = DepthEstimator(lite_model, fold_batch_norms=False).predict(image, frame)
    finally:
        lite_model.set_output_contract(uncertainty_calibration=None)
    assert result.uncertainty_calibrated
    np.testing.assert_allclose(result.depth_m, raw.depth_m)
    from deltar.inference.blend import zone_grid_mask
    from deltar.inference.preprocess import resize_to_image, scale_rects

    # Computed on the network's output grid, then resized to the image.
    estimator = DepthEstimator(lite_model, fold_batch_norms=False)
    depth, spread = (m[0, 0] for m in estimator.run_network(estimator.prepare([image],
                                                                              [frame])))
    inside = zone_grid_mask(scale_rects(result.zone_rects, image.shape[:2], depth.shape),
                            depth.shape)
    assert inside.any() and (~inside).any()
    expected = np.where(inside, np.hypot(2.0 * spread, 0.05 * depth),
                        np.hypot(3.0 * spread, 0.1 * depth))
    expected = resize_to_image(expected[None, None], image.shape[:2])[0, 0]
    np.testing.assert_allclose(result.uncertainty_m, expected, rtol=1e-5)
    # uncertainty=None keeps the raw spread whatever the weights carry.
    lite_model.set_output_contract(uncertainty_calibration=calibration.to_dict())
    try:
        plain = DepthEstimator(lite_model, fold_batch_norms=False,
                               uncertainty=None).predict(image, frame)
    finally:
        lite_model.set_output_contract(uncertainty_calibration=None)
    np.testing.assert_allclose(plain.uncertainty_m, raw.uncertainty_m)
    with pytest.raises(ValueError, match="uncertainty must be"):
        DepthEstimator(lite_model, fold_batch_norms=False, uncertainty="calibrated")


def test_sigma_in_a_box_is_sigma_with_its_mask(rng) -> None:
    from deltar.inference.blend import grid_box, zone_grid_mask

    calibration = UncertaintyCalibration(inside=RegionCalibration(1.2, 0.03, 0.5),
                                         outside=RegionCalibration(2.5, 0.08, 1.0))
    spread, depth, moved = (rng.uniform(0.0, 3.0, (40, 50)).astype(np.float32)
                            for _ in range(3))
    rects = np.array([[5.5, 7.2, 20.0, 30.9], [18.0, 25.0, 33.3, 41.0]], np.float32)
    with_mask = calibration.sigma(spread, depth, moved, zone_grid_mask(rects, (40, 50)))
    with_box = calibration.sigma(spread, depth, moved, grid_box(rects, (40, 50)))
    assert with_box.dtype == np.float32
    np.testing.assert_array_equal(with_box, with_mask)
    inside = calibration.inside
    np.testing.assert_allclose(with_box[10, 10], np.sqrt((inside.spread * spread[10, 10]) ** 2
                                                         + (inside.floor * depth[10, 10]) ** 2
                                                         + (inside.disagreement
                                                            * moved[10, 10]) ** 2), rtol=1e-6)


def test_region_sigma_takes_scalars() -> None:
    region = RegionCalibration(1.5, 0.02, 0.5)
    assert np.isclose(region.sigma(0.1, 2.0, 0.2), np.sqrt(0.15 ** 2 + 0.04 ** 2 + 0.1 ** 2))
