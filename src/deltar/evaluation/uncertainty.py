"""Fit a checkpoint's output stage on frames with ground truth: outlier rule, zone
consistency, blend, sigma, no-target rule.

First the rule that sets aside zones disagreeing with every neighbour
(:mod:`deltar.sensor.zone_outliers`) is chosen among candidates, no rejection included,
by the estimator's mean relative error on the frames (:func:`fit_outlier_rule`); given
clean sets, a learned detector of biased zones trained on them
(:mod:`deltar.sensor.zone_outlier_detector`) is among the candidates too. The rest is
fitted with what was chosen. For plane-select networks that read no-target flags, the depth
such a zone stands for is chosen next (:func:`fit_no_target_depth`), then how far the
depth moves to reproduce the zones' readings
(:func:`deltar.evaluation.zone_consistency_fit.fit_zone_consistency`). The estimator runs
the network over the frames; for plane-select heads the zones' colorization fill is computed
too, and :func:`deltar.inference.blend_fit.fit_confidence_blend` fits the blend's
coefficients on sampled pixels. The blend is per pixel, so the blended depth of those
pixels is exact; their absolute errors and the network's spread then fit the sigma
(:func:`deltar.inference.uncertainty.fit_uncertainty_calibration`), so the sigma
describes the depth that is returned. All of it is written into a new checkpoint's
config and travels with the weights into ``DepthEstimator``, ``deltar predict`` and the
ONNX export. Fit on the training scenes' frames only: an output stage fitted on the
frames it is judged on says nothing. Last, for networks that read no-target flags, the
threshold of the rule that infers them for readings without flags is chosen on the same
frames with their flags removed (:func:`fit_no_target_inference`).
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from deltar.evaluation.network_reuse import reuse_network_outputs
from deltar.evaluation.zone_consistency_fit import fit_zone_consistency, frame_picks
from deltar.inference.blend import ConfidenceBlend
from deltar.inference.blend_fit import BlendPixels, fit_confidence_blend
from deltar.inference.uncertainty import (
    CalibrationPixels,
    UncertaintyCalibration,
    check_pixel_budget,
    coverage,
    fit_uncertainty_calibration,
)
from deltar.inference.zone_consistency import STRENGTH_CANDIDATES
from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M
from deltar.sensor.zone_outlier_detector import OutlierDetector
from deltar.sensor.zone_outliers import OutlierRule


@dataclass
class UncertaintyFit:
    """Outcome of :func:`fit_checkpoint_uncertainty`.

    Attributes:
        calibration: the fitted sigma coefficients.
        blend: the fitted blend coefficients (None: the network does not blend).
        frames: frames used.
        pixels: pixels used (per region: ``inside``, ``outside``).
        raw_coverage: (within 1, within 2) network spreads, per region, before.
        coverage: the same with the calibrated sigma, on the fitting pixels.
        relative_error: mean relative error on the fitting pixels of ``network``,
            ``fill`` and ``blend`` (the last two only when the network blends).
        no_target_min_neighbour_m: the chosen no-target rule for frames without flags
            (metres, or None), :func:`fit_no_target_inference`.
        no_target_errors: mean relative error of each candidate rule over the frames
            where some candidate reads a zone as no target (empty when the network reads
            no flags or no such frame exists).
        outlier_rule: the chosen zone outlier rule (None: keep every zone),
            :func:`fit_outlier_rule`.
        outlier_errors: mean relative error of each candidate outlier rule (None: no
            rejection) over the frames where some candidate rejects a zone.
        no_target_depth_m: the chosen depth of no-target zones, metres
            (:func:`fit_no_target_depth`; None for networks that read no flags).
        no_target_depth_errors: mean relative error of each candidate depth over the
            frames with a no-target zone.
        zone_consistency: the chosen zone-consistency strength, ``zone_consistency_errors``
            each candidate's mean relative error (``fit_zone_consistency``).
        path: the written checkpoint.
    """

    calibration: UncertaintyCalibration
    blend: ConfidenceBlend | None
    frames: int
    pixels: dict[str, int]
    raw_coverage: dict[str, tuple[float, float]]
    coverage: dict[str, tuple[float, float]]
    relative_error: dict[str, float]
    no_target_min_neighbour_m: float | None
    no_target_errors: dict[float | None, float]
    outlier_rule: OutlierRule | OutlierDetector | None
    outlier_errors: dict[OutlierRule | OutlierDetector | None, float]
    no_target_depth_m: float | None
    no_target_depth_errors: dict[float, float]
    zone_consistency: float
    zone_consistency_errors: dict[float, float]
    path: Path


def collect_pixels(estimator, sets: Sequence[Sequence], *, with_fill: bool,
                   frames_per_set: int | None = None, pixels_per_frame: int = 4000,
                   min_depth: float = 1e-3, max_depth: float = 10.0, seed: int = 0,
                   on_frame: Callable[[], None] | None = None) -> tuple[BlendPixels, int]:
    """Run ``estimator``'s network over sets and sample pixels with ground truth.

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator` without blend
            or calibration (``blend=None, uncertainty=None``): the network's depth and
            raw spread (frames without no-target flags get them by the estimator's
            rule; :func:`fit_checkpoint_uncertainty` sets none).
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image, zones and
            ground-truth depth in metres).
        with_fill: also compute the zones' colorization fill
            (:meth:`~deltar.inference.estimator.DepthEstimator.blend_fill_for`); else
            the pixels' ``fill_m`` is the network's depth.
        frames_per_set: at most this many frames of each set, spread evenly (all by
            default).
        pixels_per_frame: random pixels with ground truth kept per frame (so every frame
            weighs alike).
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
        for index in frame_picks(len(samples), frames_per_set):
            sample = samples[index]
            frame = sample.zone_frame()
            result = estimator.predict(sample.rgb, frame, zone_rects=sample.zone_rects)
            truth = sample.depth_m
            chosen = np.flatnonzero((truth > min_depth) & (truth < max_depth))
            if chosen.size:
                if chosen.size > pixels_per_frame:
                    chosen = rng.choice(chosen, size=pixels_per_frame, replace=False)
                fill = (estimator.blend_fill_for(sample.rgb, result.zone_frame,
                                                 result.zone_rects)
                        if with_fill else None)
                fill = result.depth_m if fill is None else fill
                inside = zone_grid_mask(result.zone_rects, truth.shape)
                parts.append(BlendPixels(*(np.asarray(a, dtype=np.float64).reshape(-1)[chosen]
                                           for a in (truth, result.depth_m, fill,
                                                     result.uncertainty_m)),
                                         inside=inside.reshape(-1)[chosen]))
                frames += 1
            if on_frame is not None:
                on_frame()
    if not parts:
        raise ValueError("no frame has ground truth to fit the output stage on")
    return BlendPixels(*(np.concatenate([getattr(p, name) for p in parts])
                         for name in ("truth_m", "network_m", "fill_m", "spread_m",
                                      "inside"))), frames


#: Thresholds :func:`fit_no_target_inference` tries, metres, most cautious first (None:
#: a frame without flags has no zone read as no target).
NO_TARGET_CANDIDATES_M: tuple[float | None, ...] = (None, 3.5, 3.0, 2.5, 2.0, 1.5)


def fit_no_target_inference(estimator, sets: Sequence[Sequence], *,
                            candidates: Sequence[float | None] = NO_TARGET_CANDIDATES_M,
                            frames_per_set: int | None = None, min_depth: float = 1e-3,
                            max_depth: float = 10.0,
                            on_frame: Callable[[], None] | None = None
                            ) -> tuple[float | None, dict[float | None, float]]:
    """Choose the no-target rule's threshold for frames without flags
    (:func:`deltar.sensor.no_target.infer_no_target`) on frames with ground truth.

    Each frame's flags are removed and every candidate's inferred flags are given to the
    estimator (as users run it: with its blend); the candidate with the lowest mean
    relative error over the frames wins, the most cautious on a tie. Frames where no
    candidate reads any zone as no target are skipped (every candidate is the same there).
    Fit on frames of the training scenes with their zones also degraded (dropped zones
    are invalid without being far), so the rule weighs both reasons a zone is invalid.

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator`.
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image, zones and
            ground-truth depth in metres).
        candidates: thresholds to try, metres (None: no inference), cautious first.
        frames_per_set: at most this many frames of each set, spread evenly.
        min_depth, max_depth: ground-truth range in metres.
        on_frame: called after each frame (progress).

    Returns:
        (the chosen threshold in metres or None, mean relative error per candidate; empty
        when no frame was affected, then the choice is None).
    """
    from deltar.sensor.no_target import infer_no_target

    def variants(frame):
        for c in candidates:
            mask = (np.zeros_like(frame.valid) if c is None else
                    infer_no_target(frame.mean_m, frame.valid, c))
            yield c, replace(frame, no_target=mask), mask

    return _choose_candidate(estimator, sets, variants, candidates, frames_per_set,
                             min_depth, max_depth, on_frame)


def _choose_candidate(estimator, sets, variants, candidates, frames_per_set, min_depth,
                      max_depth, on_frame):
    """The candidate with the lowest mean relative error of the estimator over the frames,
    the first on a tie, and each candidate's mean: what :func:`fit_no_target_inference`
    and :func:`fit_outlier_rule` share. ``variants(frame)`` yields (candidate, the frame
    as that candidate changes it, (n, n) or (Z,) bool mask of what it changed); frames
    where no candidate changes anything are skipped, and candidates with the same mask
    are predicted once."""
    from deltar.evaluation.metrics import EmptyFrameError, depth_metrics

    errors: dict = {c: [] for c in candidates}
    for samples in sets:
        for index in frame_picks(len(samples), frames_per_set):
            sample = samples[index]
            changed = list(variants(sample.zone_frame()))
            if any(mask.any() for _, _, mask in changed):
                scored: dict[bytes, float] = {}  # candidates that change the same zones
                for c, frame, mask in changed:
                    key = np.packbits(mask).tobytes()
                    if key not in scored:
                        depth = estimator.predict(sample.rgb, frame,
                                                  zone_rects=sample.zone_rects).depth_m
                        try:
                            scored[key] = depth_metrics(depth, sample.depth_m, min_depth,
                                                        max_depth)["rel"]
                        except EmptyFrameError:
                            scored[key] = float("nan")
                    errors[c].append(scored[key])
            if on_frame is not None:
                on_frame()
    means = {c: float(np.nanmean(v)) for c, v in errors.items() if v and
             not np.all(np.isnan(v))}
    best = min(means.values(), default=None)
    return (next(c for c in candidates if means.get(c) == best) if means else None), means


#: Outlier rules :func:`fit_outlier_rule` tries (None: keep every zone), most cautious
#: first: a zone must lie 5 % (or 3 %) beyond all its neighbours, in a frame with at
#: least 3 (4) such zones.
OUTLIER_CANDIDATES: tuple[OutlierRule | None, ...] = (
    None, OutlierRule(0.05, min_zones=5), OutlierRule(0.05, min_zones=3),
    OutlierRule(0.03, min_zones=4))
#: Thresholds at which a trained zone outlier detector joins those candidates (probability
#: that a zone is biased), most cautious first.
DETECTOR_THRESHOLDS: tuple[float, ...] = (0.95, 0.85, 0.7, 0.5)


def fit_outlier_rule(estimator, sets: Sequence[Sequence], *,
                     candidates: Sequence[OutlierRule | OutlierDetector | None] =
                     OUTLIER_CANDIDATES,
                     frames_per_set: int | None = None, min_depth: float = 1e-3,
                     max_depth: float = 10.0, on_frame: Callable[[], None] | None = None
                     ) -> tuple[OutlierRule | OutlierDetector | None, dict]:
    """Choose the zone outlier rule (:mod:`deltar.sensor.zone_outliers`) on frames with
    ground truth.

    Each candidate's rejected zones are set invalid and the estimator (as given: fit with
    ``blend=None`` so the choice does not depend on a blend fitted without the rule)
    predicts; the candidate with the lowest mean relative error over the frames wins,
    the most cautious on a tie. Frames where no candidate rejects a zone are skipped
    (every candidate is the same there). Fit on frames of the training scenes, clean and
    with degraded zones, so that the rule weighs what rejecting costs on clean readings
    against what it saves on noisy ones.

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator`; its own
            ``zone_outliers`` is replaced while it runs and restored after.
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image, zones and
            ground-truth depth in metres).
        candidates: rules to try (None: keep every zone), cautious first.
        frames_per_set: at most this many frames of each set, spread evenly.
        min_depth, max_depth: ground-truth range in metres.
        on_frame: called after each frame (progress).

    Returns:
        (the chosen rule or None, mean relative error per candidate; empty when no
        candidate rejected any zone, then the choice is None).
    """
    from deltar.sensor.zone_outliers import reject_outlier_zones

    grids: set[int] = set()  # frames of one grid: the chosen rule is for that grid

    def variants(frame):
        grids.add(frame.grid)
        no_target = estimator.no_target_of(frame)
        for c in candidates:
            rule = replace(c, grid=frame.grid) if isinstance(c, OutlierRule) else c
            yield c, *reject_outlier_zones(frame, rule, no_target)

    kept = estimator.zone_outliers
    try:
        estimator.zone_outliers = None
        chosen, errors = _choose_candidate(estimator, sets, variants, candidates,
                                           frames_per_set, min_depth, max_depth, on_frame)
        if isinstance(chosen, OutlierRule) and len(grids) == 1:
            chosen = replace(chosen, grid=grids.pop())
        return chosen, errors
    finally:
        estimator.zone_outliers = kept


#: No-target depths :func:`fit_no_target_depth` tries, metres, the prior first.
NO_TARGET_DEPTH_CANDIDATES_M: tuple[float, ...] = (NO_TARGET_DEPTH_M, 5.5, 6.0, 6.5, 7.0)


def fit_no_target_depth(estimator, sets: Sequence[Sequence], *,
                        candidates: Sequence[float] = NO_TARGET_DEPTH_CANDIDATES_M,
                        frames_per_set: int | None = None, min_depth: float = 1e-3,
                        max_depth: float = 10.0, on_frame: Callable[[], None] | None = None
                        ) -> tuple[float, dict[float, float]]:
    """Choose the depth a zone that reported *no target* stands for (the plane-select
    head's hypothesis and the fill's reading there) on frames with ground truth.

    Such a zone says only that its surface lies beyond the sensor's range; how far
    beyond is a prior, here the one that fits the training scenes best: each candidate
    runs the estimator on the frames that have a no-target zone, and the one with the
    lowest mean relative error wins, the first on a tie (the 5 m prior).

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator` with a PyTorch
            plane-select model that reads the flags; it is left at the chosen depth.
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample`.
        candidates: depths to try, metres, the prior first.
        frames_per_set: at most this many frames of each set, spread evenly.
        min_depth, max_depth: ground-truth range in metres.
        on_frame: called after each frame (progress).

    Returns:
        (the chosen depth in metres, mean relative error per candidate; empty when no
        frame has a no-target zone, then the choice is the first candidate).
    """
    from deltar.evaluation.metrics import EmptyFrameError, depth_metrics

    errors: dict[float, list[float]] = {float(c): [] for c in candidates}
    for samples in sets:
        for index in frame_picks(len(samples), frames_per_set):
            sample = samples[index]
            frame = sample.zone_frame()
            if estimator.no_target_of(frame).any():
                for depth_m in errors:
                    _set_no_target_depth(estimator, depth_m)
                    depth = estimator.predict(sample.rgb, frame,
                                              zone_rects=sample.zone_rects).depth_m
                    try:
                        errors[depth_m].append(depth_metrics(depth, sample.depth_m, min_depth,
                                                             max_depth)["rel"])
                    except EmptyFrameError:
                        errors[depth_m].append(float("nan"))
            if on_frame is not None:
                on_frame()
    means = {c: float(np.nanmean(v)) for c, v in errors.items() if v and
             not np.all(np.isnan(v))}
    chosen = float(candidates[0]) if not means else \
        next(c for c in errors if means.get(c) == min(means.values()))
    _set_no_target_depth(estimator, chosen)
    return chosen, means


def _set_no_target_depth(estimator, depth_m: float) -> None:
    """Point the estimator's network and fill at a no-target depth (metres)."""
    estimator.model.set_output_contract(no_target_depth=depth_m)
    estimator.no_target_depth_m = depth_m


def fit_checkpoint_uncertainty(checkpoint: str | os.PathLike, sets: Sequence[Sequence],
                               out: str | os.PathLike, *, frames_per_set: int | None = None,
                               pixels_per_frame: int = 4000, min_pixels: int = 1000,
                               overwrite: bool = False, blend_objective: str = "relative",
                               outlier_candidates: Sequence[OutlierRule | None] =
                               OUTLIER_CANDIDATES,
                               detector_sets: Sequence[Sequence] = (),
                               detector_noise: Mapping[str, float] | None = None,
                               consistency_candidates: Sequence[float] = STRENGTH_CANDIDATES,
                               on_frame: Callable[[], None] | None = None,
                               on_passes: Callable[[int], None] | None = None
                               ) -> UncertaintyFit:
    """Fit a checkpoint's blend (plane-select networks) and sigma calibration on sets
    with ground truth (module docstring); write them into a new checkpoint file.

    Args:
        checkpoint: a deltar checkpoint file or bundled name (``"default"``).
        sets: sequences of ZJU-L5 samples (e.g. ``deltar simulate`` sets of the model's
            training scenes).
        out: the new checkpoint (never the input file; written atomically).
        frames_per_set, pixels_per_frame: see :func:`collect_pixels`.
        min_pixels: fewest pixels each region (inside, beyond the zone grid) needs.
        blend_objective: what the blend's fit minimises
            (:data:`~deltar.inference.blend_fit.BLEND_OBJECTIVES`).
        outlier_candidates: zone outlier rules to choose among
            (:func:`fit_outlier_rule`); ``(None,)`` (and no ``detector_sets``) keeps every
            zone without trying.
        detector_sets: sets whose zones are right (clean simulations of the training
            scenes): a zone outlier detector is trained on them
            (:func:`~deltar.sensor.zone_outlier_detector.fit_outlier_detector`, their
            ``frames_per_set``) and joins the candidates at each of
            :data:`DETECTOR_THRESHOLDS`. Empty: no detector.
        detector_noise: the degradation it learns (``fit_outlier_detector``'s
            ``drop_fraction``, ``bias_prob``, ``bias_mean_m``, ``bias_std_m``); None: its
            defaults, those of ``deltar simulate``'s degraded sets.
        consistency_candidates: zone-consistency strengths to choose among
            (:func:`~deltar.evaluation.zone_consistency_fit.fit_zone_consistency`); ``(0.0,)``
            keeps the network's depth without trying.
        overwrite: replace an existing ``out``.
        on_frame: called after each frame (progress).
        on_passes: called once the checkpoint is read, with how many times the fit
            visits each frame: the outlier rule, the zone consistency, the blend and sigma,
            and for networks that read no-target flags the no-target depth and rule.

    Raises:
        ValueError: ``out`` is the checkpoint itself, or too few pixels to fit.
    """
    from deltar.inference.estimator import DepthEstimator
    from deltar.models.checkpoint import load_checkpoint, save_checkpoint
    from deltar.weights import resolve_checkpoint

    source, out = Path(resolve_checkpoint(checkpoint)), Path(out)
    if out.exists() and out.resolve() == source.resolve():
        raise ValueError(f"--out {out} is the checkpoint being calibrated; write a new file")
    check_pixel_budget(sets, frames_per_set, pixels_per_frame, min_pixels)  # before any pass
    model, preset, _ = load_checkpoint(source)
    if on_passes is not None:
        on_passes(5 if model.uses_no_target else 3)
    blends = model.network_config.head.name == "plane_select"
    # A copy serves the estimator (it prepares its model for inference in place); the
    # original is what is saved, so the file is read once. The output stage being
    # refitted (outlier rule, blend, sigma, no-target rule) is left out, so the fit
    # depends on the network and the frames alone, not on what the checkpoint carried.
    estimator = DepthEstimator(copy.deepcopy(model), blend=None, uncertainty=None,
                               no_target_min_neighbour_m=None, zone_outliers=None,
                               zone_consistency=0.0, weights=f"{preset} from {source}")
    reuse_network_outputs(estimator)  # passes that give the network the same inputs
    # The outlier rule first: it changes the zones everything after it reads.
    if detector_sets:
        from deltar.sensor.zone_outlier_detector import fit_outlier_detector

        detector = fit_outlier_detector(
            [samples[i].zone_frame() for samples in detector_sets
             for i in frame_picks(len(samples), frames_per_set)], **(detector_noise or {}))
        outlier_candidates = (*outlier_candidates,
                              *(detector.with_threshold(t) for t in DETECTOR_THRESHOLDS))
    outlier_rule, outlier_errors = fit_outlier_rule(
        estimator, sets, candidates=outlier_candidates, frames_per_set=frames_per_set,
        on_frame=on_frame)
    estimator.zone_outliers = outlier_rule
    # Then the no-target depth: the head's far hypothesis, which the pixels below read.
    far_depth, far_errors = fit_no_target_depth(
        estimator, sets, frames_per_set=frames_per_set, on_frame=on_frame) \
        if model.uses_no_target and blends else (None, {})
    # Then the zone consistency: it changes the network's depth the blend and sigma read.
    consistency, consistency_errors = (0.0, {}) if tuple(consistency_candidates) == (0.0,) \
        else fit_zone_consistency(estimator, sets, candidates=consistency_candidates,
                                  frames_per_set=frames_per_set, on_frame=on_frame)
    estimator.zone_consistency = consistency
    pixels, frames = collect_pixels(estimator, sets, with_fill=blends,
                                    frames_per_set=frames_per_set,
                                    pixels_per_frame=pixels_per_frame, on_frame=on_frame)
    blend = fit_confidence_blend(pixels, min_pixels, blend_objective) if blends else None
    depth = pixels.network_m if blend is None else pixels.blended(blend).astype(np.float64)
    error = np.abs(depth - pixels.truth_m)
    moved = np.abs(pixels.network_m - depth)
    calibration = fit_uncertainty_calibration(
        CalibrationPixels(error, pixels.spread_m, depth, moved, pixels.inside), min_pixels)
    regions = {"inside": pixels.inside, "outside": ~pixels.inside}
    sigma = calibration.sigma(pixels.spread_m, depth, moved, pixels.inside)
    # The rule for frames without flags, chosen with the fitted blend as users run it.
    estimator.blend = blend
    rule, rule_errors = fit_no_target_inference(
        estimator, sets, frames_per_set=frames_per_set, on_frame=on_frame) \
        if model.uses_no_target else (None, {})
    relative = {"network": pixels.network_m}
    if blend is not None:
        relative.update(fill=pixels.fill_m, blend=depth)
    fit = UncertaintyFit(
        calibration=calibration, blend=blend, frames=frames,
        pixels={name: int(mask.sum()) for name, mask in regions.items()},
        raw_coverage={name: coverage(np.abs(pixels.network_m[m] - pixels.truth_m[m]),
                                     pixels.spread_m[m]) for name, m in regions.items()},
        coverage={name: coverage(error[m], sigma[m]) for name, m in regions.items()},
        relative_error={name: float(np.mean(np.abs(v - pixels.truth_m) / pixels.truth_m))
                        for name, v in relative.items()},
        no_target_min_neighbour_m=rule, no_target_errors=rule_errors,
        outlier_rule=outlier_rule, outlier_errors=outlier_errors,
        no_target_depth_m=far_depth, no_target_depth_errors=far_errors,
        zone_consistency=consistency, zone_consistency_errors=consistency_errors, path=out)
    model.set_output_contract(uncertainty_calibration=calibration.to_dict(),
                              no_target_min_neighbour_m=rule, zone_consistency=consistency,
                              zone_outlier_rule=None if outlier_rule is None
                              else outlier_rule.to_dict(),
                              **({} if far_depth is None else {"no_target_depth": far_depth}))
    if blend is not None:
        model.set_output_contract(confidence_blend=blend.to_dict())
    save_checkpoint(out, model, preset, overwrite=overwrite)
    return fit
