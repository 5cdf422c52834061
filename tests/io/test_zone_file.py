"""Zone-frame files: JSON / NPZ round trips, driver dumps, clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deltar.io.zone_file import (
    SCHEMA_VERSION,
    load_zone_frame,
    save_zone_frame,
    zone_frame_from_dict,
    zone_frame_from_driver_result,
    zone_frame_to_dict,
)
from deltar.sensor.zone_frame import Orientation, ZoneFrame


def _frame(rng: np.random.Generator, grid: int = 8, with_hist: bool = True) -> ZoneFrame:
    zones = grid * grid
    valid = rng.random(zones) > 0.2
    mean = np.where(valid, rng.uniform(0.2, 3.5, zones), 0.0)
    sigma = np.where(valid, rng.uniform(0.0, 0.1, zones), 0.0)
    hist = dict(hist_edges_m=np.linspace(0, 4, 101),
                hist_counts=rng.integers(0, 50, (zones, 100)).astype(float)) if with_hist else {}
    return ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid,
                     status=np.where(valid, 5, 255).astype(np.uint8), timestamp_s=12.25,
                     sensor_model="VL53L8CX", **hist)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
@pytest.mark.parametrize("grid", [4, 8])
def test_round_trip_keeps_every_field(tmp_path, rng, suffix, grid):
    frame = _frame(rng, grid)
    path = save_zone_frame(tmp_path / f"frame{suffix}", frame)
    back = load_zone_frame(path)
    assert back.grid == grid
    np.testing.assert_allclose(back.mean_m, frame.mean_m, atol=1e-6)
    np.testing.assert_allclose(back.sigma_m, frame.sigma_m, atol=1e-6)
    np.testing.assert_array_equal(back.valid, frame.valid)
    np.testing.assert_array_equal(back.status, frame.status)
    np.testing.assert_array_equal(back.no_target, frame.no_target)
    assert back.no_target.any()
    np.testing.assert_allclose(back.hist_counts, frame.hist_counts)
    np.testing.assert_allclose(back.hist_edges_m, frame.hist_edges_m, atol=1e-6)
    assert back.timestamp_s == 12.25
    assert back.sensor_model == "VL53L8CX"


def test_json_layout_is_flat_row_major_and_versioned(tmp_path, rng):
    frame = _frame(rng, with_hist=False)
    path = save_zone_frame(tmp_path / "f.json", frame)
    data = json.loads(path.read_text())
    assert data["schema_version"] == SCHEMA_VERSION
    assert data["zone_count"] == 64
    # Zone (r, c) is entry r * 8 + c.
    assert data["mean_m"][2 * 8 + 5] == pytest.approx(float(frame.mean_m[2, 5]), abs=1e-6)
    assert "hist_counts" not in data


def test_save_refuses_to_overwrite(tmp_path, rng):
    path = save_zone_frame(tmp_path / "f.json", _frame(rng))
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        save_zone_frame(path, _frame(rng))
    assert path.read_bytes() == before


def test_driver_dump_json_is_converted(tmp_path):
    # 16 zones, driver order; zone 3 has status 255 (no target) -> invalid.
    distance = [1000 + 10 * i for i in range(16)]
    status = [5] * 16
    status[3] = 255
    dump = {"distance_mm": distance, "range_sigma_mm": [7] * 16, "target_status": status,
            "timestamp_s": 3.5}
    path = tmp_path / "raw.json"
    path.write_text(json.dumps(dump))
    frame = load_zone_frame(path)
    assert frame.grid == 4
    assert frame.mean_m[0, 2] == pytest.approx(1.02)
    assert not frame.valid[0, 3] and frame.mean_m[0, 3] == 0.0
    assert frame.sigma_m[1, 1] == pytest.approx(0.007)
    assert frame.timestamp_s == 3.5
    # Up-down flip as the vl53l5cx-ctypes example does: driver row 0 becomes image row 3.
    flipped = load_zone_frame(path, orientation=Orientation(flip_ud=True))
    assert flipped.mean_m[3, 2] == pytest.approx(1.02)


def test_a_4x4_dump_of_the_8x8_sized_driver_buffer_reads_its_first_16_zones(tmp_path):
    """ST's results buffer holds 64 entries per target whatever the resolution; in 4x4
    mode the first 16 are filled (the rest stale): the dump's grid says which."""
    distance = [1000 + 10 * i for i in range(16)] + [0] * 48
    dump = {"distance_mm": distance, "range_sigma_mm": [7] * 64, "target_status": [5] * 64,
            "grid": 4}
    path = tmp_path / "raw4.json"
    path.write_text(json.dumps(dump))
    frame = load_zone_frame(path)
    assert frame.grid == 4 and frame.valid.all() and frame.targets_per_zone == 1
    np.testing.assert_allclose(frame.mean_m.reshape(-1), np.arange(1000, 1160, 10) / 1000)
    # The same with the driver's 64 target counts beside the grid.
    with_counts = dict(dump, nb_target_detected=[1] * 16 + [0] * 48)
    path.write_text(json.dumps(with_counts))
    np.testing.assert_array_equal(load_zone_frame(path).mean_m, frame.mean_m)
    # A compact dump of 16 zones x 4 targets says so.
    compact = {"distance_mm": [1500] * 64, "range_sigma_mm": [7] * 64,
               "target_status": [5] * 64, "grid": 4, "targets_per_zone": 4}
    path.write_text(json.dumps(compact))
    assert load_zone_frame(path).target_mean_m.shape == (4, 4, 4)
    for bad, message in (({"grid": 5}, "grid must be 4 or 8"),
                         ({"range_sigma_mm": None}, "range_sigma_mm missing")):
        broken = {k: v for k, v in dict(dump, **bad).items() if v is not None}
        path.write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=message):
            load_zone_frame(path)


