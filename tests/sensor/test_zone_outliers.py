"""Zones that disagree with every neighbour (deltar.sensor.zone_outliers)."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_outliers import (
    OutlierRule,
    find_outlier_zones,
    reject_outlier_zones,
    resolve_outlier_rule,
)


def _ramp(n: int = 8, far_m: float = 2.35) -> np.ndarray:
    """A floor seen in perspective: depth grows down the grid from 2 m to ``far_m``."""
    return np.repeat(np.linspace(2.0, far_m, n)[:, None], n, axis=1)


def test_smooth_surfaces_and_depth_edges_have_no_outliers() -> None:
    valid = np.ones((8, 8), bool)
    assert not find_outlier_zones(_ramp(far_m=5.0), valid, 0.03).any()
    # A step: each zone beside the edge still has neighbours on its own side.
    step = np.where(np.arange(8)[None, :] < 4, 1.0, 3.0) * np.ones((8, 8))
    assert not find_outlier_zones(step, valid, 0.03).any()
    # A one-zone-wide strip (a table leg) has neighbours along it.
    strip = np.full((8, 8), 3.0)
    strip[:, 4] = 1.0
    assert not find_outlier_zones(strip, valid, 0.03).any()


@pytest.mark.parametrize("offset", [1.1, 1 / 1.1])
def test_a_zone_beyond_all_its_neighbours_is_an_outlier(offset) -> None:
    mean = _ramp()
    mean[3, 5] *= offset  # 10 % farther or nearer than its ramp (2.5 % per row)
    valid = np.ones((8, 8), bool)
    found = find_outlier_zones(mean, valid, 0.05)
    assert found.sum() == 1 and found[3, 5]
    # Within the tolerance it is kept; on a steeper ramp it lies between its neighbours.
    assert not find_outlier_zones(mean, valid, 0.2).any()
    steep = _ramp(far_m=5.0)
    steep[3, 5] *= offset
    assert not find_outlier_zones(steep, valid, 0.05).any()


def test_invalid_zones_are_never_outliers_and_too_few_neighbours_keep_a_zone() -> None:
    mean = np.full((8, 8), 2.0)
    mean[0, 0] = 3.0  # a corner: three neighbours
    mean[4, 4] = 3.0
    valid = np.ones((8, 8), bool)
    assert find_outlier_zones(mean, valid, 0.05, min_neighbours=4)[4, 4]
    assert not find_outlier_zones(mean, valid, 0.05, min_neighbours=4)[0, 0]
    assert find_outlier_zones(mean, valid, 0.05, min_neighbours=3)[0, 0]
    # Invalid neighbours neither count nor vote; an invalid zone is never flagged.
    valid[3:6, 3:6] = False
    valid[4, 4] = True
    assert not find_outlier_zones(mean, valid, 0.05).any()
    valid[4, 4] = False
    assert not find_outlier_zones(mean, valid, 0.05)[4, 4]


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match=r"\(n, n\)"):
        find_outlier_zones(np.ones((8, 8)), np.ones((4, 4), bool), 0.05)


def _frame(targets: bool = False) -> ZoneFrame:
    mean = _ramp()
    for row, col in ((2, 2), (2, 5), (5, 3)):
        mean[row, col] += 0.3
    frame = ZoneFrame(mean_m=mean.astype(np.float32), sigma_m=np.full((8, 8), 0.02, np.float32),
                      valid=np.ones((8, 8), bool), no_target=np.zeros((8, 8), bool))
    if targets:
        second = np.zeros((8, 8, 2), np.float32)
        second[..., 0], second[..., 1] = mean, mean + 0.5
        valid = np.ones((8, 8, 2), bool)
        frame = ZoneFrame(mean_m=mean.astype(np.float32),
                          sigma_m=np.full((8, 8), 0.02, np.float32), valid=np.ones((8, 8), bool),
                          target_mean_m=second, target_sigma_m=np.full((8, 8, 2), 0.02, np.float32),
                          target_valid=valid, target_signal=np.ones((8, 8, 2), np.float32))
    return frame


@pytest.mark.parametrize("targets", [False, True])
def test_a_frame_with_enough_outliers_has_them_set_invalid(targets) -> None:
    frame = _frame(targets)
    no_target = np.zeros(64, bool)
    screened, rejected = reject_outlier_zones(frame, OutlierRule(0.05, min_zones=3), no_target)
    assert rejected.sum() == 3 and rejected.reshape(8, 8)[2, 2]
    assert screened.valid_count == 61 and not screened.valid[2, 2]
    assert frame.valid.all()  # the input frame is left as it was
    if targets:
        assert not screened.target_valid[2, 2].any() and screened.target_valid[0, 0].all()
    # Fewer outliers than the rule's minimum: the frame is kept whole.
    kept, none = reject_outlier_zones(frame, OutlierRule(0.05, min_zones=4), no_target)
    assert kept is frame and not none.any()
    # What the rule finds is what is set aside.
    assert np.array_equal(OutlierRule(0.05, min_zones=3).find(frame).reshape(-1), rejected)
    assert not OutlierRule(0.05, min_zones=4).find(frame).any()
    assert reject_outlier_zones(frame, None, no_target)[0] is frame


def test_rejected_zones_are_failed_not_beyond_the_range() -> None:
    # A frame without flags: the returned frame carries the flags read before, so a
    # rejected zone is never inferred to be "no target" afterwards.
    from deltar.sensor.no_target import frame_no_target

    mean = np.full((8, 8), 3.8, np.float32)
    for row, col in ((2, 2), (2, 5), (5, 3)):
        mean[row, col] = 3.0
    frame = ZoneFrame(mean_m=mean, sigma_m=np.full((8, 8), 0.02, np.float32),
                      valid=np.ones((8, 8), bool))
    flags = frame_no_target(frame, 3.5)
    screened, rejected = reject_outlier_zones(frame, OutlierRule(0.05, min_zones=3), flags)
    assert rejected.sum() == 3
    assert not frame_no_target(screened, 3.5).any()


def test_rule_values_and_stored_form_are_checked() -> None:
    rule = OutlierRule(0.05, min_zones=3)
    assert OutlierRule.from_dict(rule.to_dict()) == rule
    assert resolve_outlier_rule("auto", {"zone_outlier_rule": rule.to_dict()}) == rule
    assert resolve_outlier_rule("auto", {}) is None
    assert resolve_outlier_rule(None, {"zone_outlier_rule": rule.to_dict()}) is None
    for bad in (0.0, -0.1, float("nan"), True):
        with pytest.raises(ValueError, match="tolerance"):
            OutlierRule(bad)
    with pytest.raises(ValueError, match="min_zones"):
        OutlierRule(0.05, min_zones=0)
    with pytest.raises(ValueError, match="min_neighbours"):
        OutlierRule(0.05, min_neighbours=9)
    with pytest.raises(ValueError, match="got keys"):
        OutlierRule.from_dict({"tolerance": 0.05, "zones": 3})
    with pytest.raises(ValueError, match="grid must be 4 or 8"):
        OutlierRule(0.05, grid=6)
    four = OutlierRule(0.05, grid=4)
    assert OutlierRule.from_dict(four.to_dict()) == four and "grid" not in rule.to_dict()


def test_a_rule_applies_to_frames_of_its_grid_only() -> None:
    """A rule chosen on 8 x 8 frames keeps every zone of a 4 x 4 frame, whose zones are
    four times as large (real structure makes one stand out far more often)."""
    mean = np.full((4, 4), 2.0, np.float32)
    mean[1, 1] = 3.0
    frame = ZoneFrame(mean_m=mean, sigma_m=np.full((4, 4), 0.02, np.float32),
                      valid=np.ones((4, 4), bool))
    for_eight = OutlierRule(0.05, min_zones=1, min_neighbours=3)
    assert not for_eight.find(frame).any()
    assert OutlierRule(0.05, min_zones=1, min_neighbours=3, grid=4).find(frame).any()
    with pytest.raises(ValueError, match="zone_outliers must be"):
        resolve_outlier_rule("yes", {})
