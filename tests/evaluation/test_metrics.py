"""Depth metrics against values worked out by hand on tiny arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from deltar.evaluation.metrics import (
    COVERAGE_KEYS,
    METRIC_KEYS,
    EmptyFrameError,
    MetricAccumulator,
    coverage_metrics,
    depth_metrics,
)


def test_hand_computed_values() -> None:
    # The 0.0 pixel is invalid ground truth and must be ignored.
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])
    pred = np.array([[1.0, 2.5], [2.0, 3.0]])
    m = depth_metrics(pred, gt)
    # Ratios max(gt/pred, pred/gt): 1, 1.25, 2.
    assert m["d1"] == pytest.approx(1 / 3)  # 1.25 is not < 1.25
    assert m["d2"] == pytest.approx(2 / 3)  # 1.25 < 1.5625 <= 2
    assert m["d3"] == pytest.approx(2 / 3)  # 2 > 1.953125
    assert m["rel"] == pytest.approx((0 + 0.5 / 2 + 2 / 4) / 3)
    assert m["sq_rel"] == pytest.approx((0 + 0.25 / 2 + 4 / 4) / 3)
    assert m["rmse"] == pytest.approx(math.sqrt((0 + 0.25 + 4) / 3))
    e = [0.0, math.log(1.25), math.log(0.5)]
    assert m["rmse_log"] == pytest.approx(math.sqrt(sum(x * x for x in e) / 3))
    assert m["log10"] == pytest.approx((0 + math.log10(1.25) + math.log10(2)) / 3)
    mean_e = sum(e) / 3
    assert m["silog"] == pytest.approx(100 * math.sqrt(sum(x * x for x in e) / 3 - mean_e**2))
    assert set(m) == set(METRIC_KEYS)


def test_delta_thresholds_compare_float32_ratios_as_the_release() -> None:
    # Millimetre depths (float32, as the files and the predictions are): 0.63 / 0.504 is
    # just below 1.25 in float64 but exactly 1.25 in float32, where the release compares
    # it, so that pixel is not within 1.25. Likewise 0.8 / 0.512 (1.5625) and
    # 1.5 / 0.768 (1.953125).
    gt = np.array([0.504, 0.512, 0.768], dtype=np.float32)
    pred = np.array([0.63, 0.8, 1.5], dtype=np.float32)
    assert np.all(np.maximum(gt / pred.astype(np.float64), pred / gt.astype(np.float64))
                  < [1.25, 1.5625, 1.953125])
    ratio = np.maximum(gt / pred, pred / gt)
    np.testing.assert_array_equal(ratio, np.float32([1.25, 1.5625, 1.953125]))
    m = depth_metrics(pred, gt)
    assert m["d1"] == 0.0
    assert m["d2"] == pytest.approx(1 / 3)
    assert m["d3"] == pytest.approx(2 / 3)


def test_perfect_prediction() -> None:
    gt = np.array([0.5, 1.0, 3.0, 7.0])
    m = depth_metrics(gt.copy(), gt)
    assert m["d1"] == m["d2"] == m["d3"] == 1.0
    for key in ("rel", "sq_rel", "rmse", "rmse_log", "log10", "silog"):
        assert m[key] == pytest.approx(0.0, abs=1e-6)


def test_silog_ignores_global_scale() -> None:
    gt = np.array([1.0, 2.0, 3.0])
    m = depth_metrics(2 * gt, gt)
    assert m["silog"] == pytest.approx(0.0, abs=1e-5)
    assert m["rmse_log"] == pytest.approx(math.log(2))


def test_range_and_clipping() -> None:
    # gt 12 m is outside (1e-3, 10) and ignored; predictions clip to [1e-3, 10].
    gt = np.array([5.0, 12.0, 2.0])
    pred = np.array([20.0, 1.0, 0.0])
    m = depth_metrics(pred, gt)
    # Remaining pairs: (gt 5, pred 10), (gt 2, pred 1e-3).
    assert m["rel"] == pytest.approx((5 / 5 + (2 - 1e-3) / 2) / 2)
    assert m["d3"] == 0.0


def test_range_bounds_compare_in_float32_as_the_release() -> None:
    # Ground truth is float32 and the release compares it with the bounds in float32:
    # a pixel at exactly 0.1 m (float32) is not > 0.1, although 0.1000000015 > 0.1 in
    # float64. It is left out, so only the exact pixel at 1 m counts.
    gt = np.array([0.1, 1.0], dtype=np.float32)
    pred = np.array([1.0, 1.0], dtype=np.float32)
    assert depth_metrics(pred, gt, min_depth=0.1, max_depth=3.0)["rel"] == 0.0
    sigma = np.array([0.5, 0.5], dtype=np.float32)
    assert coverage_metrics(pred, sigma, gt, min_depth=0.1)["within_1sigma"] == 1.0
    # Likewise the upper bound: 0.7 m in float32 (0.69999999) is not < 0.7 in float32.
    gt = np.array([0.7, 0.5], dtype=np.float32)
    assert depth_metrics(np.float32([0.5, 0.5]), gt, max_depth=0.7)["rel"] == 0.0


def test_custom_range() -> None:
    gt = np.array([0.5, 1.5, 2.5])
    pred = np.array([1.0, 1.5, 2.5])
    assert depth_metrics(pred, gt, min_depth=1.0, max_depth=3.0)["rel"] == 0.0


def test_accepts_torch_tensors() -> None:
    gt = torch.tensor([1.0, 2.0])
    pred = torch.tensor([1.0, 4.0])
    assert depth_metrics(pred, gt)["rel"] == pytest.approx(0.5)


@pytest.mark.parametrize("bad", ["pred", "gt"])
def test_nan_raises(bad: str) -> None:
    gt = np.array([1.0, 2.0])
    pred = np.array([1.0, 2.0])
    (pred if bad == "pred" else gt)[0] = np.nan
    with pytest.raises(ValueError, match=f"{bad}_m"):
        depth_metrics(pred, gt)


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="same shape"):
        depth_metrics(np.ones((2, 3)), np.ones((3, 2)))


def test_bad_range_raises() -> None:
    with pytest.raises(ValueError, match="min_depth"):
        depth_metrics(np.ones(2), np.ones(2), min_depth=5.0, max_depth=1.0)


def test_empty_frame_raises() -> None:
    with pytest.raises(EmptyFrameError):
        depth_metrics(np.ones((2, 2)), np.zeros((2, 2)))


def test_accumulator_averages_per_frame_then_over_frames() -> None:
    acc = MetricAccumulator()
    # Frame 1: one pixel, rel 1. Frame 2: three exact pixels, rel 0.
    acc.update(np.array([2.0]), np.array([1.0]))
    acc.update(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]))
    result = acc.compute()
    # Per-frame mean: (1 + 0) / 2; pooling pixels would give 1 / 4.
    assert result["rel"] == pytest.approx(0.5)
    assert result["d1"] == pytest.approx(0.5)
    assert acc.count == 2


def test_accumulator_skips_empty_frames_with_warning() -> None:
    acc = MetricAccumulator()
    acc.update(np.array([2.0]), np.array([1.0]))
    with pytest.warns(RuntimeWarning, match="skipping frame 'empty'"):
        assert acc.update(np.array([1.0]), np.array([0.0]), name="empty") is None
    assert acc.skipped == 1 and acc.count == 1
    assert acc.compute()["rel"] == pytest.approx(1.0)
    assert all(math.isfinite(v) for v in acc.compute().values())


def test_accumulator_without_frames_raises() -> None:
    with pytest.raises(ValueError, match="no frame"):
        MetricAccumulator().compute()


def test_accumulator_add_rejects_incomplete_dict() -> None:
    with pytest.raises(ValueError, match="missing keys"):
        MetricAccumulator().add({"d1": 1.0})


def test_coverage_counts_errors_within_one_and_two_sigma() -> None:
    gt = np.array([[1.0, 2.0, 3.0, 4.0, 0.0]])
    pred = np.array([[1.05, 2.15, 3.5, 4.0, 9.0]])  # errors 0.05, 0.15, 0.5, 0, (invalid)
    sigma = np.full_like(gt, 0.1)
    metrics = coverage_metrics(pred, sigma, gt)
    assert metrics == {"within_1sigma": pytest.approx(0.5), "within_2sigma": pytest.approx(0.75)}
    accumulator = MetricAccumulator(keys=COVERAGE_KEYS)
    accumulator.add(metrics)
    accumulator.add({"within_1sigma": 1.0, "within_2sigma": 1.0})
    assert accumulator.compute()["within_1sigma"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="one shape"):
        coverage_metrics(pred, sigma[:, :2], gt)
    with pytest.raises(EmptyFrameError):
        coverage_metrics(pred, sigma, np.zeros_like(gt))
