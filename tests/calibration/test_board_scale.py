"""The printed board's size against its spec, from its views and the zones' planes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deltar.calibration.board import parse_board_spec
from deltar.calibration.board_scale import board_scale, warn_board_scale

SPEC = parse_board_spec("charuco:7x5:0.04:0.03:DICT_5X5_100")


def _views(printed: float, noise_m: float = 0.0, count: int = 10, seed: int = 0):
    """Board planes as its pose gives them for a board printed ``printed`` times the
    spec's size, and the zones' planes of a sensor 4 cm beside the camera."""
    rng = np.random.default_rng(seed)
    sensor_in_camera = np.array([0.04, -0.02, 0.01])
    normals = Rotation.from_euler("xy", rng.uniform(-40, 40, (count, 2)), degrees=True) \
        .apply([0.0, 0.0, -1.0])
    true_offsets = rng.uniform(0.5, 0.9, count)
    board_offsets = true_offsets / printed  # its pose places it 1 / printed too far
    zone_offsets = true_offsets + normals @ sensor_in_camera + rng.normal(0, noise_m, count)
    return normals, board_offsets, zone_offsets


@pytest.mark.parametrize("printed", [0.94, 1.0, 1.1])
def test_the_scale_is_recovered(printed):
    scale, error = board_scale(*_views(printed))
    assert scale == pytest.approx(printed, abs=1e-9) and error < 1e-9
    scale, error = board_scale(*_views(printed, noise_m=0.003))
    assert abs(scale - printed) < 4 * error + 1e-3 and error < 0.02


def test_a_board_printed_small_is_warned_about_and_a_right_one_is_not():
    with pytest.warns(UserWarning, match=r"printed at 0\.9[0-9]+ times .* about 37\.[0-9] mm "
                                         r"rather than 40 mm"):
        normals, board, zones = _views(0.94, noise_m=0.002)
        off_m = warn_board_scale(normals, board, zones, SPEC)
    # |1 - k| times the median distance the board's pose gives (0.7 / 0.94 m or so).
    assert off_m == pytest.approx(0.06 * np.median(board), rel=0.2) and off_m > 0.03
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_board_scale(*_views(1.0, noise_m=0.002), SPEC) == 0.0
        assert warn_board_scale(*_views(0.9, count=4), SPEC) is None  # too few views
