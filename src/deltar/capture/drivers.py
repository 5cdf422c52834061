"""Sensor and camera sources for recording: real drivers behind one small interface.

* :class:`SensorAdapter` is the boundary to a multi-zone ToF driver: ``start()``,
  ``read(timeout_s) -> ZoneFrame | None`` (with a timestamp), ``stop()``.
  :class:`DriverAdapter` wraps any driver object with a "data ready" and a "get data"
  method; :func:`open_vl53l5cx_ctypes`, :func:`open_sparkfun` and
  :func:`open_circuitpython` build one for the three Python drivers on PyPI,
  importing them only when called (none can run without an I2C device).
* :class:`OpenCVCamera` grabs RGB frames from ``cv2.VideoCapture``.
* :class:`SimulatedRig` needs no hardware: it plays an RGB-D source (procedural
  scenes, an RGB-D folder, flat walls) as a camera plus a sensor whose zone frames are
  simulated from the depth, so recording and replay can be tested anywhere.

All timestamps are seconds on ``time.monotonic`` (hardware) or a simulated clock.
"""

from __future__ import annotations

import dataclasses
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from deltar.camera import CameraIntrinsics, strict_number
from deltar.io.zone_file import zone_frame_from_driver_result
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics, zone_rects
from deltar.sensor.zone_frame import Orientation, ZoneFrame
from deltar.sensor.zone_values import is_supported_grid


