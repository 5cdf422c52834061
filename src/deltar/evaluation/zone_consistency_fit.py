"""Choose the zone-consistency strength (:mod:`deltar.inference.zone_consistency`) on
frames with ground truth, with the rest of a model's output stage
(:func:`deltar.evaluation.uncertainty.fit_checkpoint_uncertainty`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from deltar.contract import check_strength
from deltar.evaluation.metrics import EmptyFrameError, depth_metrics
from deltar.inference.zone_consistency import STRENGTH_CANDIDATES

__all__ = ["fit_zone_consistency", "frame_picks"]


def frame_picks(count: int, frames_per_set: int | None) -> Sequence[int]:
    """Indices of at most ``frames_per_set`` frames of ``count``, spread evenly (the
    output stage's fits all visit the same frames)."""
    if frames_per_set is None or frames_per_set >= count:
        return range(count)
    return [int(i) for i in np.linspace(0, count - 1, frames_per_set).round()]


def fit_zone_consistency(estimator, sets: Sequence[Sequence], *,
                         candidates: Sequence[float] = STRENGTH_CANDIDATES,
                         frames_per_set: int | None = None, min_depth: float = 1e-3,
                         max_depth: float = 10.0,
                         on_frame: Callable[[], None] | None = None
                         ) -> tuple[float, dict[float, float]]:
    """Choose the zone-consistency strength on frames with ground truth.

    The estimator (as given, with its zone outlier rule; fit with ``blend=None`` so the
    choice does not depend on a blend fitted without it) predicts each frame with each
    candidate; the one with the lowest mean relative error wins, the first on a tie.

    Args:
        estimator: a :class:`~deltar.inference.estimator.DepthEstimator`; its own
            ``zone_consistency`` is replaced while it runs and restored after.
        sets: sequences of :class:`~deltar.data.zju_l5.ZJUL5Sample` (image, zones and
            ground-truth depth in metres), of the training scenes.
        candidates: strengths in [0, 1] to try.
        frames_per_set: at most this many frames of each set, spread evenly.
        min_depth, max_depth: ground-truth range in metres.
        on_frame: called after each frame (progress).

    Returns:
        (the chosen strength, mean relative error per candidate).
    """
    candidates = [check_strength(c, "candidates") for c in candidates]
    if not candidates:
        raise ValueError("fit_zone_consistency needs at least one candidate")
    errors: dict[float, list[float]] = {c: [] for c in candidates}
    kept = estimator.zone_consistency
    try:
        for samples in sets:
            for index in frame_picks(len(samples), frames_per_set):
                sample = samples[index]
                for strength in candidates:
                    estimator.zone_consistency = strength
                    depth = estimator.predict(sample.rgb, sample.zone_frame(),
                                              zone_rects=sample.zone_rects).depth_m
                    try:
                        errors[strength].append(depth_metrics(depth, sample.depth_m,
                                                              min_depth, max_depth)["rel"])
                    except EmptyFrameError:
                        pass
                if on_frame is not None:
                    on_frame()
    finally:
        estimator.zone_consistency = kept
    means = {c: float(np.mean(v)) for c, v in errors.items() if v}
    if not means:
        raise ValueError("no frame has ground truth to choose the zone consistency on")
    best = min(means.values())
    return next(c for c in candidates if means.get(c) == best), means
