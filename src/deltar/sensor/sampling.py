"""Depth hypotheses per zone: the samples DELTAR's distribution encoder reads.

Each zone's depth distribution is turned into ``K`` depth values (metres):

* ``"icdf"`` (probability-driven): quantiles of N(mean, sigma) at ``K`` probabilities
  evenly spaced from 1e-3 to 1 - 1e-3 (what the released network was run with);
* ``"uniform"``: ``K`` values evenly spaced over mean +- 3 sigma (the release's training
  configuration);
* from a per-zone histogram: quantiles of the piecewise-uniform density the histogram
  describes, at the same probabilities as ``"icdf"``.

Invalid zones get all-zero hypotheses.
"""

from __future__ import annotations

import math

import torch

from deltar.contract import HYPOTHESIS_SAMPLINGS
from deltar.sensor.hypotheses import ICDF_PROBABILITY_MARGIN, _check_num_samples

# ICDF_PROBABILITY_MARGIN and the K check live in the torch-free numpy twins
# (deltar.sensor.hypotheses), so that both samplings share them.
__all__ = ["ICDF_PROBABILITY_MARGIN", "icdf_probabilities", "sample_hypotheses",
           "sample_hypotheses_from_histogram"]


def icdf_probabilities(num_samples: int, dtype: torch.dtype = torch.float32,
                       device: torch.device | str | None = None) -> torch.Tensor:
    """The ``num_samples`` probabilities evenly spaced from 1e-3 to 1 - 1e-3, shape (K,)."""
    _check_num_samples(num_samples)
    margin = ICDF_PROBABILITY_MARGIN
    probs = torch.linspace(margin, 1.0 - margin, num_samples, dtype=torch.float64)
    return probs.to(dtype=dtype, device=device)


def sample_hypotheses(mean_m: torch.Tensor, sigma_m: torch.Tensor, valid: torch.Tensor,
                      num_samples: int = 16, method: str = "icdf") -> torch.Tensor:
    """Sample depth hypotheses from each zone's Gaussian.

    Args:
        mean_m: (..., Z) zone means in metres.
        sigma_m: (..., Z) zone standard deviations in metres (>= 0 in valid zones; a
            sigma of 0 gives ``K`` copies of the mean).
        valid: (..., Z) bool, zones that carry a measurement.
        num_samples: K, hypotheses per zone.
        method: ``"icdf"`` (Gaussian quantiles) or ``"uniform"`` (mean +- 3 sigma).

    Returns:
        (..., Z, K) tensor in metres, in ``mean_m``'s float dtype and device, increasing
        along K, clamped at 0 m (no negative distance); zeros for invalid zones.

    Raises:
        ValueError: unknown method, shapes that differ, NaN/inf or negative sigma in a
            valid zone.
    """
    if method not in HYPOTHESIS_SAMPLINGS:
        raise ValueError(f"method must be one of {HYPOTHESIS_SAMPLINGS}, got {method!r}")
    _check_num_samples(num_samples)
    mean, sigma, valid = _check_zone_inputs(mean_m, sigma_m, valid)
    if not torch.isfinite(mean[valid]).all() or not torch.isfinite(sigma[valid]).all():
        raise ValueError("mean_m and sigma_m must be finite in valid zones")
    if (sigma[valid] < 0).any():
        raise ValueError("sigma_m must be >= 0 in valid zones")
    # Invalid zones may hold anything (NaN included); compute on zeros there.
    mean = torch.where(valid, mean, torch.zeros_like(mean))
    sigma = torch.where(valid, sigma, torch.zeros_like(sigma))
    if method == "icdf":
        probs = icdf_probabilities(num_samples, mean.dtype, mean.device)
        # Standard-normal quantiles, the same expression torch.distributions.Normal.icdf uses.
        z = torch.erfinv(2 * probs - 1) * math.sqrt(2)
        samples = mean[..., None] + sigma[..., None] * z
    else:
        offsets = torch.linspace(-3.0, 3.0, num_samples, dtype=mean.dtype, device=mean.device)
        samples = mean[..., None] + sigma[..., None] * offsets
    # A hypothesis is a distance: a wide zone near the sensor (sigma > mean / 3) would
    # otherwise get negative samples, which the network rejects.
    samples = samples.clamp_min(0.0)
    return torch.where(valid[..., None], samples, torch.zeros_like(samples))