class SensorAdapter(ABC):
    """A multi-zone ToF sensor producing :class:`ZoneFrame` objects (image orientation)."""

    #: zones per side the sensor is configured for.
    grid: int = 8
    sensor_model: str = "VL53L5CX"

    def start(self) -> None:  # noqa: B027 - optional hook
        """Start ranging."""

    @abstractmethod
    def read(self, timeout_s: float = 1.0) -> ZoneFrame | None:
        """The next frame with ``timestamp_s`` set, or None if none came within the timeout."""

    def stop(self) -> None:  # noqa: B027 - optional hook
        """Stop ranging."""

    def __enter__(self) -> SensorAdapter:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class DriverAdapter(SensorAdapter):
    """Adapts a Python driver object: polls its data-ready method, converts its results.

    Args:
        driver: the driver object.
        data_ready: name of the method returning True when a frame is waiting.
        get_data: name of the method returning the results (an object or dict with
            ``distance_mm``, ``range_sigma_mm``, ``target_status`` as flat lists, and
            optionally ``nb_target_detected`` and ``signal_per_spad``).
        start: name of the method that starts ranging (None: nothing to call).
        stop: name of the method that stops ranging (None: nothing to call).
        start_args: positional arguments of the start method.
        grid: zones per side the driver was configured for (4 or 8).
        orientation: how the driver's grid maps onto the image.
        sensor_model: stored in each frame.
        clock: time source in seconds (``time.monotonic``).
        poll_interval_s: sleep between data-ready polls.
        targets_per_zone: targets per zone the driver was built for
            (``VL53L5CX_NB_TARGET_PER_ZONE``, 1..4). When given, the results are read as
            ``grid`` x ``grid`` zones of that many targets each (the first ``16 * T``
            entries of an 8x8-sized buffer in 4x4 mode) and the frames carry the target
            arrays, with each target's ``signal_per_spad`` (kcps per SPAD) as
            ``target_signal`` when the results have it (it weighs a zone's targets
            against each other); None infers it from the result's length and ``grid``
            (:meth:`ZoneFrame.from_driver`: in 4x4 mode ST's buffer, sized for 8x8, holds
            ``64 * T`` entries, of which the first ``16 * T`` are read).
        target_order: ``"strongest"`` or ``"closest"``, as the driver was configured.
    """

    def __init__(self, driver: Any, *, data_ready: str = "data_ready",
                 get_data: str = "get_data", start: str | None = "start_ranging",
                 stop: str | None = "stop_ranging", start_args: tuple = (), grid: int = 8,
                 orientation: Orientation | None = None, sensor_model: str = "VL53L5CX",
                 clock: Callable[[], float] = time.monotonic,
                 poll_interval_s: float = 0.002, targets_per_zone: int | None = None,
                 target_order: str = "strongest") -> None:
        for name in (data_ready, get_data, start, stop):
            if name is not None and not callable(getattr(driver, name, None)):
                raise ValueError(f"driver {type(driver).__name__} has no method {name!r}")
        _check_grid(grid)
        interval = _number_or_nan(poll_interval_s)
        if not (math.isfinite(interval) and interval >= 0):
            raise ValueError(f"poll_interval_s must be a finite number of seconds >= 0, "
                             f"got {poll_interval_s!r}")
        self.driver = driver
        self._names = (data_ready, get_data, start, stop)
        self._start_args = tuple(start_args)
        self.grid = grid
        self.orientation = orientation or Orientation()
        self.sensor_model = sensor_model
        self.clock = clock
        self.poll_interval_s = poll_interval_s
        if targets_per_zone is not None and (
                isinstance(targets_per_zone, bool) or not isinstance(targets_per_zone, int)
                or not 1 <= targets_per_zone <= 4):
            raise ValueError(f"targets_per_zone must be an integer in 1..4, got "
                             f"{targets_per_zone!r}")
        if target_order not in ("strongest", "closest"):
            raise ValueError(f"target_order must be 'strongest' or 'closest', got "
                             f"{target_order!r}")
        self.targets_per_zone = targets_per_zone
        self.target_order = target_order

    def start(self) -> None:
        """Start ranging (the driver's start method with ``start_args``; nothing when
        the adapter was given ``start=None``)."""
        if self._names[2] is not None:
            getattr(self.driver, self._names[2])(*self._start_args)

    def stop(self) -> None:
        """Stop ranging (the driver's stop method; nothing when given ``stop=None``)."""
        if self._names[3] is not None:
            getattr(self.driver, self._names[3])()

    def read(self, timeout_s: float = 1.0) -> ZoneFrame | None:
        """The next frame: polls the driver's data-ready method every
        ``poll_interval_s`` for up to ``timeout_s`` seconds, then reads the results.

        Returns:
            A :class:`ZoneFrame` (``grid`` x ``grid`` zones, metres, reoriented to the
            image, stamped in seconds of ``clock`` when the data was seen ready), or
            None when no frame was ready in time.

        Raises:
            ValueError: ``timeout_s`` not a number or NaN (a negative one polls once);
                a result the driver returns that is not a reading (its fields missing,
                not lists of numbers, lengths that do not fit ``grid``), naming the field.
        """
        if math.isnan(_number_or_nan(timeout_s)):
            # NaN would never compare past the deadline: the read would wait forever.
            raise ValueError(f"timeout_s must be a number of seconds (inf: wait for a "
                             f"frame), got {timeout_s!r}")
        data_ready, get_data = (getattr(self.driver, n) for n in self._names[:2])
        deadline = self.clock() + timeout_s
        while not data_ready():
            if self.clock() >= deadline:
                return None
            time.sleep(self.poll_interval_s)
        # Timestamp when the frame was seen ready, before the (slow) I2C transfer.
        timestamp = self.clock()
        result = get_data()
        return zone_frame_from_driver_result(
            result, orientation=self.orientation, timestamp_s=timestamp,
            sensor_model=self.sensor_model,
            grid=self.grid, targets_per_zone=self.targets_per_zone,
            target_order=self.target_order)


#: Highest ranging frequency per zones per side, Hz (ST's datasheets: 15 Hz at 8x8,
#: 60 Hz at 4x4); the drivers pass it on as a uint8 without checking it.
MAX_RANGING_HZ = {4: 60, 8: 15}


def _number_or_nan(value: Any) -> float:
    """``value`` as a float (:func:`~deltar.camera.strict_number`), NaN when it is not a
    number (a string, a boolean), for checks that refuse NaN anyway."""
    try:
        return strict_number(value, "value")
    except ValueError:
        return math.nan


def _check_grid(grid: Any) -> None:
    """``ValueError`` naming ``grid`` unless it is the integer 4 or 8."""
    if not is_supported_grid(grid):
        raise ValueError(f"grid must be 4 or 8, got {grid!r}")


