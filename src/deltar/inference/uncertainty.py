"""Calibrated uncertainty: a per-pixel sigma that means what a Gaussian sigma means.

The network's spread (the standard deviation of the depth distribution its head puts
on each pixel) ranks pixels by how sure the network is, but its scale is the head's own:
on unseen rooms about half of the pixels fall within one spread of the truth, where a
Gaussian's sigma holds 68 %. And once the estimator blends the network's depth with the
colorization fill (:mod:`deltar.inference.blend`), the spread no longer describes the
depth that is returned.

:class:`UncertaintyCalibration` maps three per-pixel quantities to the sigma of the
returned depth, separately inside the zone grid's bounding box and beyond it (where the
depth is extrapolated):

    sigma^2 = (a * spread)^2 + (b * depth)^2 + (c * |network depth - returned depth|)^2

``spread`` is the network's, ``b * depth`` a relative floor (a zone reading is never
better than a few percent), and the last term is how far the blend moved the pixel: the
network and the fill disagree there, so neither is to be trusted fully. Every term is
metric and scales with the readings, so sigma stays scale-equivariant like the depth.

:func:`fit_uncertainty_calibration` chooses ``(a, b, c)`` per region from pixels of
frames with ground truth (the training scenes' frames, never the test scenes'): for each
shape ``(b / a, c / a)`` on a grid and each overall scale that puts 60-80 % of the
absolute errors within one sigma, the pair whose one- and two-sigma coverages are
nearest 68.3 % and 95.4 % (misses weighed by 1 / 5 % and 1 / 2.5 %). Depth errors are
heavier-tailed than a Gaussian's, so no scale gives both exactly; the fit trades a few
points at one sigma for the two-sigma tail.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence, Sized
from dataclasses import dataclass

import numpy as np

from deltar.inference.regions import RegionPair, check_coefficients

#: Fraction of a Gaussian within one and two standard deviations.
GAUSSIAN_WITHIN_1 = math.erf(1 / math.sqrt(2))
GAUSSIAN_WITHIN_2 = math.erf(2 / math.sqrt(2))
#: Ratios (b / a, c / a) tried by the fit (b: relative floor; c: blend disagreement).
FLOOR_RATIOS = (0.0, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32)
DISAGREEMENT_RATIOS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)


@dataclass(frozen=True)
class RegionCalibration:
    """Coefficients of one region (see the module docstring); all >= 0, dimensionless."""

    spread: float
    floor: float
    disagreement: float

    def __post_init__(self) -> None:
        check_coefficients(self, "uncertainty calibration", nonnegative=True)
        if self.spread == self.floor == self.disagreement == 0:
            raise ValueError("uncertainty calibration coefficients are all 0: sigma would be 0")

    def sigma(self, spread_m: np.ndarray, depth_m: np.ndarray, moved_m: np.ndarray
              ) -> np.ndarray:
        """Sigma in metres of pixels of this region (arrays of one shape, as
        :meth:`UncertaintyCalibration.sigma`'s), in the arrays' float type."""
        total = np.square(self.spread * spread_m)
        total += np.square(self.floor * depth_m)
        total += np.square(self.disagreement * moved_m)
        return np.sqrt(total)


@dataclass(frozen=True)
class UncertaintyCalibration(RegionPair, region_type=RegionCalibration,
                             what="uncertainty calibration"):
    """Calibrated sigma inside and beyond the zone grid (module docstring); the fields,
    their checks and the JSON form (``to_dict`` / ``from_dict``) are :class:`RegionPair`'s."""

    inside: RegionCalibration
    outside: RegionCalibration

    def sigma(self, spread_m: np.ndarray, depth_m: np.ndarray, moved_m: np.ndarray,
              inside: np.ndarray | tuple[slice, slice]) -> np.ndarray:
        """(H, W) float32 calibrated sigma in metres.

        Args:
            spread_m: (H, W) the network's spread, metres.
            depth_m: (H, W) the returned (possibly blended) depth, metres.
            moved_m: (H, W) |network depth - returned depth|, metres (0 without a blend).
            inside: (H, W) bool, True inside the zone grid's bounding box; or that box
                as (rows, cols) slices (the same values, without masks' gathers).
        """
        if isinstance(inside, tuple):
            out = self.outside.sigma(spread_m, depth_m, moved_m).astype(np.float32, copy=False)
            out[inside] = self.inside.sigma(spread_m[inside], depth_m[inside], moved_m[inside])
            return out
        out = np.empty(np.shape(depth_m), dtype=np.float32)
        for region, mask in ((self.inside, inside), (self.outside, ~inside)):
            out[mask] = region.sigma(spread_m[mask], depth_m[mask], moved_m[mask])
        return out


def resolve_uncertainty(uncertainty: UncertaintyCalibration | str | None, contract: Mapping
                        ) -> UncertaintyCalibration | None:
    """The calibration an estimator uses (its ``uncertainty`` argument) given the weights'
    contract: ``"auto"`` the one they carry (``contract["uncertainty_calibration"]``, or
    None: the raw spread), a calibration as it is, None the raw spread.

    Raises:
        ValueError: anything else.
    """
    if uncertainty == "auto":
        stored = contract.get("uncertainty_calibration")
        return None if stored is None else UncertaintyCalibration.from_dict(stored)
    if uncertainty is not None and not isinstance(uncertainty, UncertaintyCalibration):
        raise ValueError(f"uncertainty must be 'auto', an UncertaintyCalibration or None, "
                         f"got {uncertainty!r}")
    return uncertainty


@dataclass
class CalibrationPixels:
    """Pixels of frames with ground truth, for :func:`fit_uncertainty_calibration`.

    Every array is (N,) float64 (``inside`` bool): the absolute error of the returned
    depth (metres), the network's spread (metres), the returned depth (metres), how far
    the blend moved the pixel (metres) and whether it lies inside the zone grid.
    """

    error_m: np.ndarray
    spread_m: np.ndarray
    depth_m: np.ndarray
    moved_m: np.ndarray
    inside: np.ndarray


def coverage(error_m: np.ndarray, sigma_m: np.ndarray) -> tuple[float, float]:
    """Fractions of pixels with |error| <= sigma and <= 2 sigma (arrays of one shape)."""
    error, sigma = np.abs(np.asarray(error_m)), np.asarray(sigma_m)
    return float(np.mean(error <= sigma)), float(np.mean(error <= 2 * sigma))


#: Coverage targets and tolerances of the fit: the scale and shape minimise the squared
#: misses of 68.3 % (within one sigma, weighed by 1 / 5 %) and 95.4 % (two, 1 / 2.5 %).
_TARGETS = ((1.0, GAUSSIAN_WITHIN_1, 0.05), (2.0, GAUSSIAN_WITHIN_2, 0.025))
#: One-sigma coverages the scale search tries (errors are heavier-tailed than a
#: Gaussian, so the best compromise usually covers a little more than 68.3 % at 1 sigma).
_LEVELS = np.linspace(0.60, 0.80, 81)


def _fit_region(pixels: CalibrationPixels, mask: np.ndarray, min_pixels: int
                ) -> RegionCalibration:
    error = pixels.error_m[mask]
    if error.size < min_pixels:
        raise ValueError(f"{error.size} calibration pixels in a region, need at least "
                         f"{min_pixels}: give more frames with ground truth")
    spread, depth, moved = (getattr(pixels, n)[mask] for n in ("spread_m", "depth_m",
                                                                "moved_m"))
    best: tuple[float, RegionCalibration] | None = None
    for floor in FLOOR_RATIOS:
        for disagreement in DISAGREEMENT_RATIOS:
            shape = np.sqrt(spread**2 + (floor * depth) ** 2 + (disagreement * moved) ** 2)
            if not np.all(shape > 0):
                continue  # a pixel the shape gives no sigma cannot be covered
            ratio = np.sort(error / shape)
            for level in _LEVELS:
                scale = float(ratio[min(int(level * ratio.size), ratio.size - 1)])
                if not (math.isfinite(scale) and scale > 0):
                    continue
                miss = sum(((np.searchsorted(ratio, k * scale, side="right") / ratio.size
                             - target) / tolerance) ** 2
                           for k, target, tolerance in _TARGETS)
                if best is None or miss < best[0]:
                    best = (miss, RegionCalibration(scale, scale * floor,
                                                    scale * disagreement))
    if best is None:
        raise ValueError("no calibration fits these pixels (every error or spread is 0)")
    return best[1]


def check_pixel_budget(sets: Sequence[Sized], frames_per_set: int | None,
                       pixels_per_frame: int, min_pixels: int = 1000) -> None:
    """Refuse, before any frame is read, a fit whose frames cannot hold ``min_pixels`` in
    each of its two regions (inside and beyond the zone grid): at most
    ``pixels_per_frame`` pixels come from each of at most ``frames_per_set`` frames of
    each set.

    Raises:
        ValueError: naming both numbers and what to raise.
    """
    frames = sum(len(s) if frames_per_set is None else min(len(s), frames_per_set)
                 for s in sets)
    if frames * pixels_per_frame < 2 * min_pixels:
        raise ValueError(f"{frames} frame(s) x {pixels_per_frame} pixels per frame give at most "
                         f"{frames * pixels_per_frame} calibration pixels, fewer than the "
                         f"{min_pixels} each of the 2 regions (inside and beyond the zone grid) "
                         "needs: give more frames or more pixels per frame (--data, "
                         "--frames-per-set, --pixels-per-frame)")


def fit_uncertainty_calibration(pixels: CalibrationPixels, min_pixels: int = 1000
                                ) -> UncertaintyCalibration:
    """Fit :class:`UncertaintyCalibration` to pixels with known error (module docstring).

    Args:
        pixels: pixels of frames with ground truth (training scenes only).
        min_pixels: fewest pixels a region needs.

    Raises:
        ValueError: too few pixels in a region, or nothing to fit.
    """
    return UncertaintyCalibration(inside=_fit_region(pixels, pixels.inside, min_pixels),
                                  outside=_fit_region(pixels, ~pixels.inside, min_pixels))
