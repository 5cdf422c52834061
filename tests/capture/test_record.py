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


def test_a_rigs_poses_are_recorded_with_their_images_and_appending_continues(tmp_path):
    from deltar.mapping.poses import read_pose_folder

    source = FlatWallSource(1.2, 6, 48, 64)
    poses = [np.eye(4) for _ in range(6)]
    for i, pose in enumerate(poses):
        pose[:3, 3] = (0.1 * i, 0.0, 0.0)
    poses[4] = None  # a frame without a pose: recorded without one
    folder = tmp_path / "rec"
    summary = record(folder, SimulatedRig(source, poses=poses))
    assert (summary.images, summary.poses) == (6, 5)
    found = read_pose_folder(folder / "pose")
    by_time = sorted(range(len(found.names)), key=lambda k: int(found.names[k]))
    colour_names = [p.stem for p in Recording(folder).color_paths]
    assert [found.names[k] for k in by_time] == [colour_names[i] for i in (0, 1, 2, 3, 5)]
    np.testing.assert_allclose(found.poses[by_time, 0, 3], [0.0, 0.1, 0.2, 0.3, 0.5])
    with pytest.raises(ValueError, match="poses: 2 for a source of 6 frames"):
        SimulatedRig(source, poses=poses[:2])
    # Appending: a clock that starts after the recording's end adds to it.
    end = Recording(folder).end_time_s()
    before, zone_lines = _digest(folder), (folder / "zones.jsonl").read_text()
    again = record(folder, SimulatedRig(source, poses=poses, start_time_s=end + 1 / 30))
    assert again.poses == 5
    after = _digest(folder)
    assert all(after[name] == digest for name, digest in before.items()
               if name.name != "zones.jsonl")
    assert (folder / "zones.jsonl").read_text().startswith(zone_lines)
    rec = Recording(folder)
    assert len(rec.color_paths) == 12 and len(read_pose_folder(folder / "pose").names) == 10
    times = [f.timestamp_s for f in rec.zone_frames()]
    assert np.all(np.diff(times) > 0) and len(times) == 6
