"""CNH (compact normalised histograms) -> ZoneFrame histograms, and the sampler on them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.inference.estimator import DepthEstimator
from deltar.sensor.cnh import (
    DEVICE_BIN_M,
    CNHConfig,
    histogram_sigma_m,
    normalize_cnh,
    simulate_cnh,
    zone_frame_from_cnh,
)
from deltar.sensor.hypotheses import zone_hypotheses
from deltar.sensor.sampling import icdf_probabilities, sample_hypotheses_from_histogram
from deltar.sensor.zone_frame import Orientation
from tests.inference.fakes import ZonePainterNet


def _peaked_cnh(peak_bins: np.ndarray, bins: int = 18, rng=None) -> np.ndarray:
    """(Z, bins) CNH values: a two-bin peak at each zone's bin plus small negative noise."""
    rng = rng or np.random.default_rng(0)
    values = rng.uniform(-0.02, 0.01, size=(peak_bins.size, bins))
    rows = np.arange(peak_bins.size)
    values[rows, peak_bins] += 3.0
    values[rows, np.minimum(peak_bins + 1, bins - 1)] += 1.0
    return values


def test_config_edges_follow_start_bin_and_sub_sample():
    cfg = CNHConfig(start_bin=4, num_bins=3, sub_sample=2, device_bin_m=0.05)
    np.testing.assert_allclose(cfg.edges_m(), [0.2, 0.3, 0.4, 0.5])
    assert cfg.bin_width_m == pytest.approx(0.1)
    assert cfg.range_m == pytest.approx((0.2, 0.5))
    default = CNHConfig()
    assert default.num_bins == 18 and default.range_m[1] == pytest.approx(126 * DEVICE_BIN_M)


def test_config_from_range_rounds_to_device_bins():
    cfg = CNHConfig.from_range(0.3, 4.0, 16, device_bin_m=0.0375)
    assert cfg.start_bin == 8 and cfg.num_bins == 16
    assert cfg.sub_sample == 7  # (4.0 - 0.3) / 16 bins = 6.2 device bins, rounded up
    near, far = cfg.range_m
    assert near == pytest.approx(0.3) and far >= 4.0
    with pytest.raises(ValueError, match="near < far"):
        CNHConfig.from_range(2.0, 1.0, 8)


@pytest.mark.parametrize("field, value", [("num_bins", 0), ("sub_sample", 1.5),
                                          ("start_bin", -1), ("device_bin_m", 0.0)])
def test_config_rejects_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        CNHConfig(**{field: value})


def test_normalize_clips_negatives_and_sums_to_one():
    values = np.array([[-1.0, 2.0, 6.0], [-1.0, -2.0, 0.0]])
    out = normalize_cnh(values, zones=2, num_bins=3)
    np.testing.assert_allclose(out[0], [0.0, 0.25, 0.75])
    assert np.all(out[1] == 0)  # nothing positive: stays empty
    with pytest.raises(ValueError, match="expected 2 zones x 4 bins"):
        normalize_cnh(values, zones=2, num_bins=4)
    with pytest.raises(ValueError, match="NaN"):
        normalize_cnh([[np.nan, 1.0, 1.0]], zones=1, num_bins=3)


def test_zone_frame_from_cnh_masks_stale_zones_and_orients():
    rng = np.random.default_rng(1)
    peaks = rng.integers(1, 16, size=64)
    cfg = CNHConfig()
    centres = (cfg.edges_m()[peaks] + cfg.edges_m()[peaks + 1]) / 2
    distance_mm = centres * 1000.0
    targets = np.ones(64, dtype=int)
    targets[[3, 40]] = 0  # no target: stale distance left by the sensor
    frame = zone_frame_from_cnh(distance_mm, _peaked_cnh(peaks, rng=rng), config=cfg,
                                nb_target_detected=targets,
                                orientation=Orientation(rot90=1), timestamp_s=2.5)
    assert frame.grid == 8 and frame.hist_counts.shape == (8, 8, 18)
    assert frame.sensor_model == "VL53L8CH" and frame.timestamp_s == 2.5
    np.testing.assert_allclose(frame.hist_counts.sum(-1), 1.0, atol=1e-6)
    assert np.all(frame.hist_counts >= 0)
    # Orientation applies to every per-zone array alike: compare against rot90 by hand.
    expected_valid = np.rot90(targets.reshape(8, 8) > 0, k=1)
    np.testing.assert_array_equal(frame.valid, expected_valid)
    # No target detected: the zones report no target, oriented like the rest.
    np.testing.assert_array_equal(frame.no_target, ~expected_valid)
    expected_mean = np.rot90((distance_mm / 1000).reshape(8, 8), k=1)
    np.testing.assert_allclose(frame.mean_m[frame.valid], expected_mean[frame.valid], rtol=1e-6)
    assert np.all(frame.mean_m[~frame.valid] == 0)
    # Sigma from the strongest run (a 3:1 two-bin peak): positive and under one bin width.
    assert np.all(frame.sigma_m[frame.valid] > 0)
    assert np.all(frame.sigma_m[frame.valid] < cfg.bin_width_m)


