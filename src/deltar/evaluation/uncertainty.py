"""Fit a checkpoint's uncertainty calibration on frames with ground truth.

The estimator runs the checkpoint as users run it (with its confidence blend), the
absolute error of every frame's returned depth is compared with the network's spread,
and :func:`deltar.inference.uncertainty.fit_uncertainty_calibration` picks the
coefficients. The result is written into a new checkpoint's config
(``uncertainty_calibration``), so the calibration travels with the weights into
``DepthEstimator``, ``deltar predict`` and the ONNX export. Fit it on the training
scenes' frames only: a calibration fitted on the frames it is judged on says nothing.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltar.inference.uncertainty import (
    CalibrationPixels,
    UncertaintyCalibration,
    concatenate_pixels,
    coverage,
    fit_uncertainty_calibration,
    sample_pixels,
)


@dataclass
class UncertaintyFit:
    """Outcome of :func:`fit_checkpoint_uncertainty`.

    Attributes:
        calibration: the fitted coefficients.
        frames: frames used.
        pixels: pixels used (per region: ``inside``, ``outside``).
        raw_coverage: (within 1, within 2) network spreads, per region, before.
        coverage: the same with the calibrated sigma, on the fitting pixels.
        path: the written checkpoint.
    """

    calibration: UncertaintyCalibration
    frames: int
    pixels: dict[str, int]
    raw_coverage: dict[str, tuple[float, float]]
    coverage: dict[str, tuple[float, float]]
    path: Path


def collect_pixels(estimator, sets: Sequence[Sequence], *, frames_per_set: int | None = None,
                   pixels_per_frame: int = 4000, min_depth: float = 1e-3,
                   max_depth: float = 10.0, seed: int = 0,
                   on_frame: Callable[[], None] | None = None
                   ) -> tuple[CalibrationPixels, int]:
    """Run ``estimator`` (raw spread: ``uncertainty=None``) over sets and sample pixels.

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator`.
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image, zones and
            ground-truth depth in metres).
        frames_per_set: at most this many frames of each set, spread evenly (all by
            default).
        pixels_per_frame: random pixels with ground truth kept per frame.
        min_depth, max_depth: ground-truth range in metres.
        seed: seed of the pixel draw.
        on_frame: called after each frame (progress).

    Returns:
        (pixels, frames used).
    """
    from deltar.inference.blend import zone_grid_mask

    rng = np.random.default_rng(seed)
    parts, frames = [], 0
    for samples in sets:
        count = len(samples)
        picks = range(count) if frames_per_set is None or frames_per_set >= count else \
            np.linspace(0, count - 1, frames_per_set).round().astype(int)
        for index in picks:
            sample = samples[int(index)]
            result = estimator.predict(sample.rgb, sample.zone_frame(),
                                       zone_rects=sample.zone_rects)
            gt = sample.depth_m
            valid = (gt > min_depth) & (gt < max_depth)
            if valid.any():
                moved = (np.zeros_like(result.depth_m) if result.network_depth_m is None
                         else np.abs(result.network_depth_m - result.depth_m))
                parts.append(sample_pixels(np.abs(result.depth_m - gt), result.uncertainty_m,
                                           result.depth_m, moved,
                                           zone_grid_mask(result.zone_rects, gt.shape),
                                           valid, pixels_per_frame, rng))
                frames += 1
            if on_frame is not None:
                on_frame()
    if not parts:
        raise ValueError("no frame has ground truth to fit the uncertainty on")
    return concatenate_pixels(parts), frames


def fit_checkpoint_uncertainty(checkpoint: str | os.PathLike, sets: Sequence[Sequence],
                               out: str | os.PathLike, *, frames_per_set: int | None = None,
                               pixels_per_frame: int = 4000, min_pixels: int = 1000,
                               overwrite: bool = False,
                               on_frame: Callable[[], None] | None = None) -> UncertaintyFit:
    """Fit the calibration of a checkpoint on sets with ground truth; write a new file.

    Args:
        checkpoint: a deltar checkpoint file or bundled name (``"default"``).
        sets: sequences of ZJU-L5 samples (e.g. ``deltar simulate`` sets of the model's
            training scenes).
        out: the new checkpoint (never the input file; written atomically).
        frames_per_set, pixels_per_frame: see :func:`collect_pixels`.
        min_pixels: fewest pixels each region (inside, beyond the zone grid) needs.
        overwrite: replace an existing ``out``.
        on_frame: called after each frame (progress).

    Raises:
        ValueError: ``out`` is the checkpoint itself, or too few pixels to fit.
    """
    from deltar.inference.estimator import DepthEstimator
    from deltar.models.checkpoint import load_checkpoint, save_checkpoint
    from deltar.weights import resolve_checkpoint

    source = Path(resolve_checkpoint(checkpoint))
    out = Path(out)
    if out.exists() and out.resolve() == source.resolve():
        raise ValueError(f"--out {out} is the checkpoint being calibrated; write a new file")
    model, preset, _ = load_checkpoint(source)
    # A copy serves the estimator (it prepares its model for inference in place); the
    # original is what is saved, so the file is read once.
    estimator = DepthEstimator(copy.deepcopy(model), uncertainty=None,
                               weights=f"{preset} from {source}")
    pixels, frames = collect_pixels(estimator, sets, frames_per_set=frames_per_set,
                                    pixels_per_frame=pixels_per_frame, on_frame=on_frame)
    calibration = fit_uncertainty_calibration(pixels, min_pixels)
    regions = {"inside": pixels.inside, "outside": ~pixels.inside}
    sigma = calibration.sigma(pixels.spread_m, pixels.depth_m, pixels.moved_m, pixels.inside)
    fit = UncertaintyFit(
        calibration=calibration, frames=frames,
        pixels={name: int(mask.sum()) for name, mask in regions.items()},
        raw_coverage={name: coverage(pixels.error_m[m], pixels.spread_m[m])
                      for name, m in regions.items()},
        coverage={name: coverage(pixels.error_m[m], sigma[m]) for name, m in regions.items()},
        path=out)
    model.config["uncertainty_calibration"] = calibration.to_dict()
    save_checkpoint(out, model, preset, overwrite=overwrite)
    return fit