def _check_setup(grid: Any, ranging_hz: Any) -> None:
    """Check what an opener sends to the sensor before it touches the hardware."""
    _check_grid(grid)
    top = MAX_RANGING_HZ[int(grid)]
    if isinstance(ranging_hz, bool) or not isinstance(ranging_hz, int | np.integer) or \
            not 1 <= ranging_hz <= top:
        raise ValueError(f"ranging_hz must be an integer in 1..{top} for a {grid}x{grid} "
                         f"grid (ST's limit), got {ranging_hz!r}")


def _import(module: str, package: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ImportError(f"the {module!r} driver is not installed; install it with "
                          f"'pip install {package}' on the machine the sensor is wired to"
                          ) from err


def open_vl53l5cx_ctypes(grid: int = 8, ranging_hz: int = 15,
                         orientation: Orientation | None = None,
                         targets_per_zone: int | None = None,
                         target_order: str = "strongest") -> DriverAdapter:
    """A sensor through ``vl53l5cx-ctypes`` (Raspberry Pi, ST's ULD via ctypes).

    Its example shows the image up-down flipped relative to the driver order, hence
    the default orientation ``Orientation(flip_ud=True)``. ``targets_per_zone`` and
    ``target_order``: as the driver library was built and configured (see
    :class:`DriverAdapter`).
    """
    _check_setup(grid, ranging_hz)
    driver_module = _import("vl53l5cx_ctypes", "vl53l5cx-ctypes")
    driver = driver_module.VL53L5CX()
    driver.set_resolution(grid * grid)
    driver.set_ranging_frequency_hz(ranging_hz)
    return DriverAdapter(driver, grid=grid,
                         orientation=orientation or Orientation(flip_ud=True),
                         targets_per_zone=targets_per_zone, target_order=target_order)


def open_sparkfun(grid: int = 8, ranging_hz: int = 15,
                  orientation: Orientation | None = None, targets_per_zone: int | None = None,
                  target_order: str = "strongest") -> DriverAdapter:
    """A sensor through SparkFun's ``sparkfun-qwiic-vl53l5cx`` (CPython / MicroPython).

    ``targets_per_zone`` and ``target_order``: see :class:`DriverAdapter`.
    """
    _check_setup(grid, ranging_hz)
    driver_module = _import("qwiic_vl53l5cx", "sparkfun-qwiic-vl53l5cx")
    driver = driver_module.QwiicVL53L5CX()
    if not driver.begin():
        raise RuntimeError("SparkFun VL53L5CX did not respond on the I2C bus")
    driver.set_resolution(grid * grid)
    driver.set_ranging_frequency_hz(ranging_hz)
    return DriverAdapter(driver, data_ready="check_data_ready", get_data="get_ranging_data",
                         grid=grid, orientation=orientation, targets_per_zone=targets_per_zone,
                         target_order=target_order)


def open_circuitpython(i2c: Any, grid: int = 8, model: str = "VL53L5CX",
                       ranging_hz: int = 15,
                       orientation: Orientation | None = None,
                       targets_per_zone: int | None = None,
                       target_order: str = "strongest") -> DriverAdapter:
    """A sensor through ``circuitpython-vl53lxcx`` on a CircuitPython board.

    The driver needs ``init()`` (firmware upload) and starts ranging with the set of
    outputs to report: distance, sigma and target status are requested, and with
    ``targets_per_zone`` given also each zone's target count and each target's
    ``signal_per_spad``.

    Args:
        i2c: the board's ``busio.I2C`` object.
        grid: zones per side.
        model: ``"VL53L5CX"`` or ``"VL53L8CX"`` (the driver class of that name).
        ranging_hz: ranging frequency, Hz: 1..15 for 8x8, 1..60 for 4x4.
        orientation: how the driver grid maps onto the image.
        targets_per_zone, target_order: as the driver was built and configured (see
            :class:`DriverAdapter`).
    """
    _check_setup(grid, ranging_hz)
    driver_module = _import("vl53lxcx", "circuitpython-vl53lxcx")
    if model not in ("VL53L5CX", "VL53L8CX"):
        raise ValueError(f"model must be VL53L5CX or VL53L8CX, got {model!r}")
    driver = getattr(driver_module, model)(i2c)
    driver.init()
    driver.resolution = grid * grid
    driver.ranging_freq = ranging_hz
    wanted = ("DATA_DISTANCE_MM", "DATA_RANGE_SIGMA_MM", "DATA_TARGET_STATUS")
    if targets_per_zone is not None:
        wanted += ("DATA_NB_TARGET_DETECTED", "DATA_SIGNAL_PER_SPAD")
    outputs = {getattr(driver_module, name) for name in wanted if hasattr(driver_module, name)}
    return DriverAdapter(driver, data_ready="check_data_ready", get_data="get_ranging_data",
                         start_args=(outputs,), grid=grid, orientation=orientation,
                         sensor_model=model, targets_per_zone=targets_per_zone,
                         target_order=target_order)


class OpenCVCamera:
    """RGB frames from ``cv2.VideoCapture`` (a device index or a video file/URL).

    Args:
        source: device index (``0``) or path/URL.
        size: optional (height, width) to request from the device.
        clock: time source in seconds.
    """

    def __init__(self, source: int | str = 0, size: tuple[int, int] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        import cv2

        self.capture = cv2.VideoCapture(source)
        if not self.capture.isOpened():
            raise ValueError(f"cannot open camera {source!r} with OpenCV")
        if size is not None:
            self.capture.set(cv2.CAP_PROP_FRAME_HEIGHT, size[0])
            self.capture.set(cv2.CAP_PROP_FRAME_WIDTH, size[1])
        self.clock = clock
        self.source = source

    def read(self) -> tuple[float, np.ndarray] | None:
        """(timestamp_s, (H, W, 3) uint8 RGB) of the next frame, or None at the end."""
        import cv2

        ok, frame = self.capture.read()
        if not ok or frame is None:
            return None
        return self.clock(), cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)

    def release(self) -> None:
        """Close the device or file (``cv2.VideoCapture.release``)."""
        self.capture.release()


@dataclass
class Capture:
    """What one step of a rig delivers; any part may be missing.

    Attributes:
        image_time_s: camera timestamp (seconds) or None.
        image: (H, W, 3) uint8 RGB or None.
        zone_frame: a zone frame with ``timestamp_s`` or None.
        depth_m: (H, W) float32 reference depth in metres (simulated rigs) or None.
        pose: (4, 4) float64 camera-to-world pose of the camera when ``image`` was taken
            (metres; simulated rigs whose source has poses) or None.
    """

    image_time_s: float | None = None
    image: np.ndarray | None = None
    zone_frame: ZoneFrame | None = None
    depth_m: np.ndarray | None = None
    pose: np.ndarray | None = None


class HardwareRig:
    """A camera and a ToF sensor read in turn: one camera frame per step plus any
    sensor frame that is ready."""

    def __init__(self, camera: OpenCVCamera, sensor: SensorAdapter) -> None:
        self.camera = camera
        self.sensor = sensor
        self.intrinsics: CameraIntrinsics | None = None
        self.grid = sensor.grid
        self.sensor_model = sensor.sensor_model

    def __enter__(self) -> HardwareRig:
        self.sensor.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.sensor.stop()
        self.camera.release()

    def grab(self) -> Capture | None:
        """One step; None when the camera has no more frames."""
        got = self.camera.read()
        if got is None:
            return None
        frame = self.sensor.read(timeout_s=0.0)
        return Capture(image_time_s=got[0], image=got[1], zone_frame=frame)


#: The simulated camera's default frame rate, Hz.
SIMULATED_CAMERA_HZ = 30.0


class SimulatedRig:
    """A camera and a simulated ToF sensor played from an RGB-D source.

    Step ``i`` delivers frame ``i`` of the source at camera time ``i / camera_hz``; the
    sensor fires every ``camera_hz / sensor_hz`` camera frames, ``sensor_delay_s``
    after the camera, with zones simulated from that frame's depth.

    Args:
        source: a sequence of :class:`~deltar.data.rgbd.RGBDFrame` (one image size).
        grid: zones per side.
        fov_deg: sensor field of view in degrees.
        extrinsics: sensor-to-camera transform (identity when None).
        camera_hz: simulated camera rate.
        sensor_hz: simulated sensor rate (at most ``camera_hz``).
        sensor_delay_s: sensor time minus camera time, seconds.
        start_time_s: time of the first camera frame.
        config: simulator parameters (``SimulatorConfig()`` when None).
        with_histogram: keep the simulated per-zone histogram in the frames (the
            VL53L5CX reports only mean and sigma, so False by default).
        max_targets: targets per zone the simulated sensor reports, 1..4 (see
            :func:`~deltar.sensor.simulate_frame.simulate_zone_frame`; 1 by default).
        target_order: order of targets 1.., ``"strongest"`` or ``"closest"``.
        poses: optional per source frame (4, 4) camera-to-world pose in metres, or None
            for a frame without one; delivered with each image (``Capture.pose``).
    """

    sensor_model = "simulated"

    def __init__(self, source: Sequence[Any], grid: int = 8,
                 fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
                 extrinsics: SensorExtrinsics | None = None,
                 camera_hz: float = SIMULATED_CAMERA_HZ,
                 sensor_hz: float = 15.0, sensor_delay_s: float = 0.004,
                 start_time_s: float = 0.0, config: Any = None,
                 with_histogram: bool = False, max_targets: int = 1,
                 target_order: str = "strongest",
                 poses: Sequence[np.ndarray | None] | None = None) -> None:
        from deltar.sensor.simulate_frame import check_target_options

        check_target_options(max_targets, target_order)
        if len(source) == 0:
            raise ValueError("the RGB-D source has no frames")
        if poses is not None and len(poses) != len(source):
            raise ValueError(f"poses: {len(poses)} for a source of {len(source)} frames")
        if not 0 < sensor_hz <= camera_hz:
            raise ValueError(f"need 0 < sensor_hz <= camera_hz, got {sensor_hz}, {camera_hz}")
        self.source = source
        self.grid = grid
        self.fov_deg = tuple(fov_deg)
        self.extrinsics = extrinsics or SensorExtrinsics()
        self.camera_hz, self.sensor_hz = float(camera_hz), float(sensor_hz)
        self.sensor_delay_s = float(sensor_delay_s)
        self.start_time_s = float(start_time_s)
        self.config = config
        self.with_histogram = with_histogram
        self.max_targets = max_targets
        self.target_order = target_order
        self.poses = poses
        self.intrinsics: CameraIntrinsics = source[0].intrinsics
        self._index = 0

    def __enter__(self) -> SimulatedRig:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def grab(self) -> Capture | None:
        """One step; None after the last source frame."""
        from deltar.sensor.simulate_frame import simulate_zone_frame

        if self._index >= len(self.source):
            return None
        i = self._index
        self._index += 1
        frame = self.source[i]
        if frame.intrinsics != self.intrinsics:
            raise ValueError(f"source frame {frame.name!r} has other intrinsics than the "
                             "first frame; a recording has one camera")
        image_time = self.start_time_s + i / self.camera_hz
        capture = Capture(image_time_s=image_time, image=frame.image, depth_m=frame.depth_m,
                          pose=None if self.poses is None else self.poses[i])
        every = self.camera_hz / self.sensor_hz
        if int(i // every) != int((i - 1) // every):
            depth = frame.depth_m
            valid = depth > 0
            # Place zones at the median scene depth: with parallax, where they land
            # depends on the distance.
            place = float(np.median(depth[valid])) if valid.any() else 2.0
            rects = zone_rects(self.intrinsics, self.grid, fov_deg=self.fov_deg,
                               extrinsics=self.extrinsics, depth_m=place)
            zones = simulate_zone_frame(depth, rects, self.config,
                                        timestamp_s=image_time + self.sensor_delay_s,
                                        max_targets=self.max_targets,
                                        target_order=self.target_order)
            if not self.with_histogram:
                zones = dataclasses.replace(zones, hist_edges_m=None, hist_counts=None)
            capture.zone_frame = zones
        return capture
