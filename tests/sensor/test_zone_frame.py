"""Tests of the zone frame (deltar.sensor.zone_frame)."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.sensor import Orientation, ZoneFrame


def _driver_lists(zones: int, status: int = 5):
    distance_mm = [1000.0 + 10 * i for i in range(zones)]
    sigma_mm = [5.0 + i for i in range(zones)]
    return distance_mm, sigma_mm, [status] * zones


@pytest.mark.parametrize("zones, grid", [(16, 4), (64, 8)])
def test_from_driver_flat_lists(zones, grid):
    distance, sigma, status = _driver_lists(zones)
    frame = ZoneFrame.from_driver(distance, sigma, status, timestamp_s=3.0)
    assert frame.grid == grid and frame.zone_count == zones
    assert frame.mean_m.shape == (grid, grid) and frame.mean_m.dtype == np.float32
    assert frame.valid.all()
    # Zone 5 (row-major) of the driver: 1050 mm and 10 mm.
    assert frame.mean_m[5 // grid, 5 % grid] == pytest.approx(1.050)
    assert frame.sigma_m[5 // grid, 5 % grid] == pytest.approx(0.010)
    mean, sigma, valid = frame.flat()
    assert mean.shape == sigma.shape == valid.shape == (zones,)
    assert mean[-1] == pytest.approx(1.0 + 0.01 * (zones - 1))
    assert frame.mean_sigma().shape == (zones, 2)
    assert frame.timestamp_s == 3.0


def test_multi_target_lists_keep_the_first_target_as_the_primary():
    distance = np.repeat(np.arange(16) * 100.0 + 500, 2)
    distance[1::2] = 3999  # second target of each zone
    frame = ZoneFrame.from_driver(distance, np.full(32, 10.0), np.full(32, 5), grid=4)
    np.testing.assert_allclose(frame.flat()[0], (np.arange(16) * 100.0 + 500) / 1000)
    np.testing.assert_allclose(frame.flat_targets()[0][:, 1], 3.999, rtol=1e-6)


def test_status_filtering():
    distance, sigma, status = _driver_lists(64)
    status[3] = 255  # no target
    status[10] = 9  # valid, large pulse
    status[20] = 4  # consistency failed
    distance[30] = 0.0  # valid status but zero distance
    frame = ZoneFrame.from_driver(distance, sigma, status)
    _, _, valid = frame.flat()
    assert not valid[3] and valid[10] and not valid[20] and not valid[30]
    assert int(valid.sum()) == 61
    mean_sigma = frame.mean_sigma()
    assert (mean_sigma[[3, 20, 30]] == 0).all()
    assert frame.status.reshape(-1)[3] == 255
    # Status 255 (and only it) is "no target": nothing within range.
    assert np.flatnonzero(frame.flat_no_target()).tolist() == [3]
    strict = ZoneFrame.from_driver(distance, sigma, status, valid_status=(5,))
    assert not strict.flat()[2][10]


def test_no_target_flags_are_checked_and_default_to_none():
    mean, valid = np.full((4, 4), 1.0), np.ones((4, 4), bool)
    valid[0, 0] = False
    plain = ZoneFrame(mean_m=mean, sigma_m=np.zeros((4, 4)), valid=valid)
    assert plain.no_target is None and not plain.flat_no_target().any()
    flags = ~valid
    frame = ZoneFrame(mean_m=mean, sigma_m=np.zeros((4, 4)), valid=valid, no_target=flags)
    assert frame.flat_no_target().tolist() == [True] + [False] * 15
    with pytest.raises(ValueError, match="no_target marks valid zones"):
        ZoneFrame(mean_m=mean, sigma_m=np.zeros((4, 4)), valid=valid,
                  no_target=np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="no_target must have shape"):
        ZoneFrame(mean_m=mean, sigma_m=np.zeros((4, 4)), valid=valid,
                  no_target=np.zeros((8, 8), bool))


def test_orientations_by_hand():
    distance = np.arange(16) * 100.0 + 100  # driver zone i at (i + 1) decimetres
    sigma, status = np.ones(16), np.full(16, 5)

    def grid_of(orientation):  # in decimetres
        return 10 * ZoneFrame.from_driver(distance, sigma, status,
                                          orientation=orientation).mean_m

    driver = (np.arange(16) + 1.0).reshape(4, 4)
    np.testing.assert_allclose(grid_of(None), driver)
    # Up-down flip: the image's top row is the driver's bottom row (zones 12..15).
    np.testing.assert_allclose(grid_of(Orientation(flip_ud=True))[0], [13, 14, 15, 16])
    # Left-right flip: the image's first column is the driver's last (zones 3, 7, 11, 15).
    np.testing.assert_allclose(grid_of(Orientation(flip_lr=True))[:, 0], [4, 8, 12, 16])
    # One counter-clockwise quarter turn: the driver's last column becomes the top row.
    np.testing.assert_allclose(grid_of(Orientation(rot90=1))[0], [4, 8, 12, 16])
    np.testing.assert_allclose(grid_of(Orientation(rot90=2)), driver[::-1, ::-1])
    np.testing.assert_allclose(grid_of(Orientation(rot90=4)), driver)
    # Flips are applied before the turn.
    both = grid_of(Orientation(flip_ud=True, rot90=1))
    np.testing.assert_allclose(both, np.rot90(driver[::-1]))


def test_rejects_wrong_counts():
    with pytest.raises(ValueError, match="distance_mm"):
        ZoneFrame.from_driver(*_driver_lists(15))
    distance, sigma, status = _driver_lists(64)
    with pytest.raises(ValueError, match="range_sigma_mm"):
        ZoneFrame.from_driver(distance, sigma[:60], status)
    with pytest.raises(ValueError, match="grid"):
        ZoneFrame.from_driver(distance, sigma, status, grid=6)
    with pytest.raises(ValueError, match="target_status"):
        ZoneFrame.from_driver(distance, sigma, [300] * 64)
    with pytest.raises(ValueError, match="distance_mm"):
        ZoneFrame.from_driver(["far"] * 64, sigma, status)
    with pytest.raises(ValueError, match="mean_m"):
        ZoneFrame(mean_m=np.ones(36), sigma_m=np.ones(36), valid=np.ones(36, bool))
    with pytest.raises(ValueError, match="sigma_m"):
        ZoneFrame(mean_m=np.ones((8, 8)), sigma_m=np.ones((4, 4)), valid=np.ones((8, 8), bool))


def test_rejects_nan_and_negative_values_in_valid_zones():
    mean = np.ones((4, 4))
    sigma = np.full((4, 4), 0.01)
    valid = np.ones((4, 4), bool)
    bad_mean = mean.copy()
    bad_mean[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"mean_m.*\[\[1, 2\]\]"):
        ZoneFrame(bad_mean, sigma, valid)
    bad_sigma = sigma.copy()
    bad_sigma[0, 3] = -0.1
    with pytest.raises(ValueError, match=r"sigma_m.*\[\[0, 3\]\]"):
        ZoneFrame(mean, bad_sigma, valid)
    with pytest.raises(ValueError, match="mean_m"):
        ZoneFrame(-mean, sigma, valid)
    # The same values in an invalid zone are fine (they carry no measurement).
    valid[1, 2] = False
    ZoneFrame(bad_mean, sigma, valid)
    # Driver NaNs make the zone invalid rather than failing.
    distance, sigma_mm, status = _driver_lists(16)
    distance[2] = float("nan")
    assert not ZoneFrame.from_driver(distance, sigma_mm, status).flat()[2][2]


def test_histogram_fields_validated():
    kwargs = dict(mean_m=np.ones((4, 4)), sigma_m=np.zeros((4, 4)), valid=np.ones((4, 4), bool))
    edges = np.linspace(0, 4, 101)
    frame = ZoneFrame(**kwargs, hist_edges_m=edges, hist_counts=np.zeros((4, 4, 100)))
    assert frame.hist_counts.dtype == np.float32
    with pytest.raises(ValueError, match="together"):
        ZoneFrame(**kwargs, hist_counts=np.zeros((4, 4, 100)))
    with pytest.raises(ValueError, match="hist_counts"):
        ZoneFrame(**kwargs, hist_edges_m=edges, hist_counts=np.zeros((4, 4, 99)))
    with pytest.raises(ValueError, match="hist_edges_m"):
        ZoneFrame(**kwargs, hist_edges_m=edges[::-1], hist_counts=np.zeros((4, 4, 100)))
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="hist_edges_m must be 1-D, finite"):
            ZoneFrame(**kwargs, hist_edges_m=[0.0, bad, 2.0], hist_counts=np.ones((4, 4, 2)))
    with pytest.raises(ValueError, match="hist_counts"):
        ZoneFrame(**kwargs, hist_edges_m=edges, hist_counts=-np.ones((4, 4, 100)))
    with pytest.raises(ValueError, match="timestamp_s"):
        ZoneFrame(**kwargs, timestamp_s=float("nan"))


def test_no_target_zones_become_far_readings():
    from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M, no_target_as_readings

    means = np.array([1.0, 0.0, 2.0, 0.0])
    valid = np.array([True, False, True, False])
    no_target = np.array([True, True, False, False])  # a valid zone's flag does not count
    got_means, got_valid = no_target_as_readings(means, valid, no_target)
    np.testing.assert_array_equal(got_means, [1.0, NO_TARGET_DEPTH_M, 2.0, 0.0])
    np.testing.assert_array_equal(got_valid, [True, True, True, False])
    np.testing.assert_array_equal(no_target_as_readings(means, valid, no_target, 7.5)[0],
                                  [1.0, 7.5, 2.0, 0.0])


# ---------------------------------------------------------------- physical validity
def _base(**changes):
    fields = {"mean_m": np.full(64, 1.5), "sigma_m": np.full(64, 0.02),
              "valid": np.ones(64, bool)}
    fields.update(changes)
    return fields


@pytest.mark.parametrize("changes, message", [
    ({"mean_m": ["1.5"] * 64}, "ZoneFrame.mean_m must hold numbers, got values of type <U3"),
    ({"sigma_m": [True] * 64}, "ZoneFrame.sigma_m must hold numbers, got booleans"),
    ({"valid": ["yes"] * 64}, "ZoneFrame.valid must hold booleans (or 0/1), got values of "
     "type <U3"),
    ({"valid": np.full(64, 2)}, "ZoneFrame.valid must hold booleans (or 0/1), got values of "
     "type int64 other than 0 and 1"),
    ({"status": np.full(64, 5.5)}, "ZoneFrame.status must hold integer codes in 0..255, "
     "got 5.5"),
    ({"status": np.full(64, 300)}, "ZoneFrame.status must hold integer codes in 0..255, "
     "got 300"),
    ({"status": np.array([255] + [5] * 63)}, "ZoneFrame zones [0] are valid but their status "
     "is 255 (no target)"),
], ids=["strings", "bools", "valid-strings", "valid-2", "fractional-status", "status-300",
        "valid-and-255"])
def test_values_are_refused_not_coerced(changes, message):
    with pytest.raises(ValueError) as caught:
        ZoneFrame(**_base(**changes))
    assert message in str(caught.value)


def test_physical_errors_name_the_zones():
    assert ZoneFrame(**_base()).physical_error() is None
    wide = ZoneFrame(**_base(sigma_m=np.array([1e6] + [0.02] * 63)))
    assert wide.physical_error() == (
        "1 valid zone(s) have a sigma larger than the VL53L5CX range 4 m (zones [0]: 1e+06 "
        "m), which no reading within the range can have; mark such zones invalid")
    counts = np.ones((64, 3))
    counts[[2, 7]] = 0
    empty = ZoneFrame(**_base(hist_edges_m=np.array([0.0, 1.0, 2.0, 3.0]), hist_counts=counts))
    assert empty.physical_error() == (
        "2 valid zone(s) have an all-zero histogram (zones [2, 7]): a zone that counted no "
        "photons measured no distance; mark such zones invalid")
    far = ZoneFrame(**_base(mean_m=np.array([9.0] + [1.5] * 63)))
    assert far.physical_error() == far.range_error()
    # Values written in after construction (a reused buffer) bypass validate().
    broken = ZoneFrame(**_base())
    broken.mean_m.flat[27] = np.nan
    broken.sigma_m.flat[3] = np.inf
    assert broken.physical_error() == (
        "2 valid zone(s) have a NaN or infinite mean or sigma (zones [3, 27]); mark such "
        "zones invalid")


def test_driver_status_codes_are_refused_not_truncated_and_wide_sigmas_invalid():
    with pytest.raises(ValueError, match=r"^target_status must hold integer codes in "
                       r"0\.\.255, got 5\.5$"):
        ZoneFrame.from_driver([1500] * 64, [20] * 64, [5.5] * 64)
    with pytest.warns(RuntimeWarning, match="1 zone.s. with a valid status have a sigma "
                      "larger than the VL53L5CX's 4 m range .up to 9 m.; marked invalid"):
        frame = ZoneFrame.from_driver([1500] * 64, [9000] + [20] * 63, [5] * 64)
    assert frame.valid_count == 63
    frame = ZoneFrame.from_driver([1500] * 64, [20] * 64, [255] * 64, valid_status=(255,))
    assert frame.valid_count == 0  # "no target" is never a reading


def test_an_unknown_sensor_models_range_is_checked_when_the_frame_is_built():
    # No listed range: the frame is held to the physical checks' 20 m at once, with the
    # driver semantics of a known model (marked invalid, with a warning naming why).
    with pytest.warns(RuntimeWarning, match=r"1 zone.s. with a valid status read more "
                      r"than the 20 m range held for the unknown sensor model 'VL53L9X' "
                      r"\(known: VL53L5CX, VL53L8CX\) \(up to 30 m\); marked invalid"):
        frame = ZoneFrame.from_driver([30000] + [1500] * 63, [20] * 64, [5] * 64,
                                      sensor_model="VL53L9X")
    assert frame.valid_count == 63 and frame.physical_error() is None
    # Within 20 m an unknown model's readings stay valid (its range is not known).
    frame = ZoneFrame.from_driver([6000] * 64, [20] * 64, [5] * 64, sensor_model="VL53L9X")
    assert frame.valid_count == 64 and frame.physical_error() is None


@pytest.mark.parametrize("changes, message", [
    ({"timestamp_s": "12.5"}, "ZoneFrame.timestamp_s must be a finite number of seconds, got "
     "'12.5'"),
    ({"timestamp_s": True}, "ZoneFrame.timestamp_s must be a finite number of seconds, got "
     "True"),
    ({"sensor_model": 5}, "ZoneFrame.sensor_model must be a string, got 5"),
], ids=["timestamp-string", "timestamp-bool", "sensor-model-number"])
def test_scalar_fields_are_refused_not_coerced(changes, message):
    with pytest.raises(ValueError) as caught:
        ZoneFrame(**_base(**changes))
    assert message in str(caught.value)


def test_driver_lists_of_different_lengths_are_refused():
    with pytest.raises(ValueError, match=r"must have the same length \(one entry per zone and "
                       r"target\), got \[16, 64, 64\]$"):
        ZoneFrame.from_driver([1500] * 16, [20] * 64, [5] * 64)


@pytest.mark.parametrize("changes, message", [
    ({"distance_mm": None}, "distance_mm is required"),
    ({"valid_status": [300]}, "valid_status must hold integer codes in 0..255, got 300"),
    ({"valid_status": None}, "valid_status must be a list of numbers, got NoneType"),
    ({"valid_status": "5"}, "valid_status must be a list of numbers, got str"),
    ({"orientation": "rot90"}, "orientation must be an Orientation"),
], ids=["no-distances", "status-300", "status-none", "status-string", "orientation-string"])
def test_driver_arguments_that_are_not_what_the_driver_gives_are_named(changes, message):
    arguments = {"distance_mm": [1500] * 64, "range_sigma_mm": [20] * 64,
                 "target_status": [5] * 64, **changes}
    with pytest.raises(ValueError) as caught:
        ZoneFrame.from_driver(arguments.pop("distance_mm"), arguments.pop("range_sigma_mm"),
                              arguments.pop("target_status"), **arguments)
    assert message in str(caught.value)


def test_valid_status_takes_one_code_or_any_iterable_of_codes():
    for codes in (5, range(5, 10), {5, 9}, (5,), np.array([5, 9])):
        frame = ZoneFrame.from_driver([1500] * 64, [20] * 64, [5] * 64, valid_status=codes)
        assert frame.valid_count == 64, codes


def test_an_unknown_sensor_model_is_still_held_to_a_range_no_sensor_reaches():
    """A typo in sensor_model must not let millimetres through as metres."""
    def frame(model, metres):
        return ZoneFrame(np.full((8, 8), metres), np.full((8, 8), 0.02),
                         np.ones((8, 8), bool), sensor_model=model)

    assert "outside the VL53L5 range 0 < d <= 20 m" in frame("VL53L5", 2000.0).physical_error()
    assert frame("simulated", 6.0).physical_error() is None  # beyond 4 m, within 20
    assert frame("VL53L5CX", 6.0).physical_error() is not None


@pytest.mark.parametrize("kwargs, message", [
    ({"rot90": 1.5}, "Orientation.rot90 must be an integer"),
    ({"rot90": True}, "Orientation.rot90 must be an integer"),
    ({"flip_ud": "no"}, "Orientation.flip_ud must be True or False, got 'no'"),
    ({"flip_lr": 1}, "Orientation.flip_lr must be True or False"),
])
def test_orientation_refuses_values_it_would_apply_wrongly(kwargs, message):
    # rot90=1.5 turned like rot90=3 and flip_ud="no" flipped (a non-empty string is true).
    with pytest.raises(ValueError, match=message):
        Orientation(**kwargs)
    assert Orientation(flip_ud=np.bool_(True), rot90=np.int64(-1)).rot90 == -1


def test_an_infinite_sigma_is_named_among_the_bad_zones():
    """The message listed no zone for an infinite sigma ('bad zones []')."""
    sigma = np.full(64, 0.02)
    sigma[9] = np.inf
    with pytest.raises(ValueError, match=r"sigma_m must be finite .* bad zones \[\[1, 1\]\]"):
        ZoneFrame(np.full(64, 1.5), sigma, np.ones(64, bool))
