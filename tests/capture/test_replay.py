"""Replay of recordings: pairing by time, outputs, and bad recordings (gaps, unsorted,
corrupt)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.capture.bag_replay import replay_bag
from deltar.capture.drivers import SimulatedRig
from deltar.capture.record import record
from deltar.capture.replay import replay, replay_to_folder
from deltar.inference.estimator import DepthEstimator
from deltar.io.recording import Recording
from deltar.io.rosbag_reader import BagInput
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.placement import zone_mean_depth
from tests.capture.test_drivers import StepSource, _check_step_targets
from tests.capture.test_record import record_wall
from tests.inference.fakes import ZonePainterNet


def _estimator():
    return DepthEstimator(ZonePainterNet(), weights="painter")


def test_replay_pairs_by_nearest_time_and_predicts(tmp_path):
    record_wall(tmp_path / "rec", frames=8)
    items = list(replay(tmp_path / "rec", _estimator()))
    assert len(items) == 4
    for item in items:
        assert abs(item.pair.color_offset_s + 0.004) < 1e-6  # colour 4 ms before the zones
        pred = item.prediction
        assert pred.depth_m.shape == (48, 64)
        assert item.reference_depth_m is not None
        painted = zone_mean_depth(pred.zone_frame, pred.zone_rects, (48, 64))
        # The painter network reproduces the zone means inside the zones (1.02 m bins).
        inside = painted > 0
        assert np.median(np.abs(pred.depth_m[inside] - painted[inside])) < 1e-4


def test_replay_writes_outputs_outside_the_recording_only(tmp_path):
    record_wall(tmp_path / "rec", frames=4)
    written = replay_to_folder(tmp_path / "rec", _estimator(), tmp_path / "out",
                               kinds=("png16", "npy"))
    assert len(written) == 4 and all(p.parent == tmp_path / "out" for p in written)
    with pytest.raises(ValueError, match="inside the recording"):
        replay_to_folder(tmp_path / "rec", _estimator(), tmp_path / "rec" / "out")


def test_missing_images_are_skipped_with_a_warning(tmp_path):
    record_wall(tmp_path / "rec", frames=8)
    rec = Recording(tmp_path / "rec")
    # Remove the colour images next to the second zone frame (frames 2 and 3).
    for path in rec.color_paths[1:4]:
        path.unlink()
    with pytest.warns(UserWarning, match="skipped 1 of 4"):
        items = list(replay(tmp_path / "rec", _estimator()))
    assert len(items) == 3


def test_time_gaps_in_the_zone_stream_are_reported(tmp_path):
    record_wall(tmp_path / "rec", frames=16, sensor_hz=30.0)
    zones = tmp_path / "rec" / "zones.jsonl"
    lines = zones.read_text().splitlines()
    zones.write_text("\n".join(lines[:5] + lines[12:]) + "\n")  # drop 7 frames
    with pytest.warns(UserWarning, match="gap in the zone frames"):
        items = list(replay(tmp_path / "rec", _estimator()))
    assert len(items) == 9


def test_unsorted_timestamps_raise_naming_the_file(tmp_path):
    record_wall(tmp_path / "rec", frames=8)
    zones = tmp_path / "rec" / "zones.jsonl"
    lines = zones.read_text().splitlines()
    lines[1], lines[2] = lines[2], lines[1]
    zones.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"zones\.jsonl:3: unsorted timestamp"):
        list(replay(tmp_path / "rec", _estimator()))


def test_corrupt_image_raises_naming_the_file(tmp_path):
    record_wall(tmp_path / "rec", frames=4)
    rec = Recording(tmp_path / "rec")
    bad = rec.color_paths[0]
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    with pytest.raises(ValueError, match=bad.name):
        list(replay(tmp_path / "rec", _estimator()))


def test_a_failing_frame_is_reported_and_skipped_when_asked(tmp_path):
    record_wall(tmp_path / "rec", frames=6)
    rec = Recording(tmp_path / "rec")
    pairs = rec.pairs()
    bad = pairs[1].color_path
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    failed = []
    written = replay_to_folder(tmp_path / "rec", _estimator(), tmp_path / "out",
                               kinds=("npy",), on_failure=lambda p, e: failed.append((p, e)))
    assert [p.color_path for p, _ in failed] == [bad]
    assert isinstance(failed[0][1], ValueError) and bad.name in str(failed[0][1])
    assert sorted(p.name for p in written) == sorted(
        f"{p.color_path.stem}_depth_m.npy" for p in pairs if p.color_path != bad)
    # Without on_failure the same frame ends the replay.
    with pytest.raises(ValueError, match=bad.name):
        list(replay(tmp_path / "rec", _estimator()))


def test_calibration_for_another_resolution_is_refused(tmp_path):
    record_wall(tmp_path / "rec", frames=4)
    calib = RigCalibration(CameraIntrinsics(100, 100, 63.5, 47.5, 128, 96), SensorExtrinsics())
    with pytest.raises(ValueError, match="96x128"):
        list(replay(tmp_path / "rec", _estimator(), calibration=calib))


def test_images_of_another_size_than_the_recordings_meta_name_it(tmp_path):
    from PIL import Image

    record_wall(tmp_path / "rec", frames=4)
    rec = Recording(tmp_path / "rec")
    small = rec.color_paths[0]
    Image.open(small).resize((16, 12)).save(small)
    size = f"{rec.meta.intrinsics.height}x{rec.meta.intrinsics.width}"
    with pytest.raises(ValueError, match=f"{small.name} is 12x16 pixels but .*meta.json is "
                       f"for the calibrated resolution {size}; the recording's images and "
                       "its meta.json disagree"):
        list(replay(tmp_path / "rec", _estimator()))
    # The map's frames are read with the same check.
    from deltar.mapping.frames import FrameSource

    with pytest.raises(ValueError, match=f"{small.name} is 12x16 pixels but .*meta.json"):
        list(FrameSource(tmp_path / "rec").load())


def test_corrupt_zone_line_names_file_and_line(tmp_path):
    record_wall(tmp_path / "rec", frames=8)
    zones = tmp_path / "rec" / "zones.jsonl"
    lines = zones.read_text().splitlines()
    data = json.loads(lines[1])
    data["mean_m"][5] = float("nan")
    lines[1] = json.dumps(data)  # json.dumps writes NaN; the reader must refuse it
    zones.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(ValueError, match=r"zones\.jsonl:2"):
            list(replay(tmp_path / "rec", _estimator()))


def test_replay_pairs_with_the_calibrations_time_offset(tmp_path):
    record_wall(tmp_path / "rec", frames=8)  # colour 4 ms before each zone frame, 30 Hz
    meta = Recording(tmp_path / "rec").meta
    calib = RigCalibration(meta.intrinsics, SensorExtrinsics(), grid=meta.grid,
                           fov_deg=meta.fov_deg, time_offset_s=0.03)
    items = list(replay(tmp_path / "rec", _estimator(), calibration=calib))
    # Zone t pairs with the image nearest t + 30 ms: the next one, 29 ms after.
    assert all(abs(item.pair.color_offset_s - 0.0293) < 1e-3 for item in items)
    items = list(replay(tmp_path / "rec", _estimator(), calibration=calib, time_offset_s=0.0))
    assert all(abs(item.pair.color_offset_s + 0.004) < 1e-6 for item in items)


class FrameCollector:
    """Stands in for the estimator: keeps the zone frames replay hands it."""

    def __init__(self) -> None:
        self.frames = []

    def predict(self, image, zone_frame, calibration):
        self.frames.append(zone_frame)
        return None


@pytest.mark.parametrize("storage", [None, "sqlite3"])
def test_simulated_targets_survive_record_and_replay(tmp_path, storage):
    rig = SimulatedRig(StepSource(1.0, frames=4, height=96, width=128), max_targets=2)
    out = tmp_path / ("bag" if storage else "rec")
    record(out, rig, bag_storage=storage)
    collector = FrameCollector()
    if storage is None:
        items = list(replay(out, collector))
    else:
        items = list(replay_bag(BagInput(out), collector))
    assert len(items) == 2 == len(collector.frames)
    _check_step_targets(collector.frames)
    # The replayed signals are the simulated rig's.
    again = SimulatedRig(StepSource(1.0, frames=4, height=96, width=128), max_targets=2)
    recorded = [c.zone_frame for c in iter(again.grab, None) if c.zone_frame is not None]
    for replayed, original in zip(collector.frames, recorded, strict=True):
        np.testing.assert_allclose(replayed.target_signal, original.target_signal, rtol=1e-6)


def double_zone_frames(folder, after_s=0.008):
    """A second zone frame ``after_s`` after each (a sensor twice the camera's rate):
    both find the same image nearest."""
    path = folder / "zones.jsonl"
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    doubled = [d for line in lines
               for d in (line, {**line, "timestamp_s": line["timestamp_s"] + after_s})]
    path.write_text("".join(json.dumps(d) + "\n" for d in doubled))


def test_one_zone_frame_per_image_is_replayed_the_nearest(tmp_path):
    record_wall(tmp_path / "rec", frames=8)
    double_zone_frames(tmp_path / "rec")
    rec = Recording(tmp_path / "rec")
    pairs = rec.pairs()
    assert len(pairs) == 8 and len({p.color_path for p in pairs}) == 4
    with pytest.warns(UserWarning, match=r"4 of 8 zone frames share a colour image with a "
                      r"zone frame nearer to it in time and are left out"):
        written = replay_to_folder(tmp_path / "rec", _estimator(), tmp_path / "out",
                                   kinds=("npy",))
    # Each image once: the second zone frame neither refuses nor replaces the first.
    assert sorted(p.name for p in written) == sorted(f"{p.color_path.stem}_depth_m.npy"
                                                     for p in pairs[::2])
    with pytest.warns(UserWarning, match="share a colour image"):
        items = list(replay(rec, _estimator()))
    # The nearer of the two: 4 ms after its image, not 12 ms.
    assert [i.pair.zone_frame.timestamp_s for i in items] == \
        [p.zone_frame.timestamp_s for p in pairs[::2]]