def test_driver_results_object_is_converted():
    class Results:  # what sparkfun / vl53l5cx-ctypes hand back: attributes, flat lists
        distance_mm = [500] * 64
        range_sigma_mm = [3] * 64
        target_status = [9] * 64

    frame = zone_frame_from_driver_result(Results(), timestamp_s=1.0)
    assert frame.grid == 8 and frame.valid.all()
    assert np.allclose(frame.mean_m, 0.5)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(mean_m=d["mean_m"][:60]), "zones"),
        (lambda d: d.update(zone_count=16), "zone count"),
        (lambda d: d["mean_m"].__setitem__(4, -1.0), "negative"),
        (lambda d: d.update(schema_version=99), "unsupported schema_version 99"),
        (lambda d: d.pop("schema_version"), "no schema_version"),
        (lambda d: d.pop("valid"), "missing keys"),
        (lambda d: d.update(no_target=[2] * 64), "no_target must hold 64 booleans"),
        (lambda d: d.update(no_target=[True] * 64), "no_target marks valid zones"),
    ],
)
def test_bad_content_names_file_and_problem(tmp_path, rng, edit, message):
    data = json.loads(save_zone_frame(tmp_path / "ok.json", _frame(rng)).read_text())
    edit(data)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message) as info:
        load_zone_frame(bad)
    assert "bad.json" in str(info.value)


def test_nan_and_corrupt_json_are_rejected(tmp_path, rng):
    data = json.loads(save_zone_frame(tmp_path / "ok.json", _frame(rng)).read_text())
    text = json.dumps(data).replace(str(data["mean_m"][0]), "NaN", 1)
    (tmp_path / "nan.json").write_text(text)
    with pytest.raises(ValueError, match="NaN"):
        load_zone_frame(tmp_path / "nan.json")
    (tmp_path / "cut.json").write_text(json.dumps(data)[:100])
    with pytest.raises(ValueError, match="corrupt JSON"):
        load_zone_frame(tmp_path / "cut.json")
    with pytest.raises(FileNotFoundError, match=r"missing\.json"):
        load_zone_frame(tmp_path / "missing.json")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"junk\.npz"):
        load_zone_frame(tmp_path / "junk.npz")


