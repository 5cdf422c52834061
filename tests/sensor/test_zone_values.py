"""Zone value helpers: each zone's neighbours."""

from __future__ import annotations

import numpy as np

from deltar.sensor.zone_values import NEIGHBOURS_3x3, zone_neighbours


def test_zone_neighbours_read_each_offset_and_fill_off_the_grid():
    values = np.arange(16, dtype=np.float32).reshape(4, 4)
    offsets = (*NEIGHBOURS_3x3, (2, -2))
    stack = zone_neighbours(values, offsets, fill=-np.inf)
    assert stack.shape == (9, 4, 4) and stack.dtype == np.float32
    for k, (dy, dx) in enumerate(offsets):
        for y in range(4):
            for x in range(4):
                inside = 0 <= y + dy < 4 and 0 <= x + dx < 4
                expected = values[y + dy, x + dx] if inside else -np.inf
                assert stack[k, y, x] == expected
    assert np.isnan(zone_neighbours(values)[0, 0, 0])  # NaN by default


def test_zone_neighbours_order_is_row_by_row():
    assert NEIGHBOURS_3x3 == ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0),
                              (1, 1))
