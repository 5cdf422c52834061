from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from deltar.evaluation.zone_consistency_fit import fit_zone_consistency, frame_picks
from deltar.inference.zone_consistency import STRENGTH_CANDIDATES


class _StubEstimator:
    """Predicts the truth off by a factor that depends on ``zone_consistency``."""

    def __init__(self, factors: dict[float, float]) -> None:
        self.factors, self.zone_consistency, self.seen = factors, 0.25, []

    def predict(self, rgb, frame, zone_rects=None):
        self.seen.append(self.zone_consistency)
        return SimpleNamespace(depth_m=rgb * self.factors[self.zone_consistency])


def _sample(truth: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(rgb=truth, depth_m=truth, zone_rects=None,
                           zone_frame=lambda: None)


def test_the_fit_chooses_the_strength_with_the_lowest_error_and_restores_the_estimator():
    truth = np.full((4, 4), 2.0, np.float32)
    estimator = _StubEstimator({0.0: 1.10, 0.5: 1.02, 1.0: 0.95})
    chosen, errors = fit_zone_consistency(estimator, [[_sample(truth)] * 3],
                                          frames_per_set=2)
    assert chosen == 0.5
    assert errors == pytest.approx({0.0: 0.10, 0.5: 0.02, 1.0: 0.05}, abs=1e-6)
    assert estimator.zone_consistency == 0.25  # restored
    assert len(estimator.seen) == 2 * len(STRENGTH_CANDIDATES)  # two frames, each strength
    # On a tie the first candidate (none) wins.
    tie = _StubEstimator({0.0: 1.05, 0.5: 0.95, 1.0: 1.05})
    assert fit_zone_consistency(tie, [[_sample(truth)]])[0] == 0.0
    with pytest.raises(ValueError, match="candidates must be a number in"):
        fit_zone_consistency(tie, [[_sample(truth)]], candidates=(0.0, 2.0))


def test_frame_picks_spread_over_the_set():
    assert list(frame_picks(5, None)) == [0, 1, 2, 3, 4]
    assert frame_picks(9, 3) == [0, 4, 8]
