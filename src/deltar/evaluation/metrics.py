"""Per-frame depth metrics and their average over a data set.

The definitions follow the evaluation code of the official DELTAR release (which in
turn follows BTS / AdaBins):

- ``d1``, ``d2``, ``d3``: fraction of pixels with ``max(gt / pred, pred / gt) < 1.25 ** k``.
- ``rel``: mean ``|gt - pred| / gt``; ``sq_rel``: mean ``(gt - pred) ** 2 / gt`` (metres).
- ``rmse``: root mean square of ``gt - pred`` (metres); ``rmse_log``: the same on natural
  logarithms.
- ``log10``: mean ``|log10 gt - log10 pred|``.
- ``silog``: ``100 * sqrt(mean(e ** 2) - mean(e) ** 2)`` with ``e = ln pred - ln gt``
  (the release's scale: variance of the log error, times 100, no lambda).

Only pixels whose ground truth lies strictly inside ``(min_depth, max_depth)`` count, and
predictions are clipped to ``[min_depth, max_depth]`` first, as the release does.
Metrics are computed per frame and then averaged over frames. The range bounds and the
``d`` ratios are compared in float32, as the release compares them (millimetre depths
give values that are exactly a bound or a threshold in float32, not in float64); the
other metrics are computed in float64, more accurately than the release's float32 (on
480 x 640 frames they differ by about 1e-7 relative, ``silog``, a difference of two
means, by up to about 2e-5).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

#: Names of the metrics returned by :func:`depth_metrics`, in display order.
METRIC_KEYS: tuple[str, ...] = (
    "d1", "d2", "d3", "rel", "sq_rel", "rmse", "rmse_log", "log10", "silog",
)

#: Uncertainty metrics of methods that also give a per-pixel sigma
#: (:func:`coverage_metrics`; a calibrated Gaussian sigma gives 0.683 and 0.954).
COVERAGE_KEYS: tuple[str, ...] = ("within_1sigma", "within_2sigma")

#: Metrics where higher is better (all others: lower is better).
HIGHER_IS_BETTER: frozenset[str] = frozenset({"d1", "d2", "d3"})


class EmptyFrameError(ValueError):
    """Raised when a frame has no pixel with ground truth inside the depth range."""


def _as_float_array(value: object, name: str) -> np.ndarray:
    """Convert a numpy array or torch tensor to a float64 numpy array."""
    if hasattr(value, "detach"):  # torch tensor, without importing torch here
        value = value.detach().cpu().numpy()
    array = np.asarray(value, dtype=np.float64)
    if array.size == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def _valid_pixels(gt: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """Where the ground truth lies strictly inside the range, compared in float32 as the
    release compares its float32 ground truth (0.1 m is not > 0.1 there)."""
    gt32 = gt.astype(np.float32)
    return (gt32 > np.float32(min_depth)) & (gt32 < np.float32(max_depth))


def depth_metrics(
    pred_m: np.ndarray,
    gt_m: np.ndarray,
    min_depth: float = 1e-3,
    max_depth: float = 10.0,
) -> dict[str, float]:
    """Depth metrics of one frame.

    Args:
        pred_m: predicted depth in metres, any shape, e.g. (H, W); numpy or torch.
        gt_m: ground-truth depth in metres, same shape; 0 (or anything outside the range)
            marks invalid pixels.
        min_depth: ground truth must be > ``min_depth`` metres; predictions are clipped to
            at least this value.
        max_depth: ground truth must be < ``max_depth`` metres; predictions are clipped to
            at most this value.

    Returns:
        Dict with the keys of :data:`METRIC_KEYS` (floats; distances in metres, ``silog``
        in the release's x100 scale).

    Raises:
        ValueError: shapes differ, inputs contain NaN / inf, or the depth range is invalid.
        EmptyFrameError: no pixel has ground truth inside the range.
    """
    if not (0.0 < min_depth < max_depth):
        raise ValueError(f"need 0 < min_depth < max_depth, got min_depth={min_depth}, "
                         f"max_depth={max_depth}")
    pred = _as_float_array(pred_m, "pred_m")
    gt = _as_float_array(gt_m, "gt_m")
    if pred.shape != gt.shape:
        raise ValueError(f"pred_m and gt_m must have the same shape, got {pred.shape} "
                         f"and {gt.shape}")
    valid = _valid_pixels(gt, min_depth, max_depth)
    if not np.any(valid):
        raise EmptyFrameError(f"no ground-truth pixel inside ({min_depth}, {max_depth}) m")
    gt = gt[valid]
    # Clipped to the float32 bounds, as the release clips its float32 prediction.
    pred = np.clip(pred[valid], float(np.float32(min_depth)), float(np.float32(max_depth)))

    # The release compares float32 ratios with the thresholds: a ratio such as 0.63 / 0.504,
    # just below 1.25 in float64, is exactly 1.25 in float32 and does not count.
    gt32, pred32 = gt.astype(np.float32), pred.astype(np.float32)
    ratio = np.maximum(gt32 / pred32, pred32 / gt32)
    diff = gt - pred
    log_err = np.log(pred) - np.log(gt)
    # mean(e^2) - mean(e)^2 can round to a tiny negative number for a perfect prediction.
    log_var = max(float(np.mean(log_err**2) - np.mean(log_err) ** 2), 0.0)
    return {
        "d1": float(np.mean(ratio < 1.25)),
        "d2": float(np.mean(ratio < 1.25**2)),
        "d3": float(np.mean(ratio < 1.25**3)),
        "rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean(log_err**2))),
        "log10": float(np.mean(np.abs(np.log10(gt) - np.log10(pred)))),
        "silog": 100.0 * math.sqrt(log_var),
    }


def coverage_metrics(pred_m: np.ndarray, sigma_m: np.ndarray, gt_m: np.ndarray,
                     min_depth: float = 1e-3, max_depth: float = 10.0) -> dict[str, float]:
    """Fractions of a frame's pixels whose error lies within one and two sigma.

    Args:
        pred_m: predicted depth in metres, e.g. (H, W).
        sigma_m: its per-pixel standard deviation in metres, same shape.
        gt_m: ground-truth depth in metres, same shape; pixels count as in
            :func:`depth_metrics` (ground truth inside the range).
        min_depth, max_depth: ground-truth range in metres.

    Returns:
        Dict with the keys of :data:`COVERAGE_KEYS`.

    Raises:
        ValueError: shapes differ or inputs contain NaN / inf.
        EmptyFrameError: no pixel has ground truth inside the range.
    """
    pred = _as_float_array(pred_m, "pred_m")
    sigma = _as_float_array(sigma_m, "sigma_m")
    gt = _as_float_array(gt_m, "gt_m")
    if not pred.shape == sigma.shape == gt.shape:
        raise ValueError(f"pred_m, sigma_m and gt_m must have one shape, got {pred.shape}, "
                         f"{sigma.shape} and {gt.shape}")
    valid = _valid_pixels(gt, min_depth, max_depth)
    if not np.any(valid):
        raise EmptyFrameError(f"no ground-truth pixel inside ({min_depth}, {max_depth}) m")
    error = np.abs(pred[valid] - gt[valid])
    return {"within_1sigma": float(np.mean(error <= sigma[valid])),
            "within_2sigma": float(np.mean(error <= 2 * sigma[valid]))}


class MetricAccumulator:
    """Averages per-frame metrics over frames (each frame weighs the same).

    Frames without any valid ground-truth pixel are skipped with a warning, so they never
    turn the averages into NaN.

    Example:
        >>> acc = MetricAccumulator()
        >>> for pred, gt in frames:  # doctest: +SKIP
        ...     acc.update(pred, gt)
        >>> acc.compute()  # doctest: +SKIP
    """

    def __init__(self, min_depth: float = 1e-3, max_depth: float = 10.0,
                 keys: Sequence[str] = METRIC_KEYS) -> None:
        """Args:
            min_depth, max_depth: ground-truth range in metres, see :func:`depth_metrics`.
            keys: the metrics averaged (:data:`METRIC_KEYS`, or :data:`COVERAGE_KEYS`).
        """
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.keys = tuple(keys)
        self._sums = dict.fromkeys(self.keys, 0.0)
        self.count = 0
        self.skipped = 0

    def update(self, pred_m: np.ndarray, gt_m: np.ndarray, name: str = "") -> dict | None:
        """Compute one frame's metrics and add them.

        Args:
            pred_m: predicted depth in metres, e.g. (H, W).
            gt_m: ground-truth depth in metres, same shape, 0 = invalid.
            name: frame name used in the warning when the frame is skipped.

        Returns:
            The frame's metrics, or None when the frame had no valid pixel (skipped).
        """
        try:
            frame = depth_metrics(pred_m, gt_m, self.min_depth, self.max_depth)
        except EmptyFrameError as err:
            self.skipped += 1
            label = f"frame {name!r}" if name else "a frame"
            warnings.warn(f"skipping {label}: {err}", RuntimeWarning, stacklevel=2)
            return None
        self.add(frame)
        return frame

    def add(self, frame_metrics: Mapping[str, float]) -> None:
        """Add metrics already computed for one frame (a dict with all of ``keys``)."""
        missing = set(self.keys) - set(frame_metrics)
        if missing:
            raise ValueError(f"frame_metrics is missing keys {sorted(missing)}")
        values = {key: float(frame_metrics[key]) for key in self.keys}
        bad = [key for key, value in values.items() if not math.isfinite(value)]
        if bad:
            raise ValueError(f"frame_metrics has non-finite values for {bad}")
        for key, value in values.items():
            self._sums[key] += value
        self.count += 1

    def compute(self) -> dict[str, float]:
        """Mean of each metric over the frames added so far.

        Raises:
            ValueError: no frame has been added (every frame was empty or skipped).
        """
        if self.count == 0:
            raise ValueError(f"no frame with valid ground truth to average "
                             f"({self.skipped} skipped)")
        return {key: self._sums[key] / self.count for key in self.keys}
