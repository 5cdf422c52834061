"""Depth for a folder of frames: plan the outputs, resume, keep going past failures.

:func:`plan_jobs` is made before the network is built: it lists the outputs that exist
(the caller refuses them, or passes ``overwrite``) or, with ``skip_existing``, leaves
out frames whose outputs all exist, and frames with only some of them (a run stopped in
the middle of a frame) write the missing ones. :func:`run_jobs` then predicts and
writes each frame; a frame that fails stops the run, or with ``keep_going`` is
reported to ``on_failure`` and skipped. The summary says what happened as values:
frames written, image-only frames (no valid zone) by name, failures with their errors.
``deltar predict`` is a thin layer over these two.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator
    from deltar.sensor.zone_frame import Orientation, ZoneFrame

#: Errors of one frame's input (bad or missing files, wrong values) that ``keep_going``
#: skips; anything else is a bug and always stops the run.
FRAME_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, ImportError)


@dataclass(frozen=True)
class FrameJob:
    """One image / zone-frame pair and the outputs still to write for it.

    Attributes:
        image: the colour image file.
        zones: its zone-frame file.
        kinds: output kinds to write (see ``deltar.inference.outputs.OUTPUT_KINDS``).
    """

    image: Path
    zones: Path
    kinds: tuple[str, ...]


@dataclass
class JobSummary:
    """What a run did.

    Attributes:
        written: frames with all their outputs written.
        image_only: file names of the frames written as image-only estimates (no valid
            zone; metric scale unknown).
        failed: (image file name, error) of the frames that failed (``keep_going``).
    """

    written: int = 0
    image_only: list[str] = field(default_factory=list)
    failed: list[tuple[str, BaseException]] = field(default_factory=list)


def plan_jobs(pairs: Sequence[tuple[Path, Path]], out: Path, kinds: Sequence[str], *,
              overwrite: bool, skip_existing: bool
              ) -> tuple[list[FrameJob], int, list[Path]]:
    """The frames to run and the outputs each still needs.

    Args:
        pairs: (image, zone file) pairs.
        out: output folder.
        kinds: requested output kinds.
        overwrite: write every output, replacing existing files.
        skip_existing: keep existing outputs, write only the missing ones.

    Returns:
        (jobs, number of frames whose outputs all exist already, the existing outputs
        the jobs would replace: empty with ``overwrite`` or ``skip_existing``; those
        frames are not among the jobs).

    Raises:
        ValueError: an output would replace one of the inputs.
    """
    from deltar.inference.outputs import OUTPUT_KINDS

    inputs = {p.resolve() for pair in pairs for p in pair}
    jobs, complete, existing = [], 0, []
    for image, zones in pairs:
        targets = {kind: out / f"{image.stem}{OUTPUT_KINDS[kind]}" for kind in kinds}
        for target in targets.values():
            if target.resolve() in inputs:
                raise ValueError(f"output {target} would overwrite an input file")
        present = [kind for kind, path in targets.items() if path.exists()]
        if overwrite or not present:
            jobs.append(FrameJob(image, zones, tuple(kinds)))
        elif skip_existing:
            missing = tuple(k for k in kinds if k not in present)
            if missing:
                jobs.append(FrameJob(image, zones, missing))
            else:
                complete += 1
        else:
            existing += [targets[kind] for kind in present]
    return jobs, complete, existing


def check_valid_zones(frame: ZoneFrame, zone_path: Path, allow_no_zones: bool = False,
                      allow: str = "allow_no_zones") -> None:
    """Refuse a frame without a valid zone unless ``allow_no_zones``: its depth would be a
    guess from the image alone. The one such check of a folder run (:func:`run_jobs`,
    and the CLI on its first frame before loading a model).

    Raises:
        ValueError: naming the zone file, why and how to accept it (``allow``: the
            argument or option that does).
    """
    if frame.valid_count == 0 and not allow_no_zones:
        no_target = 0 if frame.no_target is None else int(np.count_nonzero(frame.no_target))
        # Open space is not a fault: say so, the scale is then only "beyond the range".
        why = f"all {frame.zone_count} report no target: nothing within the sensor's range" \
            if no_target == frame.zone_count else \
            f"all {frame.zone_count} invalid: error codes, out of range or flagged invalid" \
            + (f"; {no_target} report no target" if no_target else "")
        raise ValueError(f"{zone_path}: no valid zone ({why}), so the depth would be a "
                         f"guess from the image alone; pass {allow} to write it as an "
                         "image-only estimate")


def run_jobs(jobs: Sequence[FrameJob], estimator: DepthEstimator, out: Path, *,
             calibration: Any = None, overwrite: bool = False, keep_going: bool = False,
             allow_no_zones: bool = False, first: tuple[Any, ZoneFrame] | None = None,
             on_prediction: Callable[[FrameJob, Any, Any], None] | None = None,
             on_failure: Callable[[str, BaseException], None] | None = None,
             on_frame: Callable[[], None] | None = None,
             allow_option: str = "allow_no_zones",
             orientation: Orientation | None = None) -> JobSummary:
    """Predict and write every job.

    Args:
        jobs: from :func:`plan_jobs`.
        estimator: the depth estimator.
        out: output folder.
        calibration: optional rig calibration.
        overwrite: replace existing outputs.
        keep_going: skip a frame that fails with one of :data:`FRAME_ERRORS` (else its
            error stops the run).
        allow_no_zones: write frames without a valid zone as image-only estimates
            (else such a frame fails).
        first: the first job's already decoded (image (H, W, 3) uint8, zone frame).
        on_prediction: ``callable(job, rgb, prediction)`` after each written frame (e.g.
            a live viewer; ``prediction.image_only`` says whether it had no valid zone).
        on_failure: ``callable(image name, error)`` for each skipped frame.
        on_frame: called after each frame, written or not (e.g. a progress bar).
        allow_option: how the no-valid-zone refusal names ``allow_no_zones``.
        orientation: how raw driver dumps' zone grids map onto the images
            (:func:`~deltar.io.zone_file.load_zone_frame`); None: as stored.

    Returns:
        A :class:`JobSummary`.
    """
    from deltar.data.rgbd_files import read_color
    from deltar.inference.outputs import write_prediction
    from deltar.io.read_ahead import read_ahead
    from deltar.io.zone_file import load_zone_frame

    def load(indexed: tuple[int, FrameJob]) -> tuple[Any, ZoneFrame]:
        index, job = indexed
        if index == 0 and first is not None:
            return first
        return read_color(job.image), load_zone_frame(job.zones, orientation=orientation)

    summary = JobSummary()
    # The depth is for the undistorted image: predicted with the calibration of
    # undistorted images, on images undistorted once (predict would undistort again).
    distorted = getattr(calibration, "has_distortion", False)
    pinhole = calibration.undistorted() if distorted else calibration
    # The next job's files are read while the estimator works on this one.
    for (_, job), loaded in read_ahead(enumerate(jobs), load):
        try:
            rgb, frame = loaded.result()
            check_valid_zones(frame, job.zones, allow_no_zones, allow_option)
            try:
                if pinhole is not calibration:  # undistorted once, here
                    rgb = calibration.undistort_image(rgb)
                prediction = estimator.predict(rgb, frame, pinhole)
            except ValueError as err:
                raise ValueError(f"{job.image.name} with {job.zones.name}: {err}") from err
            write_prediction(out, job.image.stem, rgb, prediction, kinds=job.kinds,
                             overwrite=overwrite,
                             title=f"{job.image.name} ({estimator.weights})")
            summary.written += 1
            if on_prediction is not None:
                on_prediction(job, rgb, prediction)
            if prediction.image_only:
                summary.image_only.append(job.image.name)
        except FRAME_ERRORS as err:
            if not keep_going:
                raise
            summary.failed.append((job.image.name, err))
            if on_failure is not None:
                on_failure(job.image.name, err)
        if on_frame is not None:
            on_frame()
    return summary
