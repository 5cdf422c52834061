"""Depth hypotheses per zone in numpy: what the estimator feeds the network.

The numpy twins of :mod:`deltar.sensor.sampling` (whose PyTorch functions the training
data pipeline uses), for inference without PyTorch: the same ``"icdf"`` and
``"uniform"`` samplings of N(mean, sigma) and the same histogram quantiles, equal to
them within float32 rounding (tested). Invalid zones get all-zero hypotheses.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import erfinv

from deltar.contract import HYPOTHESIS_SAMPLINGS

if TYPE_CHECKING:
    from deltar.sensor.zone_frame import ZoneFrame

#: Lowest and highest probability used for inverse-CDF sampling (the release's values).
ICDF_PROBABILITY_MARGIN = 1e-3

__all__ = ["ICDF_PROBABILITY_MARGIN", "frame_hypotheses", "icdf_probabilities",
           "zone_hypotheses", "zone_hypotheses_from_histogram"]


def icdf_probabilities(num_samples: int) -> np.ndarray:
    """(K,) float64 probabilities evenly spaced from 1e-3 to 1 - 1e-3."""
    _check_num_samples(num_samples)
    margin = ICDF_PROBABILITY_MARGIN
    return np.linspace(margin, 1.0 - margin, int(num_samples), dtype=np.float64)


def zone_hypotheses(mean_m: np.ndarray, sigma_m: np.ndarray, valid: np.ndarray,
                    num_samples: int = 16, method: str = "icdf") -> np.ndarray:
    """Sample depth hypotheses from each zone's Gaussian.

    Args:
        mean_m: (..., Z) zone means in metres.
        sigma_m: (..., Z) zone standard deviations in metres (>= 0 in valid zones; a
            sigma of 0 gives ``K`` copies of the mean).
        valid: (..., Z) bool, zones that carry a measurement.
        num_samples: K, hypotheses per zone.
        method: ``"icdf"`` (Gaussian quantiles at :func:`icdf_probabilities`) or
            ``"uniform"`` (K values evenly spaced over mean +- 3 sigma).

    Returns:
        (..., Z, K) float32 metres, increasing along K, clamped at 0 m (no negative
        distance); zeros for invalid zones.

    Raises:
        ValueError: unknown method, shapes that differ, a ``valid`` that is not bool,
            NaN/inf or negative sigma in a valid zone.
    """
    if method not in HYPOTHESIS_SAMPLINGS:
        raise ValueError(f"method must be one of {HYPOTHESIS_SAMPLINGS}, got {method!r}")
    _check_num_samples(num_samples)
    mean = np.asarray(mean_m, dtype=np.float32)
    sigma = np.asarray(sigma_m, dtype=np.float32)
    valid = np.asarray(valid)
    if mean.ndim < 1:
        raise ValueError(f"mean_m must have shape (..., Z), got {mean.shape}")
    if sigma.shape != mean.shape:
        raise ValueError(f"sigma_m has shape {sigma.shape}, expected {mean.shape} like mean_m")
    if valid.dtype != bool or valid.shape != mean.shape:
        raise ValueError(f"valid must be a bool array of shape {mean.shape}, got "
                         f"{valid.dtype} {valid.shape}")
    if not np.isfinite(mean[valid]).all() or not np.isfinite(sigma[valid]).all():
        raise ValueError("mean_m and sigma_m must be finite in valid zones")
    if (sigma[valid] < 0).any():
        raise ValueError("sigma_m must be >= 0 in valid zones")
    # Invalid zones may hold anything (NaN included); compute on zeros there.
    mean = np.where(valid, mean, np.float32(0.0))
    sigma = np.where(valid, sigma, np.float32(0.0))
    if method == "icdf":
        # Standard-normal quantiles, in float64, then float32 as the means.
        steps = (erfinv(2 * icdf_probabilities(num_samples) - 1) * math.sqrt(2))
    else:
        steps = np.linspace(-3.0, 3.0, int(num_samples), dtype=np.float64)
    samples = mean[..., None] + sigma[..., None] * steps.astype(np.float32)
    # A hypothesis is a distance: a wide zone near the sensor (sigma > mean / 3) would
    # otherwise get negative samples, which the network rejects.
    samples = np.maximum(samples, np.float32(0.0))
    return np.where(valid[..., None], samples, np.float32(0.0)).astype(np.float32)


def zone_hypotheses_from_histogram(edges_m: np.ndarray, counts: np.ndarray,
                                   valid: np.ndarray, num_samples: int = 16) -> np.ndarray:
    """Inverse-CDF hypotheses from per-zone histograms.

    Each zone's histogram is read as a piecewise-uniform density over the bins; the
    hypotheses are its quantiles at :func:`icdf_probabilities`, so they never fall into
    an empty bin.

    Args:
        edges_m: (bins + 1,) strictly increasing bin edges in metres.
        counts: (..., Z, bins) non-negative counts.
        valid: (..., Z) bool; zones whose counts sum to 0 are treated as invalid too.
        num_samples: K, hypotheses per zone.

    Returns:
        (..., Z, K) float32 metres; zeros for invalid zones.

    Raises:
        ValueError: wrong shapes, non-increasing edges, negative or non-finite counts.
    """
    _check_num_samples(num_samples)
    edges = np.asarray(edges_m, dtype=np.float64)
    weights = np.asarray(counts, dtype=np.float64)
    valid = np.asarray(valid)
    if edges.ndim != 1 or edges.size < 2 or not (np.diff(edges) > 0).all():
        raise ValueError(f"edges_m must be 1-D and strictly increasing, got shape "
                         f"{edges.shape}")
    bins = edges.size - 1
    if weights.ndim < 2 or weights.shape[-1] != bins:
        raise ValueError(f"counts must have shape (..., Z, {bins}) to match edges_m, got "
                         f"{weights.shape}")
    if valid.dtype != bool or valid.shape != weights.shape[:-1]:
        raise ValueError(f"valid must be a bool array of shape {weights.shape[:-1]}, got "
                         f"{valid.dtype} {valid.shape}")
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise ValueError("counts must be finite and >= 0")
    total = weights.sum(-1, keepdims=True)
    usable = valid & (total[..., 0] > 0)
    cdf = np.cumsum(weights, -1) / np.where(total > 0, total, 1.0)
    cdf = np.concatenate([np.zeros((*cdf.shape[:-1], 1)), cdf], axis=-1)  # at the edges
    probs = icdf_probabilities(num_samples)
    flat_cdf = cdf.reshape(-1, bins + 1)
    # Bin i holds probability p when cdf[i] <= p < cdf[i + 1]; empty bins hold none.
    index = np.stack([np.searchsorted(row, probs, side="right") for row in flat_cdf])
    index = np.clip(index - 1, 0, bins - 1).reshape(*cdf.shape[:-1], -1)
    lower = np.take_along_axis(cdf, index, -1)
    mass = np.take_along_axis(cdf, index + 1, -1) - lower
    fraction = np.where(mass > 0, (probs - lower) / np.where(mass > 0, mass, 1.0), 0.5)
    samples = edges[index] + np.clip(fraction, 0.0, 1.0) * (edges[index + 1] - edges[index])
    samples = np.where(usable[..., None], samples, 0.0)
    return samples.astype(np.float32)


def frame_hypotheses(frame: ZoneFrame, num_samples: int = 16, method: str = "icdf",
                     from_histogram: bool = False) -> np.ndarray:
    """One frame's hypotheses as a network's input contract asks for them.

    Args:
        frame: the zone frame.
        num_samples: K, hypotheses per zone.
        method: sampling of N(mean, sigma) (:func:`zone_hypotheses`).
        from_histogram: draw them from the frame's per-zone histograms when it carries
            them (:func:`zone_hypotheses_from_histogram`; the network's
            ``histogram_hypotheses``); otherwise, and for frames without histograms,
            from each zone's mean and sigma.

    Returns:
        (Z, K) float32 metres (Z = grid * grid, row-major); zeros for invalid zones.
    """
    mean, sigma, valid = frame.flat()
    if from_histogram and frame.hist_counts is not None:
        counts = frame.hist_counts.reshape(frame.zone_count, -1)
        return zone_hypotheses_from_histogram(frame.hist_edges_m, counts, valid, num_samples)
    return zone_hypotheses(mean, sigma, valid, num_samples, method)


def _check_num_samples(num_samples: int) -> None:
    if int(num_samples) != num_samples or num_samples < 2:
        raise ValueError(f"num_samples must be an integer >= 2, got {num_samples}")
