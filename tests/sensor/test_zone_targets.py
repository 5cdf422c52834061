"""Several targets per zone in ZoneFrame (deltar.sensor.zone_targets): the target arrays,
from_driver, validation."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.sensor import Orientation, ZoneFrame


def _driver_targets(zones: int, per_zone: int):
    """Flat zone-major driver lists: target t of zone z reads 1000 + 10 z + 1000 t mm."""
    zone = np.repeat(np.arange(zones), per_zone)
    target = np.tile(np.arange(per_zone), zones)
    distance = 500.0 + 10 * zone + 1000 * target
    sigma = 5.0 + target
    status = np.full(zones * per_zone, 5)
    return distance, sigma, status


def test_from_driver_fills_every_target_and_keeps_the_first_as_primary():
    distance, sigma, status = _driver_targets(64, 3)
    status[3 * 7 + 1] = 4  # zone 7, target 1: consistency failed
    status[3 * 9 + 2] = 9  # zone 9, target 2: valid with large pulse
    detected = np.full(64, 3)
    detected[11] = 1  # zone 11 saw one target: its other entries are stale
    frame = ZoneFrame.from_driver(distance, sigma, status, nb_target_detected=detected)
    assert frame.grid == 8 and frame.targets_per_zone == 3
    assert frame.target_mean_m.shape == frame.target_valid.shape == (8, 8, 3)
    assert frame.target_mean_m.dtype == np.float32 and frame.target_status.dtype == np.uint8
    mean, sigma_m, valid = frame.flat_targets()
    np.testing.assert_allclose(mean[5], [0.55, 1.55, 2.55], atol=1e-6)
    np.testing.assert_allclose(sigma_m[5], [0.005, 0.006, 0.007], atol=1e-6)
    assert valid[7].tolist() == [True, False, True] and mean[7, 1] == 0
    assert valid[9].tolist() == [True, True, True]
    assert valid[11].tolist() == [True, False, False]
    # The primary reading is the first target, as with one target per zone.
    np.testing.assert_array_equal(frame.mean_m, frame.target_mean_m[..., 0])
    np.testing.assert_array_equal(frame.valid, frame.target_valid[..., 0])
    np.testing.assert_array_equal(frame.status, frame.target_status[..., 0])
    single = ZoneFrame.from_driver(distance[::3], sigma[::3], status[::3])
    np.testing.assert_array_equal(frame.mean_m, single.mean_m)
    assert single.target_mean_m is None and single.targets_per_zone == 1


def test_from_driver_target_validity_follows_status_range_and_detected_count():
    distance, sigma, status = _driver_targets(16, 2)
    status[1], status[3] = 255, 12  # zone 0 target 1: no target; zone 1 target 1: blurred
    distance[5] = 0  # zone 2 target 1: error code
    with pytest.warns(RuntimeWarning, match="1 target.s. with a valid status read more than"):
        distance[7] = 4500  # zone 3 target 1: beyond the 4 m range
        frame = ZoneFrame.from_driver(distance, sigma, status, grid=4)
    assert frame.flat_targets()[2][:5, 1].tolist() == [False, False, False, False, True]
    assert frame.target_order == "strongest"
    # nb_target_detected = 0 leaves nothing valid in the zone, the primary included.
    frame = ZoneFrame.from_driver(*_driver_targets(16, 2), nb_target_detected=[0] + [2] * 15)
    assert frame.grid == 4 and not frame.target_valid[0, 0].any() and not frame.valid[0, 0]


def test_from_driver_closest_order_and_explicit_targets_per_zone():
    distance, sigma, status = _driver_targets(16, 2)
    frame = ZoneFrame.from_driver(distance, sigma, status, targets_per_zone=2,
                                  target_order="closest")
    assert frame.grid == 4 and frame.target_order == "closest"
    # One target per zone, asked for explicitly: T = 1 target arrays.
    frame = ZoneFrame.from_driver(distance[::2], sigma[::2], status[::2], targets_per_zone=1)
    assert frame.targets_per_zone == 1 and frame.target_mean_m.shape == (4, 4, 1)


def test_from_driver_reads_a_4x4_frame_from_an_8x8_sized_buffer():
    distance, sigma, status = _driver_targets(64, 2)  # ST's buffers hold 64 zones
    frame = ZoneFrame.from_driver(distance, sigma, status, grid=4, targets_per_zone=2)
    np.testing.assert_allclose(frame.flat_targets()[0][15], [0.65, 1.65], atol=1e-6)


@pytest.mark.parametrize("kwargs, message", [
    (dict(grid=8, targets_per_zone=3), "distance_mm has 128 entries; expected 192 for a 8x8 "
     "grid with 3 target.s. per zone"),
    (dict(targets_per_zone=5), "targets_per_zone must be an integer in 1..4, got 5"),
    (dict(targets_per_zone=True), "targets_per_zone must be an integer in 1..4, got True"),
    (dict(target_order="nearest"), "target_order must be one of"),
    (dict(nb_target_detected=[2] * 63), "nb_target_detected has 63 zones"),
    (dict(grid=8, nb_target_detected=[2] * 16), "nb_target_detected has 16 entries; "
     "expected 64"),
    (dict(nb_target_detected=[2.5] * 64), "nb_target_detected must hold integer codes"),
    (dict(nb_target_detected=[2] * 5 + [5] + [2] * 58), r"nb_target_detected must hold "
     r"target counts in 0..4 \(the sensor reports at most 4 targets per zone\), got 5 for "
     r"zone 5"),
    (dict(nb_target_detected=[-1] * 64), "nb_target_detected must hold integer codes"),
])
def test_from_driver_refuses_inconsistent_target_input(kwargs, message):
    distance, sigma, status = _driver_targets(64, 2)
    with pytest.raises(ValueError, match=message):
        ZoneFrame.from_driver(distance, sigma, status, **kwargs)


def test_from_driver_refuses_more_than_four_targets_per_zone():
    with pytest.raises(ValueError, match="at most 4 targets per zone"):
        ZoneFrame.from_driver(*_driver_targets(16, 5), grid=4)


def test_orientation_applies_to_the_target_arrays():
    distance, sigma, status = _driver_targets(16, 2)
    plain = ZoneFrame.from_driver(distance, sigma, status, grid=4)
    turned = ZoneFrame.from_driver(distance, sigma, status, grid=4,
                                   orientation=Orientation(flip_ud=True, rot90=1))
    for name in ("target_mean_m", "target_sigma_m", "target_valid", "target_status"):
        expected = np.rot90(getattr(plain, name)[::-1], k=1, axes=(0, 1))
        np.testing.assert_array_equal(getattr(turned, name), expected)
    np.testing.assert_array_equal(turned.mean_m, turned.target_mean_m[..., 0])


def _frame_fields(**changes):
    mean = np.full((4, 4, 2), 1.5, np.float32)
    mean[..., 1] = 3.0
    fields = {"mean_m": mean[..., 0].copy(), "sigma_m": np.full((4, 4), 0.02),
              "valid": np.ones((4, 4), bool), "target_mean_m": mean,
              "target_sigma_m": np.full((4, 4, 2), 0.02), "target_valid": np.ones((4, 4, 2), bool)}
    fields.update(changes)
    return fields


def test_targets_accessor_with_and_without_target_arrays():
    frame = ZoneFrame(**_frame_fields())
    mean, sigma, valid = frame.targets()
    assert mean.shape == sigma.shape == valid.shape == (4, 4, 2)
    single = ZoneFrame(mean_m=np.full(16, 1.5), sigma_m=np.full(16, 0.02),
                       valid=np.arange(16) % 2 == 0)
    mean, sigma, valid = single.targets()
    assert mean.shape == (4, 4, 1) and mean.dtype == np.float32 and valid.dtype == bool
    np.testing.assert_array_equal(valid[..., 0], single.valid)
    assert np.all(mean[~valid] == 0) and np.all(mean[valid] == np.float32(1.5))
    assert single.flat_targets()[0].shape == (16, 1)


def test_flat_target_arrays_are_reshaped_and_invalid_targets_read_zero():
    fields = _frame_fields()
    flat = {k: (v.reshape(16, -1) if k.startswith("target") else v.reshape(-1))
            for k, v in fields.items()}
    flat["target_valid"] = flat["target_valid"].copy()
    flat["target_valid"][3, 1] = False
    flat["target_mean_m"] = flat["target_mean_m"].copy()
    flat["target_mean_m"][3, 1] = np.nan  # meaningless where not valid
    frame = ZoneFrame(**flat)
    assert frame.target_mean_m.shape == (4, 4, 2)
    assert frame.target_mean_m[0, 3, 1] == 0 and frame.target_sigma_m[0, 3, 1] == 0


@pytest.mark.parametrize("changes, message", [
    ({"target_mean_m": np.ones((4, 4, 5))}, r"ZoneFrame.target_mean_m must have shape \(4, "
     r"4, T\) with T in 1..4, got \(4, 4, 5\)"),
    ({"target_mean_m": np.ones((4, 4))}, r"ZoneFrame.target_mean_m must have shape \(4, 4, "
     r"T\)"),
    ({"target_sigma_m": np.ones((4, 4, 3))}, r"ZoneFrame.target_sigma_m must have shape \(4, "
     r"4, 2\) like target_mean_m"),
    ({"target_valid": np.ones((4, 4, 1), bool)}, "ZoneFrame.target_valid must have shape"),
    ({"target_status": np.full((4, 4, 3), 5)}, "ZoneFrame.target_status must have shape"),
    ({"target_valid": None}, "ZoneFrame.target_mean_m, target_sigma_m and target_valid must "
     "be given together"),
    ({"target_mean_m": None, "target_sigma_m": None, "target_valid": None,
      "target_status": np.full((4, 4, 2), 5)}, "ZoneFrame.target_status needs"),
    ({"target_mean_m": np.full((4, 4, 2), -1.0)}, "ZoneFrame.target_mean_m must be finite and "
     ">= 0 in valid targets"),
    ({"target_sigma_m": np.full((4, 4, 2), np.nan)}, "ZoneFrame.target_sigma_m must be "
     "finite and >= 0"),
    ({"target_valid": np.full((4, 4, 2), "yes")}, "ZoneFrame.target_valid must hold booleans"),
    ({"target_mean_m": np.full((4, 4, 2), "1")}, "ZoneFrame.target_mean_m must hold numbers"),
    ({"target_status": np.full((4, 4, 2), 255)}, "ZoneFrame.target_status is 255 .no target. "
     "for valid targets"),
    ({"target_status": np.full((4, 4, 2), 300)}, "ZoneFrame.target_status must hold integer "
     "codes"),
    ({"target_order": "nearest"}, "ZoneFrame.target_order must be one of"),
    ({"mean_m": np.full((4, 4), 1.2)}, r"target_valid \[..., 0\] must equal mean_m / sigma_m "
     "/ valid in 'strongest' order"),
    ({"valid": np.zeros((4, 4), bool)}, "target 0 is the primary reading"),
], ids=["T5", "2d", "sigma-shape", "valid-shape", "status-shape", "partial", "status-alone",
        "negative", "nan-sigma", "valid-strings", "mean-strings", "status-255", "status-300",
        "order", "primary-mean", "primary-valid"])
def test_bad_target_arrays_name_the_field(changes, message):
    with pytest.raises(ValueError, match=message):
        ZoneFrame(**_frame_fields(**changes))


def test_closest_order_does_not_tie_target_0_to_the_primary():
    frame = ZoneFrame(**_frame_fields(mean_m=np.full((4, 4), 3.0), target_order="closest"))
    assert frame.target_order == "closest" and frame.mean_m[0, 0] == 3.0


def test_several_targets_without_a_grid_say_how_to_read_them():
    with pytest.raises(ValueError, match=r"distance_mm has 128 entries; expected 16 \(4x4\) or 64 "
                                         r"\(8x8\), or pass grid= or targets_per_zone="):
        ZoneFrame.from_driver(*_driver_targets(64, 2))


def test_physical_error_names_targets_out_of_range():
    mean = np.full((4, 4, 2), 1.5, np.float32)
    mean[1, 2, 1] = 4.5
    frame = ZoneFrame(**_frame_fields(target_mean_m=mean))
    assert frame.physical_error() == (
        "1 valid target(s) read distances outside the VL53L5CX range 0 < d <= 4 m or have a "
        "sigma larger than it (zone 6 target 1: 4.5 m, sigma 0.02 m); mark such targets "
        "invalid")
    assert ZoneFrame(**_frame_fields()).physical_error() is None


def test_from_driver_refuses_metres_written_as_millimetres():
    """The sensor ranges from 20 mm: a frame whose every valid reading is below 10 "mm"
    holds metres, which would give depth a thousand times too near."""
    with pytest.raises(ValueError, match=r"distance_mm must be millimetres.*up to 3\.5.*metres"):
        ZoneFrame.from_driver(np.linspace(0.5, 3.5, 64), np.full(64, 0.01), np.full(64, 5))
    # Readings in millimetres, near ones included, are read as they are.
    near = ZoneFrame.from_driver(np.full(64, 25.0), np.full(64, 2.0), np.full(64, 5))
    assert near.valid.all() and near.mean_m[0, 0] == pytest.approx(0.025)


def test_a_4x4_reading_of_no_entries_or_too_many_targets_is_refused_by_name():
    with pytest.raises(ValueError, match="distance_mm has 0 entries"):
        ZoneFrame.from_driver([], [], [], grid=4)
    with pytest.raises(ValueError, match="at most 4 targets per zone"):
        ZoneFrame.from_driver(np.full(320, 1500.0), np.full(320, 5.0), np.full(320, 5), grid=4)
