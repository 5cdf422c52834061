"""Replay a recording: pair zone frames with images by time, predict, write or show.

Without a rig calibration, zones are placed with the recording's own camera
intrinsics and sensor field of view, sensor and camera assumed at the same place
(identity extrinsic).
"""

from __future__ import annotations

import itertools
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.calibration.rig import RigCalibration, pairing_time_offset
from deltar.inference.folder import FRAME_ERRORS
from deltar.io.pairing import one_per_image
from deltar.io.read_ahead import read_ahead
from deltar.io.recording import META_FILE, Recording, RecordingPair
from deltar.sensor.geometry import SensorExtrinsics

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator
    from deltar.inference.prediction import DepthPrediction

#: A gap between zone frames longer than this many median periods is reported.
GAP_FACTOR = 3.0


@dataclass
class ReplayItem:
    """One replayed frame.

    Attributes:
        pair: the recording's zone frame with its colour (and depth) image.
        image: (H, W, 3) uint8 RGB, undistorted when the calibration has lens
            distortion: the image the predicted depth belongs to.
        prediction: the estimator's result.
        reference_depth_m: (H, W) recorded depth in metres (0 invalid) or None,
            undistorted (nearest pixel) as the image.
    """

    pair: RecordingPair
    image: np.ndarray
    prediction: DepthPrediction
    reference_depth_m: np.ndarray | None


def recording_calibration(recording: Recording) -> RigCalibration:
    """A nominal calibration from a recording's metadata (identity extrinsic)."""
    meta = recording.meta
    return RigCalibration(intrinsics=meta.intrinsics, extrinsics=SensorExtrinsics(),
                          grid=meta.grid, fov_deg=meta.fov_deg, sensor_model=meta.sensor_model)


def check_recording_image(pair: RecordingPair, image: np.ndarray, calibration: RigCalibration,
                          own: Recording | None = None) -> None:
    """Refuse a pair's (H, W, 3) image of another size than the rig it is read with: the
    user's ``calibration`` (named ``--calib``) or, with ``own``, the recording's own
    camera (:func:`recording_calibration`, naming its ``meta.json``).

    Raises:
        ValueError: naming the image file and what it disagrees with.
    """
    if own is None:
        calibration.check_image_size(image.shape[:2], str(pair.color_path), "--calib")
        return
    calibration.check_image_size(
        image.shape[:2], str(pair.color_path), str(own.folder / META_FILE),
        f"the recording's images and its {META_FILE} disagree (give --calib for these images)")


def check_gaps(recording: Recording, pairs: list[RecordingPair]) -> list[tuple[float, float]]:
    """Warn about gaps in the zone-frame stream; return them as (start_s, length_s).

    A gap is an interval between consecutive zone frames longer than
    :data:`GAP_FACTOR` times the median interval.
    """
    times = np.array([p.zone_frame.timestamp_s for p in pairs], dtype=np.float64)
    if times.size < 3:
        return []
    steps = np.diff(times)
    limit = GAP_FACTOR * float(np.median(steps))
    gaps = [(float(times[i]), float(steps[i])) for i in np.flatnonzero(steps > limit)]
    for start, length in gaps:
        warnings.warn(f"{recording.folder}: {length:.3f} s gap in the zone frames after "
                      f"t = {start:.3f} s (median period {np.median(steps):.3f} s)",
                      stacklevel=2)
    return gaps


def replay_pairs(recording: Recording, pairs: list[RecordingPair], time_offset_s: float
                 ) -> list[RecordingPair]:
    """The pairs a replay predicts: one per colour image, the zone frame nearest it
    (the others counted in a warning). Outputs are named by the image, so a second
    zone frame on one image would write over the first."""
    return one_per_image(pairs, lambda p: p.color_path,
                         lambda p: abs(p.color_offset_s - time_offset_s), recording.folder)


