"""The frames a map is built from, and their depth: model, classical baseline or recorded.

:func:`open_frames` lists the frames of a recording folder or a ROS 2 bag (a zone frame
with the colour image nearest in time) without decoding images; :class:`FrameSource`
then loads them one by one. A :class:`DepthSource` turns a loaded frame into depth
(metres) and a per-pixel integration weight.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from deltar.io.read_ahead import read_ahead
from deltar.sensor.zone_values import sensor_max_range_m

if TYPE_CHECKING:
    from deltar.calibration.rig import RigCalibration
    from deltar.inference.estimator import DepthEstimator
    from deltar.sensor.zone_frame import ZoneFrame

#: Name of the depth source that reads the recording's own depth images (reference).
RECORDED = "recorded"
#: Default largest relative uncertainty (sigma / depth) of an integrated pixel.
DEFAULT_MAX_RELATIVE_SIGMA = 0.15
#: Default TSDF truncation distance the weights are made for, metres (the map's default:
#: 4 voxels of 2 cm).
DEFAULT_TRUNCATION_M = 0.08
#: Sensor range assumed for sensor models without a known one, metres (the L5's).
FALLBACK_RANGE_M = 4.0


@dataclass
class MapFrame:
    """One frame to integrate.

    Attributes:
        name: the frame's name (a recording's colour image stem, a bag's image stamp).
        time_s: the colour image's time, seconds.
        image: (H, W, 3) uint8 RGB (None until loaded).
        zone_frame: the ToF reading.
        calibration: the rig calibration its zones are placed with.
        recorded_depth_m: (H, W) float32 recorded depth in metres (0 invalid) or None.
        camera_frame_id: a bag image's ``header.frame_id`` (None for recordings).
    """

    name: str
    time_s: float
    image: np.ndarray | None
    zone_frame: ZoneFrame
    calibration: RigCalibration
    recorded_depth_m: np.ndarray | None = None
    camera_frame_id: str | None = None


class FrameSource:
    """The frames of a recording folder or a ROS 2 bag, listed first, loaded on demand.

    Args:
        path: a recording folder (``meta.json``) or a ROS 2 bag folder (``metadata.yaml``).
        calibration: rig calibration; nominal from the recording's metadata or the bag's
            CameraInfo when None.
        tolerance_s: largest |image time - zone time| of a pair, seconds.
        every: use every ``every``-th pair.
        limit: at most this many frames.
        bag_options: ``BagInput`` keyword arguments (topics, ToF format) for bags.

    Attributes:
        frames: the listed :class:`MapFrame` (images not loaded).
        kind: ``"recording"`` or ``"bag"``.
        sensor_model: the ToF sensor's model name.
    """

    def __init__(self, path: str | os.PathLike, *, calibration: RigCalibration | None = None,
                 tolerance_s: float = 0.02, every: int = 1, limit: int | None = None,
                 bag_options: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"recording or bag not found: {self.path}")
        if int(every) < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.kind = "bag" if (self.path / "metadata.yaml").is_file() else "recording"
        if self.kind == "bag":
            self._list_bag(calibration, tolerance_s, bag_options or {})
        else:
            self._list_recording(calibration, tolerance_s)
        selection = list(range(len(self.frames)))[::int(every)][:limit]
        self.frames = [self.frames[i] for i in selection]
        self._pairs = [self._pairs[i] for i in selection]
        models = {f.zone_frame.sensor_model for f in self.frames}
        self.sensor_model = models.pop() if len(models) == 1 else "VL53L5CX"

    def _list_recording(self, calibration: RigCalibration | None, tolerance_s: float) -> None:
        from deltar.capture.replay import recording_calibration, replay_pairs
        from deltar.io.recording import Recording

        rec = Recording(self.path)
        self.recording = rec
        # Without --calib, the recording's own camera: its meta.json is named in refusals.
        self._own_camera = rec if calibration is None else None
        calib = calibration or recording_calibration(rec)
        calib.check_image_size((rec.meta.intrinsics.height, rec.meta.intrinsics.width),
                               f"the recording {self.path}", "--calib")
        _check_grid(calibration, rec.meta.grid, f"the recording {self.path}")
        # The recording warns of zone frames without an image near them itself.
        offset = calib.time_offset_s
        pairs = replay_pairs(rec, rec.pairs(tolerance_s=tolerance_s, time_offset_s=offset),
                             offset)  # one zone frame per image, as replay
        self.frames = [MapFrame(p.color_path.stem, int(p.color_path.stem) * 1e-9, None,
                                p.zone_frame, calib) for p in pairs]
        self._pairs = pairs

    def _list_bag(self, calibration: RigCalibration | None, tolerance_s: float,
                  options: dict[str, Any]) -> None:
        from deltar.calibration.rig import pairing_time_offset
        from deltar.capture.bag_replay import pair_calibration
        from deltar.io.rosbag_reader import BagInput

        bag = BagInput(self.path, **options)
        self.bag = bag
        # The calibration's clock offset, as for recordings and `deltar replay --bag`;
        # the bag gives one ToF frame per image.
        pairs = bag.pairs(tolerance_s=tolerance_s, time_offset_s=pairing_time_offset(calibration))
        for pair in pairs[:1]:  # one zone topic: one grid
            _check_grid(calibration, pair.zone_frame.grid, f"the bag {self.path}")
        self.frames = [MapFrame(str(p.image_stamp_ns), p.image_stamp_ns / 1e9, None,
                                p.zone_frame, pair_calibration(p, calibration),
                                camera_frame_id=p.frame_id or None) for p in pairs]
        self._pairs = pairs
        # The depth message nearest each image (the bag's depth topic, if it has one).
        self._depth_indices = bag.depth_indices(pairs, tolerance_s)

    def frames_without_recorded_depth(self) -> int:
        """How many of the frames come without recorded depth (``--method recorded`` needs
        it for every one): no ``depth/`` image of a recording within the pairing
        tolerance, or no message of a bag's depth topic (none read without one)."""
        if self.kind == "bag":
            return sum(i is None for i in self._depth_indices)
        return sum(pair.depth_path is None for pair in self._pairs)

    def check_recorded_depth_size(self) -> None:
        """Refuse a recording whose recorded depth (what ``--method recorded`` maps) is not
        the size of its colour images, naming the first depth file: read from the first
        frame with depth, a cheap check before the long part (a bag's reader refuses such
        depth itself, naming the topic).

        Raises:
            ValueError: the depth is not registered to the colour image pixel for pixel.
        """
        if self.kind == "bag":
            return
        for frame, pair in zip(self.frames, self._pairs, strict=True):
            if pair.depth_path is not None:
                frame.image, frame.recorded_depth_m = pair.load_images()
                try:
                    check_depth_size(frame, pair.depth_path)
                finally:
                    frame.image, frame.recorded_depth_m = None, None
                return

    def __len__(self) -> int:
        return len(self.frames)

    def load(self, frames: list[MapFrame] | None = None) -> Iterator[MapFrame]:
        """Yield ``frames`` (default: all; in order from a recording, in bag order from a
        bag) with their image (and recorded depth).

        A frame's image is released again when the next one is yielded; from a
        recording the next frame's files are read while the caller works on the
        current one (:func:`~deltar.io.read_ahead.read_ahead`), so at most two frames'
        images are held. With lens distortion the image and the recorded depth are
        undistorted once, here, and the frame carries the undistorted camera's
        calibration while it is yielded (:meth:`RigCalibration.undistorted`), so the
        depth, its prediction and the integration do not undistort them again.
        """
        wanted = {id(f) for f in (self.frames if frames is None else frames)}
        chosen = [(p, f) for p, f in zip(self._pairs, self.frames, strict=True)
                  if id(f) in wanted]
        if self.kind == "bag":
            by_pair = {id(p): f for p, f in chosen}
            depth_of = {id(p): d for p, d in zip(self._pairs, self._depth_indices, strict=True)}
            pairs = [p for p, _ in chosen]
            for pair, rgb, depth in self.bag.images_with_depth(
                    pairs, [depth_of[id(p)] for p in pairs]):
                frame = by_pair[id(pair)]
                frame.image, frame.recorded_depth_m = rgb, depth
                yield from _undistorted_once(frame)
            return
        from deltar.capture.replay import check_recording_image

        for (pair, frame), loaded in read_ahead(chosen, lambda chosen_pair:
                                                chosen_pair[0].load_images()):
            frame.image, frame.recorded_depth_m = loaded.result()
            check_recording_image(pair, frame.image, frame.calibration, self._own_camera)
            yield from _undistorted_once(frame)

    def depth_limit_m(self) -> float:
        """The sensor's range in metres (the L5's 4 m for unknown or simulated models)."""
        limit = sensor_max_range_m(self.sensor_model)
        return limit if math.isfinite(limit) else FALLBACK_RANGE_M


