"""Recording a simulated rig: the folder layout, no overwriting."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from deltar.capture.drivers import SimulatedRig
from deltar.capture.record import record
from deltar.data.flat_wall import FlatWallSource
from deltar.io.recording import Recording


def record_wall(folder, frames=8, distance=1.01, sensor_hz=15.0):
    """A simulated rig in front of a flat wall at ``distance`` metres, recorded."""
    rig = SimulatedRig(FlatWallSource(distance, frames, 48, 64), sensor_hz=sensor_hz)
    return record(folder, rig)


def _digest(folder):
    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_simulated_recording_layout(tmp_path):
    summary = record_wall(tmp_path / "rec", frames=8)
    assert (summary.images, summary.zone_frames, summary.depth_maps) == (8, 4, 8)
    rec = Recording(tmp_path / "rec")
    assert rec.meta.intrinsics.width == 64 and rec.meta.grid == 8
    assert len(rec.color_paths) == 8 and len(rec.depth_paths) == 8
    times = [f.timestamp_s for f in rec.zone_frames()]
    np.testing.assert_allclose(times, np.arange(0, 8, 2) / 30.0 + 0.004)


def test_recording_never_overwrites(tmp_path):
    folder = tmp_path / "rec"
    record_wall(folder)
    before = _digest(folder)
    with pytest.raises(FileExistsError):
        record_wall(folder)  # same clock: the first colour image already exists
    assert _digest(folder) == before
