"""Replay a ROS 2 bag: pair ToF frames with camera images, predict, write a new bag.

The input bag is only read (:class:`deltar.io.rosbag_reader.BagInput`). Outputs go to a new
bag (:class:`deltar.io.rosbag_writer.BagWriter`), one message set per predicted frame, with
the camera image's header stamp, frame id and bag time:

- ``<prefix>/depth``: ``sensor_msgs/msg/Image`` ``32FC1``, metres, NaN = invalid;
- ``<prefix>/uncertainty``: the same for the per-pixel uncertainty;
- ``<prefix>/camera_info``: the intrinsics the depth is for;
- ``<prefix>/points`` (optional): ``sensor_msgs/msg/PointCloud2`` x y z rgb in the
  camera's optical frame (x right, y down, z forward).

Zones are placed with the rig calibration when given, else with the bag's CameraInfo,
the sensor's nominal field of view and an identity extrinsic.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.calibration.rig import RigCalibration, pairing_time_offset
from deltar.sensor.geometry import DEFAULT_FOV_DEG, SensorExtrinsics

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator
    from deltar.inference.prediction import DepthPrediction
    from deltar.io.rosbag_reader import BagInput, BagPair


@dataclass
class BagReplayItem:
    """One predicted frame of a bag.

    Attributes:
        pair: the ToF frame and its camera image's stamps.
        image: (H, W, 3) uint8 RGB, undistorted when the calibration has lens
            distortion: the image the predicted depth belongs to.
        prediction: the estimator's result.
        calibration: the calibration the zones were placed with.
    """

    pair: BagPair
    image: np.ndarray
    prediction: DepthPrediction
    calibration: RigCalibration


def pair_calibration(pair: BagPair, calibration: RigCalibration | None,
                     fov_deg: tuple[float, float] = DEFAULT_FOV_DEG) -> RigCalibration:
    """The given calibration, or a nominal one from the pair's CameraInfo.

    Raises:
        ValueError: neither a calibration nor a CameraInfo is available.
    """
    if calibration is not None:
        return calibration
    if pair.intrinsics is None:
        raise ValueError("the bag has no sensor_msgs/msg/CameraInfo topic; pass a rig "
                         "calibration (--calib) for the camera intrinsics")
    return RigCalibration(intrinsics=pair.intrinsics, extrinsics=SensorExtrinsics(),
                          grid=pair.zone_frame.grid, fov_deg=fov_deg,
                          sensor_model=pair.zone_frame.sensor_model)


def replay_bag(bag: BagInput, estimator: DepthEstimator, *,
               calibration: RigCalibration | None = None, tolerance_s: float = 0.02,
               time_offset_s: float | None = None, every: int = 1, limit: int | None = None,
               fov_deg: tuple[float, float] = DEFAULT_FOV_DEG, skip_no_zones: bool = False,
               pairs: list[BagPair] | None = None,
               on_total: Callable[[int], None] | None = None) -> Iterator[BagReplayItem]:
    """Predict depth for every ToF frame of a bag that has a camera image near it.

    Args:
        bag: the opened input bag.
        estimator: the depth estimator.
        calibration: rig calibration (its resolution must match the images); nominal
            from CameraInfo when None.
        tolerance_s: largest |image stamp - (ToF stamp + offset)|, seconds.
        time_offset_s: camera clock minus sensor clock, seconds, applied when pairing
            (default: the calibration's ``time_offset_s``, 0 without one).
        every: use every ``every``-th pair.
        limit: stop after this many predictions.
        fov_deg: sensor field of view of the nominal placement, degrees.
        skip_no_zones: skip ToF frames without any valid zone (with a warning) instead
            of predicting image-only estimates (see ``DepthPrediction.image_only``; they
            are warned about either way).
        pairs: the bag's pairs when already made (``bag.pairs(tolerance_s,
            time_offset_s)``: the CLI checks the first before the model); then
            ``tolerance_s`` and ``time_offset_s`` are not used.
        on_total: called once, before the first prediction, with the number of frames
            that will be predicted (after ``every``, ``limit`` and skipped frames): a
            progress display's total.

    Yields:
        :class:`BagReplayItem` per predicted frame, in bag order of the images.

    Raises:
        ValueError: images of another size than the intrinsics (naming the topic), or a
            frame the estimator refuses (naming the ToF topic and stamp).
    """
    if pairs is None:
        pairs = bag.pairs(tolerance_s=tolerance_s,
                          time_offset_s=pairing_time_offset(calibration, time_offset_s))
    chosen: list[BagPair] = []
    for pair in pairs[::max(1, int(every))]:
        if limit is not None and len(chosen) >= limit:
            break
        if pair.zone_frame.valid_count == 0:
            # As folder replay: no metric anchor, so never written without a word.
            what = "skipped" if skip_no_zones else "image-only estimate"
            warnings.warn(f"{bag.path}: {bag.tof_topic} frame stamped "
                          f"{pair.tof_stamp_ns} ns has no valid zone; {what}", stacklevel=2)
            if skip_no_zones:
                continue
        chosen.append(pair)
    if on_total is not None:
        on_total(len(chosen))
    for pair, image in bag.images(chosen):
        calib = pair_calibration(pair, calibration, fov_deg)
        size = (calib.intrinsics.height, calib.intrinsics.width)
        if image.shape[:2] != size:
            raise ValueError(f"{bag.image_topic}: images are {image.shape[0]}x{image.shape[1]},"
                             f" the camera intrinsics are for {size[0]}x{size[1]}")
        # The depth is for the undistorted image: undistorted once, here, and predicted
        # with the calibration of undistorted images (predict would undistort again).
        image = calib.undistort_image(image)
        try:
            prediction = estimator.predict(image, pair.zone_frame, calib.undistorted())
        except ValueError as err:  # name the frame: the message may not
            raise ValueError(f"{bag.path}: {bag.tof_topic} frame stamped {pair.tof_stamp_ns} "
                             f"ns: {err}") from err
        yield BagReplayItem(pair, image, prediction, calib)


def replay_bag_to_bag(bag: BagInput, estimator: DepthEstimator, out_bag: str | os.PathLike, *,
                      storage: str = "sqlite3", prefix: str = "/deltar", points: bool = False,
                      point_stride: int = 2, on_item: Callable[[BagReplayItem], None] | None = None,
                      **replay_kwargs) -> tuple[Path, int]:
    """Replay a bag and write depth, uncertainty, CameraInfo (and points) into a new bag.

    Args:
        bag: the input bag (never written).
        estimator: the depth estimator.
        out_bag: the output bag folder; must not exist nor lie inside the input bag.
        storage: ``"sqlite3"`` or ``"mcap"``.
        prefix: topic prefix of the outputs (see the module docstring).
        points: also write a coloured ``PointCloud2`` per frame.
        point_stride: keep every ``point_stride``-th pixel in each direction for points.
        on_item: called after each written frame (progress display, viewer).
        replay_kwargs: passed to :func:`replay_bag`.

    Returns:
        (the output bag path, frames written).

    A ``KeyboardInterrupt`` (Ctrl+C, or SIGTERM in the CLI) keeps the bag with the frames
    written before it (none written: no bag), warns how many, and propagates; any other
    error leaves no bag.

    Raises:
        ValueError: ``out_bag`` is the input bag or inside it.
        FileExistsError: ``out_bag`` exists.
    """
    from deltar.inference.outputs import depth_to_points
    from deltar.io.rosbag_writer import OUTPUT_TOPICS, BagWriter

    out = Path(out_bag).resolve()
    source = bag.path.resolve()
    if out == source or source in out.parents:
        raise ValueError(f"output bag {out_bag} is the input bag {bag.path} or inside it; "
                         "choose a path outside it")
    topic = {key: f"{prefix.rstrip('/')}/{name}" for key, name in OUTPUT_TOPICS.items()}
    frames = 0
    writer = BagWriter(out_bag, storage=storage)
    try:
        for item in replay_bag(bag, estimator, **replay_kwargs):
            pair, pred = item.pair, item.prediction
            stamp, frame_id, log = pair.image_stamp_ns, pair.frame_id, pair.image_log_ns
            depth = pred.depth_m
            valid = np.isfinite(depth) & (depth > 0)
            uncertainty = np.where(valid, pred.uncertainty_m, np.nan)
            # Everything computed before the first message: a stop lands between frames
            # all but always (in the few writes below it leaves the frame partial).
            cloud = depth_to_points(depth, pred.intrinsics, item.image, point_stride) \
                if points else None
            writer.add_metric_image(topic["depth"], stamp, frame_id, depth, log)
            writer.add_metric_image(topic["uncertainty"], stamp, frame_id, uncertainty, log)
            writer.add_camera_info(topic["camera_info"], stamp, frame_id, pred.intrinsics, log)
            if cloud is not None:
                writer.add_point_cloud(topic["points"], stamp, frame_id, *cloud, log)
            frames += 1
            if on_item is not None:
                on_item(item)
    except KeyboardInterrupt:
        # A stop (Ctrl+C, SIGTERM) keeps the frames replayed so far, as a stopped
        # `record --bag` does: a long replay is not lost to the key that ends it.
        if writer.close(keep=frames > 0) is not None:
            warnings.warn(f"stopped: the bag {out_bag} keeps the {frames} frames replayed "
                          "before the stop", stacklevel=2)
        raise
    except BaseException:
        writer.close(keep=False)  # an error: no bag that looks finished
        raise
    writer.close()
    return Path(out_bag), frames
