"""Fitting the confidence blend's coefficients on pixels with ground truth.

:func:`fit_confidence_blend` fits the two :class:`~deltar.inference.blend.RegionBlend`
of a :class:`~deltar.inference.blend.ConfidenceBlend` (inside the zone grid and beyond
it) to pixels sampled from a model's training scenes (:class:`BlendPixels`,
gathered by :mod:`deltar.evaluation.uncertainty`; ``deltar fit-uncertainty`` runs it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deltar.inference.blend import (
    ConfidenceBlend,
    RegionBlend,
    blend_weight,
    log_relative_spread,
    mix_log_depth,
)


@dataclass
class BlendPixels:
    """Pixels of frames with ground truth, for :func:`fit_confidence_blend` (and, blended,
    for the uncertainty calibration).

    Every array is (N,) float64 (``inside`` bool): the ground truth, the network's depth,
    the fill, the network's spread (all metres) and whether the pixel lies inside the
    zone grid's bounding box.
    """

    truth_m: np.ndarray
    network_m: np.ndarray
    fill_m: np.ndarray
    spread_m: np.ndarray
    inside: np.ndarray

    def blended(self, blend: ConfidenceBlend) -> np.ndarray:
        """(N,) float32 blended depth in metres, as
        :func:`~deltar.inference.blend.blend_with_fill` gives it."""
        weight = blend_weight(self.network_m, self.spread_m, self.inside, blend)
        return mix_log_depth(self.network_m.astype(np.float32), self.fill_m.astype(np.float32),
                             weight)


#: Log-depth error (about 1 %) below which the fit's loss turns from absolute to squared:
#: a smooth stand-in for the mean relative error.
_FIT_SMOOTHING = 0.01
#: Starting points of the fit: the network alone, an even mix, the fill alone.
_FIT_STARTS = ((4.0, 0.0), (0.0, -1.0), (-4.0, 0.0))


def _fit_region_blend(pixels: BlendPixels, mask: np.ndarray, min_pixels: int,
                      region: str, objective: str) -> RegionBlend:
    from scipy.optimize import minimize  # scipy: on use

    count = int(mask.sum())
    if count < min_pixels:
        raise ValueError(f"{count} pixels with ground truth {region} the zone grid, need at "
                         f"least {min_pixels}: give more frames with ground truth")
    log_spread = log_relative_spread(pixels.network_m[mask], pixels.spread_m[mask])
    log_network = np.log(np.maximum(pixels.network_m[mask], 1e-6))
    log_fill = np.log(np.maximum(pixels.fill_m[mask], 1e-6))
    gap = log_network - log_fill
    offset = log_fill - np.log(np.maximum(pixels.truth_m[mask], 1e-6))
    design = np.stack([np.ones_like(gap), log_spread.astype(np.float64)])  # (2, N)

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        weight = 1.0 / (1.0 + np.exp(-np.clip(theta @ design, -60.0, 60.0)))
        error = weight * gap + offset
        if objective == "squared":
            slope = 2.0 * error * gap * weight * (1.0 - weight)
            return float(np.mean(error * error)), design @ slope / error.size
        smooth = np.sqrt(error * error + _FIT_SMOOTHING ** 2)
        slope = error / smooth * gap * weight * (1.0 - weight)
        return float(smooth.mean()), design @ slope / error.size

    best = None
    for start in _FIT_STARTS:
        result = minimize(loss, np.asarray(start), jac=True, method="L-BFGS-B",
                          bounds=[(-50.0, 50.0)] * 2)
        if best is None or result.fun < best.fun:
            best = result
    return RegionBlend(*(float(v) for v in best.x))


#: What :func:`fit_confidence_blend` can minimise over pixels: a smoothed absolute
#: log-depth error (about the mean relative error) or the squared log-depth error (which
#: weighs large errors more, as RMSE does).
BLEND_OBJECTIVES = ("relative", "squared")


def fit_confidence_blend(pixels: BlendPixels, min_pixels: int = 1000,
                         objective: str = "relative") -> ConfidenceBlend:
    """Fit :class:`ConfidenceBlend` to pixels with ground truth (training scenes only).

    Per region, the coefficients minimise the mean over pixels of the blend's log-depth
    error, smoothed absolute (``"relative"``, about the mean relative error) or squared
    (``"squared"``), by L-BFGS from three starts (network alone, an even mix, the fill
    alone). Every frame should give the same number of pixels, so that each weighs alike.

    Args:
        pixels: the sampled pixels.
        min_pixels: fewest pixels each region needs.
        objective: one of :data:`BLEND_OBJECTIVES`.

    Raises:
        ValueError: too few pixels in a region, or an unknown objective.
    """
    if objective not in BLEND_OBJECTIVES:
        raise ValueError(f"objective must be one of {BLEND_OBJECTIVES}, got {objective!r}")
    inside = np.asarray(pixels.inside, dtype=bool)
    return ConfidenceBlend(
        inside=_fit_region_blend(pixels, inside, min_pixels, "inside", objective),
        outside=_fit_region_blend(pixels, ~inside, min_pixels, "outside", objective))