def sample_hypotheses_from_histogram(edges_m: torch.Tensor, counts: torch.Tensor,
                                     valid: torch.Tensor,
                                     num_samples: int = 16) -> torch.Tensor:
    """Inverse-CDF hypotheses from per-zone histograms.

    Each zone's histogram is read as a piecewise-uniform density over the bins; the
    hypotheses are its quantiles at ``icdf_probabilities(K)``, so they never fall into
    an empty bin.

    Args:
        edges_m: (bins + 1,) strictly increasing bin edges in metres.
        counts: (..., Z, bins) non-negative counts.
        valid: (..., Z) bool; zones whose counts sum to 0 are treated as invalid too.
        num_samples: K, hypotheses per zone.

    Returns:
        (..., Z, K) float32 tensor in metres (float64 when ``counts`` is float64);
        zeros for invalid zones.

    Raises:
        ValueError: wrong shapes, non-increasing edges, negative or non-finite counts.
    """
    _check_num_samples(num_samples)
    counts = torch.as_tensor(counts)
    dtype = torch.float64 if counts.dtype == torch.float64 else torch.float32
    edges = torch.as_tensor(edges_m, device=counts.device).to(torch.float64)
    valid = torch.as_tensor(valid, device=counts.device)
    if edges.ndim != 1 or edges.numel() < 2 or not (torch.diff(edges) > 0).all():
        raise ValueError(f"edges_m must be 1-D and strictly increasing, got shape "
                         f"{tuple(edges.shape)}")
    bins = edges.numel() - 1
    if counts.ndim < 2 or counts.shape[-1] != bins:
        raise ValueError(f"counts must have shape (..., Z, {bins}) to match edges_m, got "
                         f"{tuple(counts.shape)}")
    if valid.dtype != torch.bool or valid.shape != counts.shape[:-1]:
        raise ValueError(f"valid must be a bool tensor of shape {tuple(counts.shape[:-1])}, "
                         f"got {valid.dtype} {tuple(valid.shape)}")
    weights = counts.to(torch.float64)
    if not torch.isfinite(weights).all() or (weights < 0).any():
        raise ValueError("counts must be finite and >= 0")
    total = weights.sum(-1, keepdim=True)
    usable = valid & (total[..., 0] > 0)
    cdf = torch.cumsum(weights, -1) / torch.where(total > 0, total, torch.ones_like(total))
    cdf = torch.nn.functional.pad(cdf, (1, 0), value=0.0)  # (..., Z, bins + 1), at the edges
    probs = icdf_probabilities(num_samples, torch.float64, counts.device)
    probs = probs.expand(*cdf.shape[:-1], num_samples).contiguous()
    # Bin i holds probability p when cdf[i] <= p < cdf[i + 1]; empty bins hold none.
    index = (torch.searchsorted(cdf.contiguous(), probs, right=True) - 1).clamp(0, bins - 1)
    lower = torch.gather(cdf, -1, index)
    mass = torch.gather(cdf, -1, index + 1) - lower
    fraction = torch.where(mass > 0, (probs - lower) / torch.where(mass > 0, mass, 1.0), 0.5)
    samples = edges[index] + fraction.clamp(0.0, 1.0) * (edges[index + 1] - edges[index])
    samples = torch.where(usable[..., None], samples, torch.zeros_like(samples))
    return samples.to(dtype)


def _check_zone_inputs(mean_m, sigma_m, valid) -> tuple[torch.Tensor, ...]:
    mean = torch.as_tensor(mean_m)
    if not mean.is_floating_point():
        mean = mean.to(torch.float32)
    sigma = torch.as_tensor(sigma_m, device=mean.device).to(mean.dtype)
    valid = torch.as_tensor(valid, device=mean.device)
    if mean.ndim < 1:
        raise ValueError(f"mean_m must have shape (..., Z), got {tuple(mean.shape)}")
    if sigma.shape != mean.shape:
        raise ValueError(f"sigma_m has shape {tuple(sigma.shape)}, expected "
                         f"{tuple(mean.shape)} like mean_m")
    if valid.dtype != torch.bool or valid.shape != mean.shape:
        raise ValueError(f"valid must be a bool tensor of shape {tuple(mean.shape)}, got "
                         f"{valid.dtype} {tuple(valid.shape)}")
    return mean, sigma, valid