def _target_frame(rng: np.random.Generator, grid: int = 8, per_zone: int = 3,
                  order: str = "strongest", with_status: bool = True,
                  timestamp_s: float = 12.25, with_signal: bool = True) -> ZoneFrame:
    zones = grid * grid
    valid = rng.random((zones, per_zone)) > 0.3
    mean = np.where(valid, rng.uniform(0.2, 3.9, (zones, per_zone)), 0.0)
    sigma = np.where(valid, rng.uniform(0.0, 0.1, (zones, per_zone)), 0.0)
    status = np.where(valid, 5, 255 * (rng.random((zones, per_zone)) > 0.5)).astype(np.uint8)
    signal = np.where(valid, rng.uniform(0.5, 800.0, (zones, per_zone)), 0.0)
    return ZoneFrame(mean_m=mean[:, 0], sigma_m=sigma[:, 0], valid=valid[:, 0],
                     status=status[:, 0] if with_status else None, timestamp_s=timestamp_s,
                     sensor_model="VL53L8CX", target_mean_m=mean, target_sigma_m=sigma,
                     target_valid=valid, target_status=status if with_status else None,
                     target_order=order, target_signal=signal if with_signal else None)


def _assert_same_targets(back: ZoneFrame, frame: ZoneFrame) -> None:
    assert back.targets_per_zone == frame.targets_per_zone
    assert back.target_order == frame.target_order
    np.testing.assert_array_equal(back.target_valid, frame.target_valid)
    np.testing.assert_allclose(back.target_mean_m, frame.target_mean_m, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.target_sigma_m, frame.target_sigma_m, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(back.valid, frame.valid)
    np.testing.assert_allclose(back.mean_m, frame.mean_m, atol=1e-6, rtol=0)
    assert (back.target_signal is None) == (frame.target_signal is None)
    if frame.target_signal is not None:
        np.testing.assert_allclose(back.target_signal, frame.target_signal, rtol=1e-6)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
@pytest.mark.parametrize("grid, per_zone, order", [(8, 3, "strongest"), (4, 2, "closest"),
                                                   (8, 1, "strongest")])
def test_zone_file_round_trip_keeps_every_target(tmp_path, rng, suffix, grid, per_zone, order):
    frame = _target_frame(rng, grid, per_zone, order)
    back = load_zone_frame(save_zone_frame(tmp_path / f"frame{suffix}", frame))
    _assert_same_targets(back, frame)
    np.testing.assert_array_equal(back.target_status, frame.target_status)


def test_single_target_files_are_unchanged_and_old_files_read(tmp_path, rng):
    frame = _target_frame(rng)
    single = ZoneFrame(mean_m=frame.mean_m, sigma_m=frame.sigma_m, valid=frame.valid,
                       status=frame.status, timestamp_s=frame.timestamp_s,
                       sensor_model=frame.sensor_model)
    data = zone_frame_to_dict(single)
    assert sorted(data) == ["mean_m", "no_target", "schema", "schema_version", "sensor_model",
                            "sigma_m", "status", "timestamp_s", "valid", "zone_count"]
    # A file written before the target keys existed: no targets, T = 1 from the primary.
    path = tmp_path / "old.json"
    path.write_text(json.dumps(data))
    back = load_zone_frame(path)
    assert back.target_mean_m is None and back.targets_per_zone == 1
    np.testing.assert_array_equal(back.targets()[2][..., 0], frame.valid)
    # With targets, the extra keys and nothing else change.
    with_targets = zone_frame_to_dict(frame)
    assert {k: v for k, v in with_targets.items() if k in data} == data
    assert sorted(set(with_targets) - set(data)) == [
        "target_mean_m", "target_order", "target_sigma_m", "target_signal", "target_status",
        "target_valid", "targets_per_zone"]
    assert np.shape(with_targets["target_mean_m"]) == (64, 3)
    assert np.shape(with_targets["target_signal"]) == (64, 3)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_target_signal_is_optional(tmp_path, rng, suffix):
    frame = _target_frame(rng, with_signal=False)
    assert "target_signal" not in zone_frame_to_dict(frame)
    back = load_zone_frame(save_zone_frame(tmp_path / f"frame{suffix}", frame))
    assert back.target_signal is None
    _assert_same_targets(back, frame)
    # A file with targets written before the signal key existed reads the same.
    data = zone_frame_to_dict(_target_frame(rng))
    del data["target_signal"]
    path = tmp_path / "old_targets.json"
    path.write_text(json.dumps(data))
    back = load_zone_frame(path)
    assert back.target_signal is None and back.targets_per_zone == 3


@pytest.mark.parametrize("edit, message", [
    ({"target_valid": None}, r"target keys .* need \['target_valid'\]"),
    ({"targets_per_zone": None}, r"need \['targets_per_zone'\]"),
    ({"targets_per_zone": 5}, "targets_per_zone must be an integer in 1..4, got 5"),
    ({"targets_per_zone": 2}, r"target_mean_m must be \(64, 2\)"),
    ({"target_mean_m": [[1.0] * 3] * 63}, r"target_mean_m must be \(64, 3\)"),
    ({"target_sigma_m": [[-1.0] * 3] * 64}, "target_sigma_m has negative values"),
    ({"target_mean_m": [["1.0"] * 3] * 64}, "target_mean_m must hold numbers"),
    ({"target_valid": [["yes"] * 3] * 64}, "target_valid must hold 192 booleans"),
    ({"target_order": "nearest"}, "ZoneFrame.target_order must be one of"),
    ({"target_order": 3}, "target_order must be a string"),
    ({"target_signal": [[-1.0] * 3] * 64}, "target_signal has negative values"),
    ({"target_signal": [[1.0] * 2] * 64}, r"target_signal must be \(64, 3\)"),
    ({"target_signal": [["1.0"] * 3] * 64}, "target_signal must hold numbers"),
    ({"target_signal": [[float("nan")] * 3] * 64}, "target_signal has NaN"),
    ({"target_signal": [[True] * 3] * 64}, "target_signal must hold numbers"),
], ids=["no-valid", "no-count", "count-5", "count-mismatch", "shape", "negative", "strings",
        "valid-strings", "order", "order-number", "signal-negative", "signal-shape",
        "signal-strings", "signal-nan", "signal-bools"])
def test_bad_target_keys_name_the_file_and_key(tmp_path, rng, edit, message):
    data = zone_frame_to_dict(_target_frame(rng))
    data.update(edit)
    data = {k: v for k, v in data.items() if v is not None}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message) as caught:
        load_zone_frame(path)
    assert str(path) in str(caught.value)


