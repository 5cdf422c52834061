"""Sensor adapters (with a fake driver), driver import errors, the simulated rig."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from deltar.capture.drivers import (
    DriverAdapter,
    SimulatedRig,
    open_circuitpython,
    open_sparkfun,
    open_vl53l5cx_ctypes,
)
from deltar.data.flat_wall import FlatWallSource
from deltar.sensor.zone_frame import Orientation


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += 0.001
        return self.now


class FakeDriver:
    """Mimics a driver: ready after ``polls`` calls, results like ST's ULD (mm, status)."""

    def __init__(self, polls: int = 2) -> None:
        self.polls, self.calls, self.started, self.stopped = polls, 0, False, False
        self.distance_mm = list(range(1000, 1064))
        self.range_sigma_mm = [5] * 64
        self.target_status = [5] * 63 + [255]

    def start_ranging(self):
        self.started = True

    def stop_ranging(self):
        self.stopped = True

    def data_ready(self):
        self.calls += 1
        return self.calls >= self.polls

    def get_data(self):
        self.calls = 0
        return self


def test_adapter_converts_driver_results_to_metres():
    driver, clock = FakeDriver(), FakeClock()
    with DriverAdapter(driver, clock=clock, poll_interval_s=0.0) as sensor:
        assert driver.started
        frame = sensor.read()
    assert driver.stopped
    mean, sigma, valid = frame.flat()
    np.testing.assert_allclose(mean[:63], np.arange(1000, 1063) / 1000.0, rtol=1e-6)
    assert sigma[0] == pytest.approx(0.005)
    assert not valid[63] and valid[:63].all()  # status 255 = no target
    assert 100.0 < frame.timestamp_s < 100.01


def test_adapter_applies_orientation():
    driver = FakeDriver(polls=1)
    frame = DriverAdapter(driver, orientation=Orientation(flip_ud=True),
                          poll_interval_s=0.0).read()
    # Driver row 7 (distances 1056..1063) becomes image row 0.
    np.testing.assert_allclose(frame.mean_m[0, :7], np.arange(1056, 1063) / 1000.0,
                               rtol=1e-6)


def test_adapter_timeout_and_missing_methods():
    driver = FakeDriver(polls=10**9)
    clock = FakeClock()
    assert DriverAdapter(driver, clock=clock, poll_interval_s=0.0).read(timeout_s=0.005) is None
    with pytest.raises(ValueError, match="get_ranging_data"):
        DriverAdapter(driver, get_data="get_ranging_data")
    # In 4x4 mode ST's buffer (sized for 8x8) holds the 16 zones in its first entries.
    frame = DriverAdapter(FakeDriver(polls=1), grid=4, poll_interval_s=0.0).read()
    assert frame.grid == 4 and frame.valid.all()
    np.testing.assert_allclose(frame.mean_m.reshape(-1), np.arange(1000, 1016) / 1000, rtol=1e-6)
    with pytest.raises(ValueError, match="expected 64"):
        driver = FakeDriver(polls=1)
        driver.distance_mm, driver.range_sigma_mm, driver.target_status = (
            driver.distance_mm[:16], driver.range_sigma_mm[:16], driver.target_status[:16])
        DriverAdapter(driver, grid=8, poll_interval_s=0.0).read()


@pytest.mark.parametrize("opener, package", [
    (open_vl53l5cx_ctypes, "vl53l5cx-ctypes"),
    (open_sparkfun, "sparkfun-qwiic-vl53l5cx"),
])
def test_missing_driver_packages_say_what_to_install(opener, package):
    with pytest.raises(ImportError, match=package):
        opener()


def test_missing_circuitpython_driver():
    with pytest.raises(ImportError, match="circuitpython-vl53lxcx"):
        open_circuitpython(i2c=None)