def replay(recording: str | os.PathLike | Recording, estimator: DepthEstimator, *,
           calibration: RigCalibration | None = None, tolerance_s: float = 0.02,
           time_offset_s: float | None = None, every: int = 1, limit: int | None = None,
           skip_no_zones: bool = False,
           on_failure: Callable[[RecordingPair, Exception], None] | None = None,
           skip_pair: Callable[[RecordingPair], bool] | None = None
           ) -> Iterator[ReplayItem]:
    """Predict depth for each zone frame of a recording that has a colour image near it.

    Zone frames without a colour image within ``tolerance_s`` are skipped with a
    warning (by ``Recording.pairs``), as are those that share an image with a zone
    frame nearer to it (:func:`replay_pairs`); gaps in the stream are warned about.

    Args:
        recording: the recording folder (or an open :class:`Recording`).
        estimator: the depth estimator.
        calibration: rig calibration; a nominal one from the recording's metadata when
            None (see :func:`recording_calibration`).
        tolerance_s: largest |image time - zone time| for a pair, seconds.
        time_offset_s: camera clock minus sensor clock, seconds, applied when pairing
            (default: the calibration's ``time_offset_s``, 0 without one).
        every: use every ``every``-th pair (>= 1).
        limit: stop after this many predictions.
        skip_no_zones: skip zone frames without any valid zone (with a warning) instead
            of predicting image-only estimates (see ``DepthPrediction.image_only``).
        on_failure: when given, a frame whose images cannot be read or whose prediction
            refuses its input (:data:`deltar.inference.folder.FRAME_ERRORS`) is passed to
            it and skipped; without it the error ends the replay.
        skip_pair: pairs for which it returns True are not read nor predicted (e.g.
            frames whose outputs exist); they still count towards ``limit``.

    Yields:
        :class:`ReplayItem` per predicted frame, in time order.

    Raises:
        FileNotFoundError / ValueError: missing or corrupt recording files (naming them),
            unsorted timestamps, a calibration for another resolution.
    """
    if int(every) < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    rec = recording if isinstance(recording, Recording) else Recording(recording)
    calib = calibration or recording_calibration(rec)
    calib.check_image_size((rec.meta.intrinsics.height, rec.meta.intrinsics.width),
                           f"the recording {rec.folder}")
    offset = pairing_time_offset(calib, time_offset_s)
    pairs = rec.pairs(tolerance_s=tolerance_s, time_offset_s=offset)
    check_gaps(rec, pairs)  # gaps in the sensor's own stream: before any is left out
    pairs = replay_pairs(rec, pairs, offset)

    def selected() -> Iterator[RecordingPair]:
        for pair in pairs[::int(every)]:
            if pair.zone_frame.valid_count == 0:
                what = "skipped" if skip_no_zones else "image-only estimate"
                warnings.warn(f"{rec.folder}: zone frame at t = "
                              f"{pair.zone_frame.timestamp_s:.3f} s has no valid zone; {what}",
                              stacklevel=5)
                if skip_no_zones:
                    continue
            yield pair

    # `limit` pairs at most (after the skipped ones), none read beyond them; the next
    # pair's images are read while the estimator works on this one.
    wanted = selected() if limit is None else itertools.islice(selected(), max(0, int(limit)))
    if skip_pair is not None:
        wanted = (pair for pair in wanted if not skip_pair(pair))
    # The depth is for the undistorted image: each image is undistorted once, here, and
    # predicted with the calibration of undistorted images (predict would undistort again).
    pinhole = calib.undistorted()
    for pair, loaded in read_ahead(wanted, RecordingPair.load_images):
        try:
            image, reference = loaded.result()
            check_recording_image(pair, image, calib, rec if calibration is None else None)
            image = calib.undistort_image(image)
            try:
                prediction = estimator.predict(image, pair.zone_frame, pinhole)
            except ValueError as err:  # name the frame: the message may not
                raise ValueError(f"{pair.color_path}: {err}") from err
        except FRAME_ERRORS as err:
            if on_failure is None:
                raise
            on_failure(pair, err)
            continue
        # Hand out the image and the recorded depth that belong to the depth.
        yield ReplayItem(pair, image, prediction,
                         None if reference is None else calib.undistort_image(reference,
                                                                              nearest=True))


def replay_to_folder(recording: str | os.PathLike, estimator: DepthEstimator,
                     out_dir: str | os.PathLike, *, kinds: tuple[str, ...] = ("png16", "npy",
                                                                              "color"),
                     calibration: RigCalibration | None = None, tolerance_s: float = 0.02,
                     time_offset_s: float | None = None, every: int = 1,
                     limit: int | None = None, overwrite: bool = False,
                     on_item: Callable[[ReplayItem], None] | None = None,
                     skip_no_zones: bool = False,
                     on_failure: Callable[[RecordingPair, Exception], None] | None = None,
                     skip_existing: bool = False) -> list[Path]:
    """Replay a recording and write outputs named by the colour image's time stamp.

    Arguments as :func:`replay`; frames without a valid zone are written as flagged
    image-only estimates unless ``skip_no_zones``. With ``on_failure`` a frame that
    fails (unreadable images, refused input, its outputs not written) is reported to it
    and skipped. With ``skip_existing`` (resuming) a frame whose outputs all exist is
    left out and one with only some gets the missing ones.

    Returns:
        The written files.

    Raises:
        ValueError: ``out_dir`` lies inside the recording (inputs are never touched).
    """
    from deltar.inference.outputs import OUTPUT_KINDS, write_prediction

    rec = Recording(recording)
    out = Path(out_dir).resolve()
    if out == rec.folder.resolve() or rec.folder.resolve() in out.parents:
        raise ValueError(f"output folder {out_dir} is inside the recording {rec.folder}; "
                         "choose a folder outside it")

    def missing(pair: RecordingPair) -> tuple[str, ...]:
        stem = pair.color_path.stem
        return tuple(k for k in kinds if not (out / f"{stem}{OUTPUT_KINDS[k]}").exists()) \
            if skip_existing else tuple(kinds)

    written: list[Path] = []
    for item in replay(rec, estimator, calibration=calibration, tolerance_s=tolerance_s,
                       time_offset_s=time_offset_s, every=every, limit=limit,
                       skip_no_zones=skip_no_zones, on_failure=on_failure,
                       skip_pair=(lambda pair: not missing(pair)) if skip_existing else None):
        try:
            paths = write_prediction(out, item.pair.color_path.stem, item.image,
                                     item.prediction, kinds=missing(item.pair),
                                     overwrite=overwrite,
                                     title=f"{item.pair.color_path.name} "
                                     f"({estimator.weights})")
        except FRAME_ERRORS as err:
            if on_failure is None:
                raise
            on_failure(item.pair, err)
            continue
        written.extend(paths.values())
        if on_item is not None:
            on_item(item)
    return written
