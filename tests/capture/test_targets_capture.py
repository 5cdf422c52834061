"""Several targets per zone through capture: driver adapters, simulated rigs, record and
replay (folders and bags)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from deltar.capture.bag_replay import replay_bag
from deltar.capture.drivers import DriverAdapter, SimulatedRig
from deltar.capture.record import record
from deltar.capture.replay import replay
from deltar.data.flat_wall import FlatWallSource
from deltar.io.rosbag_reader import BagInput
from deltar.sensor.zone_frame import Orientation


class MultiTargetDriver:
    """Results like ST's ULD built with two targets per zone, buffers sized for 8x8."""

    def __init__(self) -> None:
        self.distance_mm = np.repeat(np.arange(64) * 10.0 + 800, 2)
        self.distance_mm[1::2] += 1500
        self.range_sigma_mm = [5] * 128
        self.target_status = [5] * 128
        self.nb_target_detected = [2] * 63 + [1]

    def data_ready(self):
        return True

    def get_data(self):
        return self

    def start_ranging(self):
        pass

    def stop_ranging(self):
        pass


def test_driver_adapter_reads_every_target():
    frame = DriverAdapter(MultiTargetDriver(), targets_per_zone=2,
                          orientation=Orientation(flip_ud=True), poll_interval_s=0.0).read()
    assert frame.grid == 8 and frame.targets_per_zone == 2
    # Driver zone 56 (row 7, column 0) is image zone (0, 0) after the flip.
    np.testing.assert_allclose(frame.target_mean_m[0, 0], [1.36, 2.86], atol=1e-6)
    # Driver zone 63 (one target detected) is image zone (0, 7).
    assert not frame.target_valid[0, 7, 1] and frame.target_valid[0, 7, 0]
    np.testing.assert_array_equal(frame.mean_m, frame.target_mean_m[..., 0])
    # 4x4 mode: the first 16 zones of the 8x8-sized buffers.
    frame = DriverAdapter(MultiTargetDriver(), grid=4, targets_per_zone=2,
                          poll_interval_s=0.0).read()
    assert frame.grid == 4
    np.testing.assert_allclose(frame.flat_targets()[0][15], [0.95, 2.45], atol=1e-6)
    with pytest.raises(ValueError, match=r"targets_per_zone must be an integer in 1\.\.4"):
        DriverAdapter(MultiTargetDriver(), targets_per_zone=0)
    with pytest.raises(ValueError, match="target_order must be"):
        DriverAdapter(MultiTargetDriver(), target_order="nearest")


class StepSource(FlatWallSource):
    """Flat-wall frames with the right part of the wall 1.5 m farther away."""

    def __getitem__(self, index):
        frame = super().__getitem__(index)
        depth = frame.depth_m.copy()
        depth[:, depth.shape[1] * 9 // 16:] += 1.5  # through the middle of a zone column
        return dataclasses.replace(frame, depth_m=depth)


class FrameCollector:
    """Stands in for the estimator: keeps the zone frames replay hands it."""

    def __init__(self) -> None:
        self.frames = []

    def predict(self, image, zone_frame, calibration):
        self.frames.append(zone_frame)
        return None


def _check_step_targets(frames) -> None:
    assert frames and all(f.targets_per_zone == 2 for f in frames)
    for frame in frames:
        np.testing.assert_array_equal(frame.target_valid[..., 0], frame.valid)
        second = frame.target_valid[..., 1]
        assert second.any()  # the zones on the step see both surfaces
        # Both surfaces, one as each target.
        pairs = np.sort(frame.target_mean_m[second], axis=-1)
        np.testing.assert_allclose(pairs, np.broadcast_to([1.0, 2.5], pairs.shape), atol=0.03)


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


def test_simulated_rig_without_histogram_keeps_the_targets():
    rig = SimulatedRig(StepSource(1.0, frames=1, height=96, width=128), max_targets=2)
    frame = rig.grab().zone_frame
    assert frame.hist_counts is None and frame.targets_per_zone == 2
    _check_step_targets([frame])
    single = SimulatedRig(StepSource(1.0, frames=1, height=96, width=128)).grab().zone_frame
    assert single.target_mean_m is None
    np.testing.assert_array_equal(single.mean_m, frame.mean_m)
    with pytest.raises(ValueError, match=r"max_targets must be an integer in 1\.\.4"):
        SimulatedRig(StepSource(1.0, frames=1), max_targets=5)