def confidence_weight(depth_m: np.ndarray, uncertainty_m: np.ndarray, *,
                      truncation_m: float, max_relative_sigma: float) -> np.ndarray:
    """Per-pixel integration weight from the predicted uncertainty.

    ``w = 1 / (1 + (sigma / t)^2)`` for the TSDF truncation distance ``t``: the inverse
    variance of the pixel's signed distance in the TSDF's own unit (``t``), with the
    variance of a perfect pixel taken as one unit (the band a pixel updates), so a
    certain pixel weighs 1 like a classical baseline's, and a pixel with ``sigma = t``
    weighs 0.5. Where views overlap, a pixel of ten times the sigma pulls about a
    hundredth as hard. Pixels whose relative sigma (``sigma / depth``) is above
    ``max_relative_sigma`` get 0 (skipped), as do those without a positive depth or a
    finite sigma.

    Args:
        depth_m, uncertainty_m: (H, W) depth and its standard deviation, metres.
        truncation_m: the TSDF's truncation distance, metres (> 0).
        max_relative_sigma: relative sigma above which a pixel is skipped (> 0).

    Returns:
        (H, W) float32 weights in [0, 1].
    """
    for name, value in (("truncation_m", truncation_m),
                        ("max_relative_sigma", max_relative_sigma)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    depth = np.asarray(depth_m, dtype=np.float32)
    sigma = np.asarray(uncertainty_m, dtype=np.float32)
    if sigma.shape != depth.shape:
        raise ValueError(f"uncertainty_m must be {depth.shape}, got {sigma.shape}")
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        weight = 1.0 / (1.0 + np.square(sigma / np.float32(truncation_m)))
        keep = np.isfinite(sigma) & (sigma >= 0) & (depth > 0) & np.isfinite(depth) \
            & (sigma <= np.float32(max_relative_sigma) * depth)
    return np.where(keep, weight, 0.0).astype(np.float32)


class DepthSource:
    """Depth and weight of a loaded frame.

    Args:
        estimator: the depth model (None with ``method``).
        method: a classical baseline's name (:data:`~deltar.evaluation.baselines.BASELINES`)
            or ``"recorded"`` (the recording's own depth images: a reference), None for
            the model.
        max_relative_sigma: pixels of the model whose sigma / depth is above this are
            skipped.
        truncation_m: the truncation distance of the map the weights are for, metres;
            below the threshold a pixel weighs ``1 / (1 + (sigma / truncation_m)^2)``
            (:func:`confidence_weight`). Baselines and recorded depth have no
            uncertainty: weight 1.
        beyond_grid: also integrate the model's pixels beyond the bounding box of the
            zone grid (still gated by ``max_relative_sigma``). Off by default: no zone
            reads those pixels, their depth is the image's extrapolation, and whether
            their calibrated sigma passes the gate hangs on a relative floor fitted to
            the training scenes, which falls on either side of the gate from one model
            to another (benchmarks/RESULTS.md); other views see the same surfaces
            inside their grids.
    """

    def __init__(self, estimator: DepthEstimator | None = None, method: str | None = None,
                 max_relative_sigma: float = DEFAULT_MAX_RELATIVE_SIGMA,
                 truncation_m: float = DEFAULT_TRUNCATION_M,
                 beyond_grid: bool = False) -> None:
        from deltar.evaluation.baselines import BASELINES

        if (estimator is None) == (method is None):
            raise ValueError("give a depth estimator or a method, not both")
        if method is not None and method not in (*BASELINES, RECORDED):
            raise ValueError(f"--method must be one of {', '.join((*BASELINES, RECORDED))}, "
                             f"got {method!r}")
        if not (math.isfinite(max_relative_sigma) and max_relative_sigma > 0):
            raise ValueError(f"--max-relative-sigma must be > 0, got {max_relative_sigma}")
        if not (math.isfinite(truncation_m) and truncation_m > 0):
            raise ValueError(f"truncation_m must be > 0, got {truncation_m}")
        self.estimator = estimator
        self.truncation_m = float(truncation_m)
        self.method = method
        self.max_relative_sigma = float(max_relative_sigma)
        self.beyond_grid = bool(beyond_grid)

    @property
    def name(self) -> str:
        """What the depth comes from, for messages."""
        return self.method or self.estimator.weights

    def __call__(self, frame: MapFrame) -> tuple[np.ndarray, np.ndarray | None]:
        """((H, W) float32 depth in metres, (H, W) float32 weight or None for all 1).

        With lens distortion in the frame's calibration the depth is for the undistorted
        image (as the estimator's), same intrinsics.
        """
        if frame.image is None:
            raise ValueError(f"frame {frame.name}: image not loaded")
        if self.method == RECORDED:
            if frame.recorded_depth_m is None:
                raise ValueError(f"frame {frame.name} has no recorded depth (--method "
                                 "recorded needs a depth image for every frame)")
            check_depth_size(frame, f"frame {frame.name}")
            # Undistorted like the colour image, by nearest pixels: interpolating would
            # make depths no surface has at edges and beside invalid pixels.
            depth = frame.calibration.undistort_image(frame.recorded_depth_m, nearest=True)
            return np.asarray(depth, dtype=np.float32), None
        height, width = frame.image.shape[:2]
        if self.method is not None:
            from deltar.evaluation.baselines import run_baseline

            mean, _, valid = frame.zone_frame.flat()
            valid = valid & (mean > 0)
            if not valid.any():
                # A baseline's fallback would be a made-up surface: fuse nothing (the
                # map counts the frame as empty).
                return np.zeros((height, width), np.float32), None
            rects = frame.calibration.zone_rects_for(frame.zone_frame, (height, width))
            depth = run_baseline(self.method, frame.calibration.undistort_image(frame.image),
                                 mean, valid, rects)
            return depth, None
        # A frame without a valid zone is image-only (prediction.image_only); the estimator
        # says so by value, not by a warning.
        prediction = self.estimator.predict(frame.image, frame.zone_frame, frame.calibration)
        weight = confidence_weight(prediction.depth_m, prediction.uncertainty_m,
                                   truncation_m=self.truncation_m,
                                   max_relative_sigma=self.max_relative_sigma)
        if not self.beyond_grid:
            from deltar.inference.blend import zone_grid_mask

            weight[~zone_grid_mask(prediction.zone_rects, weight.shape)] = 0.0
        return prediction.depth_m, weight


def _check_grid(calibration: RigCalibration | None, grid: int, what: str) -> None:
    """``ValueError`` naming --calib when the rig calibration is for another zone grid."""
    if calibration is not None and calibration.grid != grid:
        raise ValueError(f"--calib is for a {calibration.grid}x{calibration.grid} zone grid, "
                         f"{what} has {grid}x{grid}")


def check_depth_size(frame: MapFrame, source: Any) -> None:
    """``ValueError`` naming the recorded depth (file or topic) when it is not the size
    of its colour image: it must be registered to the camera, pixel for pixel."""
    depth, image = frame.recorded_depth_m, frame.image
    if depth is not None and depth.shape[:2] != image.shape[:2]:
        raise ValueError(f"{source}: the recorded depth is {depth.shape[1]}x{depth.shape[0]} "
                         f"pixels, its colour image {image.shape[1]}x{image.shape[0]}; depth "
                         "must be registered to the colour camera, pixel for pixel")


def _undistorted_once(frame: MapFrame) -> Iterator[MapFrame]:
    """Yield a loaded ``frame`` with its image and recorded depth undistorted (the latter
    by nearest pixels: interpolating makes depths no surface has) and the undistorted
    camera's calibration; then release its images and give its calibration back."""
    calibration = frame.calibration
    if calibration.has_distortion:
        frame.image = calibration.undistort_image(frame.image)
        if frame.recorded_depth_m is not None and \
                frame.recorded_depth_m.shape[:2] == frame.image.shape[:2]:  # else refused later
            frame.recorded_depth_m = calibration.undistort_image(frame.recorded_depth_m,
                                                                 nearest=True)
        frame.calibration = calibration.undistorted()
    try:
        yield frame
    finally:
        frame.image, frame.recorded_depth_m, frame.calibration = None, None, calibration