def test_driver_dumps_and_results_with_several_targets(tmp_path):
    distance = np.repeat(np.arange(16) * 100.0 + 500, 2)
    distance[1::2] += 1500
    dump = {"distance_mm": distance.tolist(), "range_sigma_mm": [10] * 32,
            "target_status": [5] * 32, "nb_target_detected": [2] * 15 + [1],
            "target_order": "closest"}
    path = tmp_path / "dump.json"
    path.write_text(json.dumps(dump))
    frame = load_zone_frame(path)
    assert frame.grid == 4 and frame.targets_per_zone == 2 and frame.target_order == "closest"
    assert frame.flat_targets()[2][:, 1].tolist() == [True] * 15 + [False]
    np.testing.assert_allclose(frame.flat_targets()[0][0], [0.5, 2.0], atol=1e-6)

    class Results:  # a driver's results object (attributes, as vl53l5cx-ctypes)
        def __init__(self) -> None:
            self.distance_mm = list(distance)
            self.range_sigma_mm = [10] * 32
            self.target_status = [5] * 32
            self.nb_target_detected = [1] * 16

    frame = zone_frame_from_driver_result(Results(), targets_per_zone=2)
    assert frame.targets_per_zone == 2 and not frame.target_valid[..., 1].any()
    with pytest.raises(ValueError, match=r"dump\.json: invalid driver output: target_order"):
        zone_frame_from_dict({**dump, "target_order": "nearest"}, source=str(path))


def test_a_driver_dict_counting_more_than_four_targets_in_a_zone_is_refused(tmp_path):
    reading = {"distance_mm": [1000.0] * 16, "range_sigma_mm": [10.0] * 16,
               "target_status": [5] * 16, "nb_target_detected": [1] * 15 + [9]}
    with pytest.raises(ValueError, match=r"nb_target_detected must hold target counts in "
                       r"0\.\.4 .*got 9 for zone 15"):
        zone_frame_from_driver_result(reading)
    path = tmp_path / "dump.json"
    path.write_text(json.dumps(reading))
    with pytest.raises(ValueError, match=r"dump\.json: .*nb_target_detected must hold "
                       r"target counts in 0\.\.4"):
        load_zone_frame(path)


