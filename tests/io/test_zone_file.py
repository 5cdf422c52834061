"""Zone-frame files: JSON / NPZ round trips, driver dumps, clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deltar.io.zone_file import (
    SCHEMA_VERSION,
    load_zone_frame,
    save_zone_frame,
    zone_frame_from_driver_result,
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
        (lambda d: d.update(schema_version=99), "schema_version"),
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
