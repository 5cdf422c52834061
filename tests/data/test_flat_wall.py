"""Flat-wall scenes: geometry, the ``wall:`` source spec, the deprecated old module."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.camera import backproject
from deltar.data.flat_wall import FlatWallSource, flat_wall_frame, open_wall_source
from deltar.data.sources import open_source


def test_flat_wall_frame_geometry():
    frame = flat_wall_frame(2.0, 31, 41)
    assert frame.depth_m[15, 20] == pytest.approx(2.0)  # the principal point's ray
    np.testing.assert_allclose(frame.depth_m, 2.0, atol=1e-6)  # fronto-parallel
    tilted = flat_wall_frame(2.0, 31, 41, tilt_deg=20.0)
    assert tilted.depth_m[15, 20] == pytest.approx(2.0, abs=1e-6)
    points = backproject(tilted.depth_m, tilted.intrinsics)
    centred = points - points.mean(0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    assert np.abs(centred @ normal).max() < 1e-5  # all points on one plane
    assert abs(abs(normal[0]) - np.sin(np.deg2rad(20.0))) < 1e-4
    with pytest.raises(ValueError, match="distance_m"):
        flat_wall_frame(0.0)


def test_wall_source_spec():
    source = open_source("wall:1.5:3:48x64")
    assert isinstance(source, FlatWallSource) and len(source) == 3
    assert source[0].depth_m.shape == (48, 64)
    np.testing.assert_allclose(source[2].depth_m, 1.5, atol=1e-6)
    default = open_wall_source("wall:2")
    assert (len(default), default.height, default.width) == (10, 240, 320)
    for bad in ("wall:", "wall:x", "wall:1:2:3"):
        with pytest.raises(ValueError, match=f"wall source must look like .*got {bad!r}"):
            open_source(bad)
    with pytest.raises(ValueError, match="wall sources define their own camera"):
        open_source("wall:1", depth_scale=1000.0)