def test_zone_frame_from_cnh_errors_name_the_field():
    with pytest.raises(ValueError, match="expected 64 zones x 18 bins"):
        zone_frame_from_cnh(np.full(64, 1000.0), np.ones((64, 17)))
    with pytest.raises(ValueError, match="nb_target_detected has 16 entries"):
        zone_frame_from_cnh(np.full(64, 1000.0), np.ones((64, 18)),
                            nb_target_detected=np.ones(16))
    with pytest.raises(ValueError, match=r"16 \(4x4\) or 64"):
        zone_frame_from_cnh(np.full(10, 1000.0), np.ones((10, 18)))



@pytest.mark.parametrize("field", ["distance_mm", "nb_target_detected", "range_sigma_mm",
                                   "target_status"])
def test_zone_frame_from_cnh_refuses_strings_and_booleans(field):
    """A THDR3K tof.json with "1500" strings read as numbers (and true as 1) before."""
    fields = {"distance_mm": [1000.0] * 64, "nb_target_detected": [1] * 64,
              "range_sigma_mm": [20.0] * 64, "target_status": [5] * 64}
    for bad in (["1500"] * 64, [True] * 64):
        with pytest.raises(ValueError, match=f"{field} must hold numbers"):
            zone_frame_from_cnh(bin_values=np.ones((64, 18)), **{**fields, field: bad})

def test_histogram_sigma_single_bin_is_uniform_spread():
    edges = np.array([0.0, 0.1, 0.2, 0.3])
    sigma = histogram_sigma_m(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]), edges)
    assert sigma[0] == pytest.approx(0.1 / np.sqrt(12))
    assert sigma[1] == 0.0


def test_sampler_reads_cnh_shaped_histograms_end_to_end():
    """18-bin CNH -> ZoneFrame -> estimator hypotheses: quantiles of the CNH density."""
    rng = np.random.default_rng(2)
    peaks = rng.integers(0, 17, size=64)
    cfg = CNHConfig()
    values = _peaked_cnh(peaks, rng=rng)
    frame = zone_frame_from_cnh(np.full(64, 1500.0), values, config=cfg)
    net = ZonePainterNet()
    net.contract_values["histogram_hypotheses"] = True  # weights trained on histograms
    hypotheses = DepthEstimator(net, weights="painter").hypotheses_for(frame)  # (64, 16)
    assert hypotheses.shape == (64, 16)
    # Independent reference: invert the piecewise-uniform CDF of each clipped histogram.
    edges = cfg.edges_m()
    probs = icdf_probabilities(16, torch.float64).numpy()
    clipped = np.clip(values, 0, None)
    for zone in range(64):
        cdf = np.concatenate([[0.0], np.cumsum(clipped[zone]) / clipped[zone].sum()])
        expected = np.interp(probs, cdf, edges)
        np.testing.assert_allclose(hypotheses[zone], expected, atol=1e-5)
        # The central hypotheses lie in the peak (bins peak, peak + 1), not in the noise.
        central = hypotheses[zone][2:-2]
        assert np.all((central >= edges[peaks[zone]]) &
                      (central <= edges[min(peaks[zone] + 2, 18)]))
    # The sampler's own entry point agrees with the estimator's.
    direct = sample_hypotheses_from_histogram(torch.from_numpy(frame.hist_edges_m),
                                              torch.from_numpy(frame.hist_counts.reshape(64, 18)),
                                              torch.from_numpy(frame.valid.reshape(-1)), 16)
    np.testing.assert_allclose(direct.numpy(), hypotheses, atol=1e-6)


def test_estimator_reads_cnh_frames_by_their_mean_and_sigma_unless_trained_on_histograms():
    """Weights that do not say they were trained on histograms (the bundled ones, the
    release) get the Gaussian hypotheses of the frame's reported mean and sigma; the
    argument overrides what the weights say either way."""
    rng = np.random.default_rng(5)
    frame = zone_frame_from_cnh(np.full(64, 1500.0), _peaked_cnh(rng.integers(0, 17, 64),
                                                                 rng=rng))
    mean, sigma, valid = frame.flat()
    gaussian = zone_hypotheses(mean, sigma, valid, 16, "icdf")
    net = ZonePainterNet()
    np.testing.assert_array_equal(DepthEstimator(net, weights="p").hypotheses_for(frame),
                                  gaussian)
    from_histogram = DepthEstimator(net, weights="p",
                                    histogram_hypotheses=True).hypotheses_for(frame)
    assert np.abs(from_histogram - gaussian).max() > 0.05
    net.contract_values["histogram_hypotheses"] = True
    np.testing.assert_array_equal(DepthEstimator(net, weights="p").hypotheses_for(frame),
                                  from_histogram)
    np.testing.assert_array_equal(DepthEstimator(net, weights="p", histogram_hypotheses=False)
                                  .hypotheses_for(frame), gaussian)


def test_simulate_cnh_puts_a_flat_wall_in_its_bin():
    cfg = CNHConfig(start_bin=2, num_bins=10, sub_sample=4, device_bin_m=0.05)  # 0.1..2.1 m
    depth = np.full((40, 40), 1.25, dtype=np.float32)
    depth[:, 20:] = 0.05  # nearer than the first bin: not counted
    rects = np.array([[0, 0, 20, 20], [0, 20, 20, 40]], dtype=np.float32)
    hist = simulate_cnh(depth, rects, cfg)
    assert hist.shape == (2, 10)
    edges = cfg.edges_m()
    wall_bin = np.searchsorted(edges, 1.25) - 1
    expected = np.zeros(10)
    expected[wall_bin] = 1.0
    np.testing.assert_allclose(hist[0], expected)
    assert np.all(hist[1] == 0)
