"""What chained odometry reports: the camera's speed, to tell a sequence from unrelated
frames."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.mapping.odometry import MAX_CAMERA_SPEED_M_S, median_speed
from tests.mapping.conftest import pose_at


def test_median_speed_of_a_walk_and_of_jumps():
    times = np.arange(6) / 30.0
    walk = np.stack([pose_at(0.02 * i, yaw_deg=i) for i in range(6)])  # 0.6 m/s
    assert median_speed(walk, times) == pytest.approx(0.6, rel=1e-6)
    assert median_speed(walk, times) < MAX_CAMERA_SPEED_M_S
    jumps = np.stack([pose_at(0.5 * (i % 2)) for i in range(6)])  # 15 m/s back and forth
    assert median_speed(jumps, times) == pytest.approx(15.0, rel=1e-6)
    assert median_speed(walk[:1], times[:1]) == 0.0
