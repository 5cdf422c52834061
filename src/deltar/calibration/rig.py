"""The rig calibration file: camera intrinsics + ToF sensor model + sensor-to-camera pose.

JSON layout (``schema_version`` 1)::

    {"schema": "deltar.rig_calibration", "schema_version": 1, "date": "2026-...Z",
     "intrinsics": {"fx": .., "fy": .., "cx": .., "cy": .., "width": .., "height": ..},
     "sensor_model": "VL53L5CX", "grid": 8, "fov_deg": [45.0, 45.0],
     "extrinsics": {"rotation": [[...], [...], [...]], "translation_m": [x, y, z]},
     "residuals": {"zone_to_cloud_before_m": .., "zone_to_cloud_after_m": .., ...},
     "distortion": [k1, k2, p1, p2, k3], "time_offset_s": 0.0}

``extrinsics`` maps sensor to camera coordinates: ``p_cam = R @ p_sensor + t`` (metres).
``distortion`` (OpenCV's order; empty = pinhole) and ``time_offset_s`` (how far the
camera's stamps run ahead of the sensor's) are optional: files without them read as
an undistorted camera on the sensor's clock.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from deltar.camera import (
    CameraIntrinsics,
    distortion_fold_error,
    strict_integer,
    strict_number,
    undistorted_coverage,
)
from deltar.io.atomic import write_text_atomic
from deltar.io.input_file import reading
from deltar.io.json_file import read_json
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics, zone_rects, zones_in_image
from deltar.sensor.zone_frame import ZoneFrame

RIG_SCHEMA_NAME = "deltar.rig_calibration"
RIG_SCHEMA_VERSION = 1
#: Distance (metres) used to place zones that carry no measurement.
FALLBACK_ZONE_DEPTH_M = 2.0
#: Largest sensor-to-camera distance of one rig, metres (sensors sit centimetres from
#: the lens; a metre or more is a unit mistake, e.g. millimetres written as metres).
MAX_TRANSLATION_M = 1.0
#: The least fraction of the undistorted image a lens distortion may leave with a source
#: pixel (real lenses keep nearly all of it; far less means wrong coefficients).
MIN_UNDISTORTED_COVERAGE = 0.5


@dataclass(frozen=True)
class RigCalibration:
    """Everything needed to place the sensor's zones in the camera image.

    Attributes:
        intrinsics: colour camera intrinsics (pixels) at the calibrated resolution.
        extrinsics: sensor-to-camera transform (metres).
        grid: zones per side (4 or 8).
        fov_deg: (horizontal, vertical) sensor field of view in degrees.
        sensor_model: e.g. ``"VL53L5CX"``.
        residuals: fit quality numbers (metres), e.g. zone-to-cloud distances.
        date: ISO 8601 UTC time of the calibration.
        schema_version: file schema version.
        distortion: the colour camera's lens distortion, OpenCV coefficients (k1, k2, p1,
            p2[, k3[, ...]]); empty for a pinhole camera. With distortion, images are
            undistorted (:meth:`undistort_image`, same intrinsics) before the zones are
            placed and depth is predicted.
        time_offset_s: how far the camera's timestamps run ahead of the sensor's,
            seconds; pairing matches a zone frame stamped t with the image nearest t +
            offset.
    """

    intrinsics: CameraIntrinsics
    extrinsics: SensorExtrinsics
    grid: int = 8
    fov_deg: tuple[float, float] = DEFAULT_FOV_DEG
    sensor_model: str = "VL53L5CX"
    residuals: dict = field(default_factory=dict)
    date: str = ""
    schema_version: int = RIG_SCHEMA_VERSION
    distortion: tuple[float, ...] = ()
    time_offset_s: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, CameraIntrinsics) or not isinstance(
                self.extrinsics, SensorExtrinsics):
            raise ValueError("RigCalibration needs CameraIntrinsics and SensorExtrinsics, got "
                             f"{type(self.intrinsics).__name__} and "
                             f"{type(self.extrinsics).__name__}")
        if isinstance(self.grid, bool) or not isinstance(self.sensor_model, str):
            raise ValueError(f"RigCalibration.grid must be 4 or 8 and sensor_model a string, "
                             f"got {self.grid!r} and {self.sensor_model!r}")
        distortion = tuple(strict_number(v, "RigCalibration.distortion")
                           for v in self.distortion)
        if len(distortion) not in (0, 4, 5, 8, 12, 14) or not all(map(math.isfinite,
                                                                      distortion)):
            raise ValueError("RigCalibration.distortion must be 0, 4, 5, 8, 12 or 14 finite "
                             f"OpenCV coefficients, got {self.distortion}")
        object.__setattr__(self, "distortion", distortion)
        if not math.isfinite(strict_number(self.time_offset_s, "RigCalibration.time_offset_s")):
            raise ValueError(f"RigCalibration.time_offset_s must be finite, got "
                             f"{self.time_offset_s}")
        object.__setattr__(self, "time_offset_s", float(self.time_offset_s))
        if self.grid not in (4, 8):
            raise ValueError(f"RigCalibration.grid must be 4 or 8, got {self.grid}")
        fov = tuple(strict_number(f, "RigCalibration.fov_deg") for f in self.fov_deg)
        if len(fov) != 2 or not all(0 < f < 180 for f in fov):
            raise ValueError(f"RigCalibration.fov_deg must be two angles in (0, 180), "
                             f"got {self.fov_deg}")
        object.__setattr__(self, "fov_deg", fov)
        if not self.date:
            object.__setattr__(self, "date", datetime.now(timezone.utc).isoformat(
                timespec="seconds"))
        self._check_geometry()

    def _check_geometry(self) -> None:
        """Refuse a rig that cannot be right: the principal point outside the image, the
        sensor a metre or more from the camera, or every zone outside the image."""
        intr = self.intrinsics
        if not (-0.5 <= intr.cx <= intr.width - 0.5 and -0.5 <= intr.cy <= intr.height - 0.5):
            raise ValueError(f"the principal point (cx, cy) = ({intr.cx:g}, {intr.cy:g}) px "
                             f"lies outside the {intr.height}x{intr.width} image")
        distance = float(np.linalg.norm(self.extrinsics.translation_m))
        if distance >= MAX_TRANSLATION_M:
            raise ValueError(f"the sensor is {distance:.6g} m from the camera (translation_m "
                             f"{self.extrinsics.translation_m.tolist()}); a rig's sensor sits "
                             f"within {MAX_TRANSLATION_M:g} m of it (millimetres written as "
                             "metres?)")
        coverage = undistorted_coverage(intr, self.distortion)
        if coverage < MIN_UNDISTORTED_COVERAGE:
            raise ValueError(f"the lens distortion {list(self.distortion)} leaves "
                             f"{100 * (1 - coverage):.0f} % of the undistorted image without a "
                             "source pixel (black): no lens of this camera does that; check "
                             "the coefficients (OpenCV's order k1, k2, p1, p2, k3)")
        inside = self.zones_inside()
        if not inside.any():
            raise ValueError(f"all {inside.size} zones fall outside the {intr.height}x"
                             f"{intr.width} image at {FALLBACK_ZONE_DEPTH_M:g} m; check the "
                             "extrinsics (rotation, translation), intrinsics and fov_deg")

    def zones_inside(self, depth_m: float = FALLBACK_ZONE_DEPTH_M) -> np.ndarray:
        """(Z,) bool: the zones whose rectangle at ``depth_m`` metres overlaps the image."""
        intr = self.intrinsics
        try:
            rects = zone_rects(intr, self.grid, fov_deg=self.fov_deg,
                               extrinsics=self.extrinsics, depth_m=depth_m)
        except ValueError:  # zones behind the camera
            return np.zeros(self.grid * self.grid, dtype=bool)
        return zones_in_image(rects, intr.height, intr.width)

    # ------------------------------------------------------------------ zones in the image
    def check_image_size(self, image_size: tuple[int, int], what: str = "image_size",
                         calibration: str = "the calibration",
                         remedy: str = "resize the images or recalibrate") -> None:
        """Refuse images of another size than the calibrated resolution: the intrinsics,
        and so the zone placement, hold for that size only. The one such check of the
        package (zone placement, undistortion, predict, replay, maps, calibration checks).

        Args:
            image_size: (height, width) of the images in pixels.
            what: how the message names the images (an argument, a file, a recording).
            calibration: how it names the calibration (e.g. ``--calib calib.json``).
            remedy: what the message suggests.

        Raises:
            ValueError: ``"<what> is HxW pixels but <calibration> is for the calibrated
                resolution HxW; <remedy>"``.
        """
        height, width = (int(s) for s in image_size)
        intr = self.intrinsics
        if (height, width) != (intr.height, intr.width):
            raise ValueError(f"{what} is {height}x{width} pixels but {calibration} is for the "
                             f"calibrated resolution {intr.height}x{intr.width}; {remedy}")

    def zone_rects_for(self, frame_or_depths: ZoneFrame | np.ndarray | float,
                       image_size: tuple[int, int]) -> np.ndarray:
        """Zone rectangles in the image, placed with each zone's measured distance.

        Args:
            frame_or_depths: a ``ZoneFrame`` (valid zones use their mean; invalid ones the
                median of the valid means, or 2 m), a (Z,) array of distances in metres,
                or one distance for all zones.
            image_size: (height, width) of the image the rectangles are for; must be the
                calibrated resolution.

        Returns:
            (Z, 4) float32 rectangles (y0, x0, y1, x1) in pixels, in the frame's zone order.

        Raises:
            ValueError: image size differs from the calibration's, or bad distances.
        """
        height, width = (int(s) for s in image_size)
        self.check_image_size((height, width))
        zones = self.grid * self.grid
        if isinstance(frame_or_depths, ZoneFrame):
            if frame_or_depths.grid != self.grid:
                raise ValueError(f"frame has a {frame_or_depths.grid}x{frame_or_depths.grid} "
                                 f"grid, calibration is for {self.grid}x{self.grid}")
            mean, _, valid = frame_or_depths.flat()
            fill = float(np.median(mean[valid])) if valid.any() else FALLBACK_ZONE_DEPTH_M
            depths = np.where(valid & (mean > 0), mean, fill).astype(np.float64)
        else:
            depths = np.broadcast_to(np.asarray(frame_or_depths, dtype=np.float64),
                                     (zones,)).copy()
        return zone_rects(self.intrinsics, self.grid, fov_deg=self.fov_deg,
                          extrinsics=self.extrinsics, depth_m=depths)

    @property
    def has_distortion(self) -> bool:
        """Whether the camera has a non-zero lens distortion."""
        return any(v != 0.0 for v in self.distortion)

    def undistort_image(self, image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """The image as the pinhole camera ``intrinsics`` would see it (same K).

        The pixel maps are computed on first use and kept with the calibration, so a
        stream pays one remap a frame (OpenCV's ``undistort`` rebuilds them every call,
        about as costly again; the result is the same to the bit).

        Args:
            image: (H, W[, C]) image at the calibrated resolution.
            nearest: take each pixel from the nearest source pixel instead of
                interpolating: for depth maps (metres or millimetres, 0 invalid), where
                interpolating across an edge or an invalid pixel makes depths no surface
                has.

        Returns:
            The undistorted image, same shape and dtype (the input when there is no
            distortion). Pixels that have no source are 0 (black).
        """
        if not self.has_distortion:
            return image
        import cv2

        image = np.asarray(image)
        # What OpenCV's remap takes: 8/16-bit integers or 32/64-bit floats, 1-4 channels.
        if image.ndim not in (2, 3) or (image.ndim == 3 and not 1 <= image.shape[2] <= 4) \
                or image.dtype not in (np.uint8, np.uint16, np.int16, np.float32, np.float64):
            raise ValueError(f"image must be (H, W) or (H, W, C) of uint8, uint16, int16, "
                             f"float32 or float64, got shape {image.shape} and dtype "
                             f"{image.dtype}")
        self.check_image_size(image.shape[:2], "image")
        return cv2.remap(image, *self._undistortion_maps(nearest),
                         cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _derived(self) -> dict:
        """What undistorting derives from the fields, kept with the calibration (not a
        field: frozen, left out of pickles and copies by :meth:`__getstate__`)."""
        return self.__dict__.setdefault("_undistortion_cache", {})

    def _undistortion_maps(self, nearest: bool) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's undistortion maps at the calibrated resolution: fixed-point ones for
        interpolation (as ``cv2.undistort`` uses), float ones for the nearest pixel."""
        import cv2

        cache = self._derived()
        if nearest not in cache:
            matrix, size = self.intrinsics.matrix, (self.intrinsics.width,
                                                    self.intrinsics.height)
            cache[nearest] = cv2.initUndistortRectifyMap(
                matrix, np.asarray(self.distortion), None, matrix, size,
                cv2.CV_32FC1 if nearest else cv2.CV_16SC2)
        return cache[nearest]

    def __getstate__(self) -> dict:
        """The fields for pickling and copies, without the undistortion maps (megabytes,
        remade on use)."""
        state = dict(self.__dict__)
        state.pop("_undistortion_cache", None)
        return state

    def undistorted(self) -> RigCalibration:
        """The calibration of this camera's undistorted images (:meth:`undistort_image`):
        the same intrinsics, zones and time offset without distortion, for images that
        were undistorted already (predicting with it does not undistort them again).
        Made once per calibration, so a stream may ask for it every frame."""
        if not self.has_distortion:
            return self
        cache = self._derived()
        if "pinhole" not in cache:
            cache["pinhole"] = replace(self, distortion=())
        return cache["pinhole"]

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        return {
            "schema": RIG_SCHEMA_NAME,
            "schema_version": self.schema_version,
            "date": self.date,
            "intrinsics": self.intrinsics.to_dict(),
            "sensor_model": self.sensor_model,
            "grid": self.grid,
            "fov_deg": list(self.fov_deg),
            "extrinsics": {"rotation": self.extrinsics.rotation.tolist(),
                           "translation_m": self.extrinsics.translation_m.tolist()},
            "residuals": {k: float(v) for k, v in self.residuals.items()},
            "distortion": list(self.distortion),
            "time_offset_s": self.time_offset_s,
        }

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the calibration atomically as JSON (refuses to overwrite by default)."""
        return write_text_atomic(path, json.dumps(self.to_dict(), indent=2,
                                                  allow_nan=False) + "\n",
                                 overwrite=overwrite)

    @classmethod
    def from_dict(cls, data: dict, source: str = "calibration") -> RigCalibration:
        """Build from the JSON dict, validating every field (errors name ``source``)."""
        if not isinstance(data, dict) or data.get("schema") != RIG_SCHEMA_NAME:
            raise ValueError(f"{source}: not a deltar rig calibration (schema "
                             f"{data.get('schema') if isinstance(data, dict) else None!r})")
        if data.get("schema_version") != RIG_SCHEMA_VERSION:
            raise ValueError(f"{source}: unsupported schema_version "
                             f"{data.get('schema_version')!r}")
        try:
            extr = data["extrinsics"]
            if not isinstance(data.get("residuals", {}), dict):
                raise ValueError("residuals must be an object of numbers, got "
                                 f"{type(data['residuals']).__name__}")
            residuals = {str(k): strict_number(v, f"residuals.{k}")
                         for k, v in data.get("residuals", {}).items()}
            if not all(math.isfinite(v) for v in residuals.values()):
                raise ValueError("residuals must be finite")
            return cls(
                intrinsics=CameraIntrinsics.from_dict(data["intrinsics"]),
                extrinsics=SensorExtrinsics(np.asarray(extr["rotation"], dtype=np.float64),
                                            np.asarray(extr["translation_m"],
                                                       dtype=np.float64)),
                grid=strict_integer(data["grid"], "grid"),
                fov_deg=tuple(strict_number(f, "fov_deg") for f in data["fov_deg"]),
                sensor_model=str(data.get("sensor_model", "VL53L5CX")),
                residuals=residuals,
                date=str(data.get("date", "")),
                distortion=tuple(strict_number(v, "distortion")
                                 for v in data.get("distortion", ())),
                time_offset_s=strict_number(data.get("time_offset_s", 0.0), "time_offset_s"),
            )
        except KeyError as err:
            raise ValueError(f"{source}: invalid calibration: missing {err}") from err
        except (TypeError, ValueError, OverflowError, AttributeError, IndexError) as err:
            raise ValueError(f"{source}: invalid calibration: {err}") from err

    @classmethod
    def load(cls, path: str | os.PathLike) -> RigCalibration:
        """Read and validate a calibration JSON file.

        Besides :meth:`from_dict`'s checks, a calibration that leaves some zones outside
        the image (at 2 m) loads with a ``UserWarning`` saying how many remain, and one
        whose lens distortion turns back inside the image
        (:func:`~deltar.camera.distortion_fold_error`) with one saying so.

        Raises:
            FileNotFoundError / IsADirectoryError: the path is missing or a folder.
            ValueError: naming the file (``InputFileError`` for unreadable content).
        """
        with reading(path, "calibration file"):
            calibration = cls.from_dict(read_json(path, "calibration file"), str(path))
        inside = calibration.zones_inside()
        if not inside.all():
            warnings.warn(f"{path}: only {int(inside.sum())} of {inside.size} zones fall "
                          f"inside the {calibration.intrinsics.height}x"
                          f"{calibration.intrinsics.width} image (at "
                          f"{FALLBACK_ZONE_DEPTH_M:g} m); the others carry no information",
                          UserWarning, stacklevel=2)
        folds = distortion_fold_error(calibration.intrinsics, calibration.distortion)
        if folds is not None:
            warnings.warn(f"{path}: its {folds}: the depth there is for folded pixels; "
                          "calibrate the camera with views reaching the image's edges",
                          UserWarning, stacklevel=2)
        return calibration



def pairing_time_offset(calibration: RigCalibration | None,
                        time_offset_s: float | None = None) -> float:
    """The clock offset frames are paired with, seconds (how far the camera's time stamps
    run ahead of the sensor's): ``time_offset_s`` when given (``--time-offset``), else
    the calibration's ``time_offset_s``, else 0."""
    if time_offset_s is not None:
        return float(time_offset_s)
    return calibration.time_offset_s if calibration is not None else 0.0