def test_driver_signal_per_spad_becomes_the_target_signal(tmp_path):
    distance = np.repeat(np.arange(16) * 100.0 + 500, 2)
    distance[1::2] += 1500
    signal = np.tile([300.0, 40.0], 16)
    dump = {"distance_mm": distance.tolist(), "range_sigma_mm": [10] * 32,
            "target_status": [5] * 32, "signal_per_spad": signal.tolist(), "targets_per_zone": 2}
    path = tmp_path / "dump.json"
    path.write_text(json.dumps(dump))
    frame = load_zone_frame(path)
    np.testing.assert_allclose(frame.flat_targets()[0][3], [0.8, 2.3], atol=1e-6)
    np.testing.assert_allclose(frame.target_signal.reshape(16, 2)[3], [300.0, 40.0])
    with pytest.raises(ValueError, match=r"dump\.json: signal_per_spad must hold numbers"):
        zone_frame_from_dict({**dump, "signal_per_spad": ["1"] * 32}, source=str(path))

    class Results:  # a driver's results object (attributes, as vl53l5cx-ctypes)
        def __init__(self, per_zone: int) -> None:
            self.distance_mm = [1000.0] * 16 * per_zone
            self.range_sigma_mm = [10] * 16 * per_zone
            self.target_status = [5] * 16 * per_zone
            self.signal_per_spad = [120.0] * 16 * per_zone + [7.0] * 5  # longer buffer

    with pytest.raises(ValueError, match="signal_per_spad"):
        zone_frame_from_driver_result(Results(2), targets_per_zone=2)
    results = Results(2)
    results.signal_per_spad = results.signal_per_spad[:32]
    frame = zone_frame_from_driver_result(results, targets_per_zone=2)
    assert frame.target_signal.shape == (4, 4, 2) and np.all(frame.target_signal == 120.0)
    # One target per zone: no target arrays, the signal is not read.
    single = zone_frame_from_driver_result(Results(1))
    assert single.target_mean_m is None and single.target_signal is None


def test_a_driver_orientation_is_refused_for_a_schema_file(tmp_path):
    from deltar.io.zone_file import load_zone_frame, save_zone_frame
    from deltar.sensor.zone_frame import Orientation, ZoneFrame

    path = tmp_path / "z.json"
    save_zone_frame(path, ZoneFrame(np.full(64, 1.5), np.full(64, 0.02), np.ones(64, bool)))
    assert load_zone_frame(path, orientation=Orientation()).valid_count == 64  # identity
    with pytest.raises(ValueError, match=r"z\.json: a zone file in deltar's schema is "
                                         r"already in image orientation"):
        load_zone_frame(path, orientation=Orientation(flip_ud=True))


def _dump(**extra):
    return {"distance_mm": [1000] * 64, "range_sigma_mm": [5] * 64,
            "target_status": [5] * 64, **extra}


@pytest.mark.parametrize("data, message", [
    (_dump(grid=8.0), r"zones\.json: grid must be 4 or 8 \(the driver's resolution\), got 8\.0"),
    (_dump(timestamp_s=float("nan")), r"^\S*zones\.json: timestamp_s must be finite"),
])
def test_driver_dump_settings_name_the_file_and_key_once(tmp_path, data, message):
    path = tmp_path / "zones.json"
    path.write_text(json.dumps(data))  # NaN written as JSON's NaN, as Python does
    with pytest.raises(ValueError, match=message) as info:
        load_zone_frame(path)
    assert "invalid driver output" not in str(info.value)


def test_schema_version_true_is_not_version_1(tmp_path, rng):
    data = zone_frame_to_dict(_frame(rng, with_hist=False))
    data["schema_version"] = True
    with pytest.raises(ValueError, match="unsupported schema_version True"):
        zone_frame_from_dict(data, source="z.json")


def test_driver_grid_float_is_refused_in_python_too():
    with pytest.raises(ValueError, match=r"grid must be one of \(4, 8\), got 8\.0"):
        ZoneFrame.from_driver([1000] * 64, [5] * 64, [5] * 64, grid=8.0)
