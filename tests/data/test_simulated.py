"""Simulated ZJU-L5-layout sets on disk: the frame numbers are checked before writing."""

from __future__ import annotations

import re

import numpy as np
import pytest

from deltar.data.procedural import ProceduralReader
from deltar.data.simulated import simulate_set


@pytest.mark.parametrize(("indices", "shown"), [
    ([-1], "-1"), ([0, -3, -2], "-3 (and 1 more)"), ([1, 2], "2"), ([0.5], "0.5"),
    ([True], "True")])
def test_frame_numbers_outside_the_source_are_refused_before_anything_is_written(
        tmp_path, indices, shown):
    # Before, -1 wrote the last frame (its degradation drawn from -1, not its number) and
    # 2 failed after frame 1 had been simulated.
    source = ProceduralReader(2, 0, 32, 32)
    with pytest.raises(ValueError, match=rf"^indices must be frame numbers in 0\.\.1 of the "
                                         rf"2 frames of source, got {re.escape(shown)}"):
        simulate_set(source, tmp_path / "set", indices)
    assert not (tmp_path / "set").exists()


def test_a_set_of_chosen_frames_is_written(tmp_path):
    index, valid_counts = simulate_set(ProceduralReader(2, 0, 32, 32), tmp_path / "set", [1],
                                       grid=4)
    assert index.is_file() and len(valid_counts) == 1


def test_aligned_layout_covers_the_same_field_of_view_with_either_grid(tmp_path):
    # The release's 8x8 grid of 56 px zones spans 448 px at 640 px wide; a 4x4 grid of the
    # same sensor spans the same field of view with zones twice as wide (112 px). Before,
    # the 4x4 zones were 28 px: the grid covered a quarter of the width.
    from deltar.data.zju_l5 import ZJUL5Dataset

    source = ProceduralReader(1, 0, 480, 640)
    for grid, side in ((8, 56), (4, 112)):
        simulate_set(source, tmp_path / f"g{grid}", grid=grid, layout="aligned")
        rects = ZJUL5Dataset(tmp_path / f"g{grid}")[0].zone_rects
        np.testing.assert_array_equal(rects[:, 2:] - rects[:, :2], side)
        np.testing.assert_array_equal(rects[0, :2], [16, 96])
        np.testing.assert_array_equal(rects[-1, 2:], [464, 544])
