"""Map accuracy, completeness and F-scores against a reference point set."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.mapping.metrics import map_scores


def test_scores_of_a_shifted_copy_and_of_a_partial_map():
    rng = np.random.default_rng(0)
    reference = rng.uniform(-1.0, 1.0, (2000, 3))
    same = map_scores(reference, reference)
    assert same["accuracy_m"] == same["completeness_m"] == 0.0
    assert same["fscore_5"] == same["fscore_10"] == 1.0
    # Every point 7 cm off: within 10 cm, not within 5 cm, both ways.
    shifted = map_scores(reference + np.array([0.07, 0.0, 0.0]), reference)
    assert shifted["precision_5"] < 0.5 and shifted["precision_10"] == 1.0
    assert shifted["accuracy_m"] <= 0.07 + 1e-9
    # Half the reference mapped exactly: precision 1, recall about one half.
    half = map_scores(reference[reference[:, 0] < 0], reference)
    assert half["precision_5"] == 1.0
    assert half["recall_5"] == pytest.approx(np.mean(reference[:, 0] < 0), abs=0.05)
    assert half["fscore_5"] == pytest.approx(2 * half["recall_5"] / (1 + half["recall_5"]))


def test_bad_points_and_thresholds_are_named():
    cloud = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"points_m must be a non-empty \(N, 3\) array"):
        map_scores(np.zeros((0, 3)), cloud)
    with pytest.raises(ValueError, match="distinct whole centimetres"):
        map_scores(cloud, cloud, thresholds_m=(0.049, 0.051))  # both would be "_5"
    with pytest.raises(ValueError, match="positive metres"):
        map_scores(cloud, cloud, thresholds_m=(float("nan"),))