def test_circuitpython_asks_for_signals_with_several_targets(monkeypatch):
    import sys
    import types

    started = []

    class FakeSensor(MultiTargetDriver):
        def __init__(self, i2c) -> None:
            super().__init__()

        def init(self) -> None:
            pass

        def check_data_ready(self):
            return True

        def get_ranging_data(self):
            return self

        def start_ranging(self, outputs):
            started.append(set(outputs))

    module = types.SimpleNamespace(VL53L5CX=FakeSensor, DATA_NB_TARGET_DETECTED=2,
                                   DATA_SIGNAL_PER_SPAD=3, DATA_RANGE_SIGMA_MM=4,
                                   DATA_DISTANCE_MM=5, DATA_TARGET_STATUS=7)
    monkeypatch.setitem(sys.modules, "vl53lxcx", module)
    with open_circuitpython(i2c=None, targets_per_zone=2) as sensor:
        frame = sensor.read()
    assert started == [{2, 3, 4, 5, 7}]
    assert frame.targets_per_zone == 2 and frame.target_signal is not None
    assert frame.target_signal.max() == pytest.approx(163.0)
    with open_circuitpython(i2c=None):
        pass
    assert started[-1] == {4, 5, 7}


def test_simulated_rig_rates_and_zones():
    rig = SimulatedRig(FlatWallSource(1.01, frames=6, height=48, width=64), grid=8,
                       camera_hz=30.0, sensor_hz=10.0, sensor_delay_s=0.004)
    captures = []
    with rig:
        while (capture := rig.grab()) is not None:
            captures.append(capture)
    assert len(captures) == 6
    np.testing.assert_allclose([c.image_time_s for c in captures], np.arange(6) / 30.0)
    with_zones = [i for i, c in enumerate(captures) if c.zone_frame is not None]
    assert with_zones == [0, 3]  # 10 Hz sensor, 30 Hz camera
    frame = captures[3].zone_frame
    assert frame.timestamp_s == pytest.approx(3 / 30.0 + 0.004)
    assert frame.hist_counts is None  # like a VL53L5CX: mean and sigma only
    mean, _, valid = frame.flat()
    # A flat wall at 1.01 m, 4 cm bins from 0: every zone reads the bin centre 1.02 m.
    assert valid.any()
    np.testing.assert_allclose(mean[valid], 1.02, atol=1e-5)


def test_hardware_rig_records_from_opencv_and_a_driver(tmp_path):
    """The hardware path end to end: a video file as the camera, a fake ULD driver."""
    import cv2

    from deltar.camera import CameraIntrinsics
    from deltar.capture.drivers import HardwareRig, OpenCVCamera
    from deltar.capture.record import record
    from deltar.io.recording import Recording

    video = tmp_path / "camera.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    for i in range(5):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    rig = HardwareRig(OpenCVCamera(str(video)), DriverAdapter(FakeDriver(polls=1),
                                                              poll_interval_s=0.0))
    intr = CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    summary = record(tmp_path / "rec", rig, intrinsics=intr)
    assert (summary.images, summary.zone_frames, summary.depth_maps) == (5, 5, 0)
    rec = Recording(tmp_path / "rec")
    assert rec.meta.intrinsics == intr and len(rec.color_paths) == 5
    assert [f.flat()[0][0] for f in rec.zone_frames()] == pytest.approx([1.0] * 5)
    with pytest.raises(ValueError, match="cannot open camera"):
        OpenCVCamera(str(tmp_path / "missing.avi"))


def test_simulated_rig_reports_zones_beyond_the_range_as_no_target():
    # A wall at 5 m: past the L5's 4 m, every zone in view reports no target.
    rig = SimulatedRig(FlatWallSource(5.0, frames=1, height=48, width=64), grid=8)
    with rig:
        frame = rig.grab().zone_frame
    assert not frame.valid.any() and frame.no_target.all()


