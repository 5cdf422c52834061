"""The raw sensor painted where its zones fall (deltar.sensor.placement)."""

from __future__ import annotations

import numpy as np

from deltar.sensor.placement import zone_mean_depth
from deltar.sensor.zone_frame import ZoneFrame


def test_zone_mean_depth_paints_valid_zones_only():
    frame = ZoneFrame(np.arange(1, 17, dtype=float).reshape(4, 4) / 10, np.zeros((4, 4)),
                      np.eye(4, dtype=bool))
    rects = np.array([[r * 2 - 0.5, c * 2 - 0.5, r * 2 + 1.5, c * 2 + 1.5]
                      for r in range(4) for c in range(4)], dtype=np.float32)
    out = zone_mean_depth(frame, rects, (8, 8))
    expected = np.zeros((8, 8), np.float32)
    for k in range(4):
        expected[2 * k:2 * k + 2, 2 * k:2 * k + 2] = (k * 4 + k + 1) / 10
    np.testing.assert_allclose(out, expected)
