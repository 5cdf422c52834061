"""How close one map is to another: accuracy, completeness, precision, recall, F-score.

The usual surface-reconstruction scores (as in Tanks and Temples), on the maps' surface
points: a map's *accuracy* is the mean distance from its points to the reference's
nearest point, its *completeness* the mean distance from the reference's points to its
nearest point; *precision* and *recall* at a threshold are the fractions of those
distances under it, and the F-score their harmonic mean.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Thresholds of the reported scores, metres.
DEFAULT_THRESHOLDS_M = (0.05, 0.10)


def map_scores(points_m: np.ndarray, reference_m: np.ndarray,
               thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M) -> dict[str, float]:
    """Scores of a map's surface points against the reference map's.

    Args:
        points_m: (N, 3) surface points of the map, metres.
        reference_m: (M, 3) surface points of the reference map, metres (same frame).
        thresholds_m: distances at which precision, recall and F-score are given.

    Returns:
        ``accuracy_m``, ``completeness_m`` (mean distances, metres) and per threshold
        ``t`` (in cm, e.g. ``5``): ``precision_5``, ``recall_5``, ``fscore_5``
        (fractions 0..1); ``points`` and ``reference_points`` (counts).

    Raises:
        ValueError: a point set that is empty or not (N, 3); thresholds that are not
            positive, or two in one whole centimetre (their scores would share a key).
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points_m, dtype=np.float64)
    reference = np.asarray(reference_m, dtype=np.float64)
    for name, array in (("points_m", points), ("reference_m", reference)):
        if array.ndim != 2 or array.shape[1] != 3 or len(array) == 0:
            raise ValueError(f"{name} must be a non-empty (N, 3) array, got {array.shape}")
    finite = all(np.isfinite(t) and t > 0 for t in thresholds_m)
    keys = [round(float(t) * 100) for t in thresholds_m] if finite else []
    if not finite or len(set(keys)) != len(keys):
        # Scores are keyed by whole centimetres: two thresholds in one would overwrite.
        raise ValueError(f"thresholds_m must be positive metres of distinct whole "
                         f"centimetres, got {list(thresholds_m)}")
    to_reference, _ = cKDTree(reference).query(points, workers=1)
    to_points, _ = cKDTree(points).query(reference, workers=1)
    scores = {"accuracy_m": float(to_reference.mean()),
              "completeness_m": float(to_points.mean()),
              "points": float(len(points)), "reference_points": float(len(reference))}
    for threshold in thresholds_m:
        key = f"{round(threshold * 100):d}"
        precision = float(np.mean(to_reference < threshold))
        recall = float(np.mean(to_points < threshold))
        fscore = 0.0 if precision + recall == 0 else \
            2 * precision * recall / (precision + recall)
        scores |= {f"precision_{key}": precision, f"recall_{key}": recall,
                   f"fscore_{key}": fscore}
    return scores