class MultiTargetDriver:
    """Results like ST's ULD built with two targets per zone, buffers sized for 8x8."""

    def __init__(self) -> None:
        self.distance_mm = np.repeat(np.arange(64) * 10.0 + 800, 2)
        self.distance_mm[1::2] += 1500
        self.range_sigma_mm = [5] * 128
        self.target_status = [5] * 128
        self.nb_target_detected = [2] * 63 + [1]
        self.signal_per_spad = np.repeat(np.arange(64) + 100.0, 2)  # kcps per SPAD
        self.signal_per_spad[1::2] /= 10

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
    # Each target's signal_per_spad, reoriented like the distances; 0 where not valid.
    np.testing.assert_allclose(frame.target_signal[0, 0], [156.0, 15.6], rtol=1e-6)
    np.testing.assert_allclose(frame.target_signal[0, 7], [163.0, 0.0], rtol=1e-6)
    # Without targets_per_zone a one-target reading needs no signal.
    single = MultiTargetDriver()
    for name in ("distance_mm", "range_sigma_mm", "target_status", "signal_per_spad"):
        setattr(single, name, list(getattr(single, name))[:64])
    single.nb_target_detected = None
    assert DriverAdapter(single, poll_interval_s=0.0).read().target_signal is None
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


def _check_step_targets(frames) -> None:
    assert frames and all(f.targets_per_zone == 2 for f in frames)
    for frame in frames:
        np.testing.assert_array_equal(frame.target_valid[..., 0], frame.valid)
        # The simulator's signal: positive for every valid target, 0 elsewhere.
        assert np.all(frame.target_signal[frame.target_valid] > 0)
        assert np.all(frame.target_signal[~frame.target_valid] == 0)
        second = frame.target_valid[..., 1]
        assert second.any()  # the zones on the step see both surfaces
        # Both surfaces, one as each target.
        pairs = np.sort(frame.target_mean_m[second], axis=-1)
        np.testing.assert_allclose(pairs, np.broadcast_to([1.0, 2.5], pairs.shape), atol=0.03)


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


@pytest.mark.parametrize("kwargs, message", [
    ({"grid": 8.0}, "grid must be 4 or 8, got 8.0"),
    ({"poll_interval_s": -1}, "poll_interval_s must be a finite number"),
    ({"poll_interval_s": float("nan")}, "poll_interval_s must be a finite number"),
])
def test_adapter_refuses_bad_settings_naming_them(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DriverAdapter(FakeDriver(), **kwargs)


def test_adapter_refuses_a_nan_timeout_instead_of_waiting_forever():
    sensor = DriverAdapter(FakeDriver(polls=10**9), clock=FakeClock(), poll_interval_s=0.0)
    with pytest.raises(ValueError, match="timeout_s must be a number"):
        sensor.read(timeout_s=float("nan"))
    with pytest.raises(ValueError, match="timeout_s must be a number"):
        sensor.read(timeout_s=None)


def test_adapter_result_fields_that_are_not_lists_name_the_field():
    driver = FakeDriver(polls=1)
    driver.distance_mm = 1000
    with pytest.raises(ValueError, match="field 'distance_mm' must be a list of numbers"):
        DriverAdapter(driver, poll_interval_s=0.0).read()
    # A driver wrapper that hands out (8, 8) numpy arrays in driver order reads as such.
    driver = FakeDriver(polls=1)
    driver.distance_mm = np.arange(1000, 1064).reshape(8, 8)
    frame = DriverAdapter(driver, poll_interval_s=0.0).read()
    np.testing.assert_allclose(frame.mean_m[0], np.arange(1000, 1008) / 1000, rtol=1e-6)


@pytest.mark.parametrize("opener", [open_vl53l5cx_ctypes, open_sparkfun,
                                    lambda **kw: open_circuitpython(i2c=None, **kw)])
@pytest.mark.parametrize("kwargs, message", [
    ({"grid": 6}, "grid must be 4 or 8, got 6"),
    ({"grid": 8, "ranging_hz": 30}, r"ranging_hz must be an integer in 1\.\.15"),
    ({"grid": 4, "ranging_hz": 0}, r"ranging_hz must be an integer in 1\.\.60"),
    ({"grid": 4, "ranging_hz": 7.5}, r"ranging_hz must be an integer"),
])
def test_openers_check_grid_and_rate_before_the_driver(opener, kwargs, message):
    # Checked before the driver is imported or told anything (none is installed here).
    with pytest.raises(ValueError, match=message):
        opener(**kwargs)
