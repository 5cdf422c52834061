from __future__ import annotations

import numpy as np
import pytest

from deltar.inference.zone_consistency import zone_consistency_field, zone_consistent_depth


def _grid_rects(height: int = 72, width: int = 120, grid: int = 8) -> np.ndarray:
    """(64, 4) rectangles tiling a (height, width) grid, cell centres at integer
    coordinates (each zone covers 9 x 15 cells, its centre on a cell)."""
    ys, xs = np.linspace(-0.5, height - 0.5, grid + 1), np.linspace(-0.5, width - 0.5, grid + 1)
    return np.array([(ys[r], xs[c], ys[r + 1], xs[c + 1]) for r in range(grid)
                     for c in range(grid)], dtype=np.float32)


def _centre(rects: np.ndarray, zone: int) -> tuple[int, int]:
    y0, x0, y1, x1 = rects[zone]
    return round(float(y0 + y1) / 2), round(float(x0 + x1) / 2)


def _wall(reading_m: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A flat wall's zone readings, sigmas and validity, and a depth map of it."""
    return (np.full(64, reading_m), np.full(64, 0.02), np.ones(64, bool),
            np.full((72, 120), reading_m, np.float32))


def test_the_field_is_each_zones_log_ratio_at_its_centre_and_moves_the_depth():
    rects = _grid_rects()
    mean, sigma, valid, depth = _wall()
    mean[27] = 2.08  # this zone reads 4 % farther than the network's depth there
    field = zone_consistency_field(depth, rects, mean, sigma, valid)
    assert field[_centre(rects, 27)] == pytest.approx(np.log(1.04), abs=1e-6)
    assert field[_centre(rects, 0)] == pytest.approx(0.0, abs=1e-7)
    # Half way between two zone centres, half of each (bilinear).
    (ya, xa), (_, xb) = _centre(rects, 27), _centre(rects, 28)
    assert field[ya, (xa + xb) // 2] == pytest.approx(np.log(1.04) / 2, abs=2e-3)
    moved = zone_consistent_depth(depth, rects, mean, sigma, valid, 0.5)
    assert moved[_centre(rects, 27)] == pytest.approx(2.0 * 1.04 ** 0.5, rel=1e-5)
    assert moved.dtype == np.float32 and moved.shape == depth.shape


def test_strength_zero_or_no_usable_zone_leave_the_depth_as_it_is():
    rects = _grid_rects()
    mean, sigma, valid, depth = _wall()
    mean[:] = 2.3
    assert zone_consistent_depth(depth, rects, mean, sigma, valid, 0.0) is not None
    np.testing.assert_array_equal(zone_consistent_depth(depth, rects, mean, sigma, valid, 0.0),
                                  depth)
    # Every reading 15 % off the depth: no footprint cell is on its zone's target.
    assert zone_consistency_field(depth, rects, mean, sigma, valid) is None
    np.testing.assert_array_equal(zone_consistent_depth(depth, rects, mean, sigma, valid, 1.0),
                                  depth)
    # No valid zone either.
    np.testing.assert_array_equal(
        zone_consistent_depth(depth, rects, *_wall()[:2], np.zeros(64, bool), 1.0), depth)


def test_a_zone_whose_target_lies_elsewhere_gives_no_ratio_and_takes_its_neighbours():
    rects = _grid_rects()
    mean, sigma, valid, depth = _wall()
    y0, x0, y1, x1 = np.ceil(rects[27]).astype(int)
    # Most of zone 27's footprint is a nearer object; the zone reports the wall behind it,
    # of which only a sliver is in its footprint (the network put the wall elsewhere).
    depth[y0:y1, x0:x1 - 2] = 1.0
    mean[27] = 2.02
    field = zone_consistency_field(depth, rects, mean, sigma, valid)
    assert field[_centre(rects, 27)] == pytest.approx(0.0, abs=1e-7)
    # With a quarter of the footprint on the target the zone counts (its ratio 2.02 / 2).
    depth[y0:y1, x0:x1] = 2.0
    depth[y0:y1, x0:x0 + 8] = 1.0  # 8 of 15 columns elsewhere: 7 on target
    field = zone_consistency_field(depth, rects, mean, sigma, valid)
    assert field[_centre(rects, 27)] == pytest.approx(np.log(1.01), abs=1e-6)


def test_invalid_zones_and_bad_arguments():
    rects = _grid_rects()
    mean, sigma, valid, depth = _wall()
    mean[27], valid[27] = 2.5, False  # an invalid zone's reading is not used
    field = zone_consistency_field(depth, rects, mean, sigma, valid)
    assert np.abs(field).max() < 1e-7
    with pytest.raises(ValueError, match="zone_consistency must be a number in"):
        zone_consistent_depth(depth, rects, mean, sigma, valid, 1.5)
    with pytest.raises(ValueError, match="zone_consistency"):
        zone_consistent_depth(depth, rects, mean, sigma, valid, float("nan"))
    with pytest.raises(ValueError, match="zone_rects"):
        zone_consistency_field(depth, rects[:60], mean, sigma, valid)
    with pytest.raises(ValueError, match="depth_m must be"):
        zone_consistency_field(depth[None], rects, mean, sigma, valid)
