"""The no-target rule for readings without flags: which invalid zones read as far."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.sensor.no_target import check_min_neighbour_m, frame_no_target, infer_no_target
from deltar.sensor.zone_frame import ZoneFrame


def _reading() -> tuple[np.ndarray, np.ndarray]:
    mean = np.full((8, 8), 1.2)
    valid = np.ones((8, 8), bool)
    mean[2, 3] = 3.4  # a far wall beside zone (2, 4)
    valid[2, 4] = False  # beside the far reading
    valid[6, 1] = False  # among near readings only: a failed zone
    valid[0:3, 7] = False  # at the border, beside near readings
    return np.where(valid, mean, 0.0), valid


def test_invalid_zones_beside_a_far_reading_read_as_no_target():
    mean, valid = _reading()
    flags = infer_no_target(mean, valid, 3.0)
    assert flags[2, 4] and not flags[6, 1] and not flags[:, 7].any()
    assert not (flags & valid).any()
    # (2, 4) is not marked when the threshold is above what its neighbour reads.
    assert not infer_no_target(mean, valid, 3.5)[2, 4]
    # A threshold of 0 reads every invalid zone beside any reading as no target.
    assert np.array_equal(infer_no_target(mean, valid, 0.0), ~valid)


def test_a_zone_with_no_valid_neighbour_reads_as_no_target():
    valid = np.ones((4, 4), bool)
    valid[:, 2:] = False  # the right half returned nothing
    mean = np.where(valid, 1.0, 0.0)
    flags = infer_no_target(mean, valid, 3.0)
    # Column 2 sits beside near readings; column 3 has no valid neighbour at all.
    assert not flags[:, 2].any() and flags[:, 3].all()


def test_frame_flags_win_over_the_rule():
    mean, valid = _reading()
    sigma = np.full((8, 8), 0.02)
    unflagged = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid)
    np.testing.assert_array_equal(frame_no_target(unflagged, 3.0),
                                  infer_no_target(mean, valid, 3.0).reshape(-1))
    assert not frame_no_target(unflagged, None).any()
    flagged = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid,
                        no_target=np.zeros((8, 8), bool))
    # A frame that carries flags (here: none set) keeps them whatever the rule says.
    assert not frame_no_target(flagged, 0.0).any()


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "3", True])
def test_bad_thresholds_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="no_target_min_neighbour_m"):
        check_min_neighbour_m(bad, "no_target_min_neighbour_m")
    assert check_min_neighbour_m(None) is None and check_min_neighbour_m(2) == 2.0


@pytest.mark.parametrize("value", [np.float32(3.5), np.float64(3.5), np.int64(3)])
def test_numpy_thresholds_are_numbers(value):
    threshold = check_min_neighbour_m(value)
    assert type(threshold) is float and threshold == float(value)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"\(n, n\)"):
        infer_no_target(np.ones((8, 8)), np.ones((4, 4), bool), 3.0)
    with pytest.raises(ValueError, match=r"\(n, n\)"):
        infer_no_target(np.ones(64), np.ones(64, bool), 3.0)


def test_a_frame_without_any_valid_zone_gets_no_flag():
    # Nothing returned anywhere: a blocked sensor, not evidence of an empty view.
    valid = np.zeros((8, 8), bool)
    assert not infer_no_target(np.zeros((8, 8)), valid, 3.5).any()
