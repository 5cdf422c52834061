"""``deltar predict`` over many frames: plan the outputs, resume, keep going past failures.

The plan is made before the network is built: existing outputs are refused (unless
``--overwrite``) or, with ``--skip-existing``, frames whose outputs all exist are left
out and frames with only some of them (a run stopped in the middle of a frame) write
the missing ones. While running, a frame that fails stops the run, or with
``--keep-going`` is reported and skipped; the summary counts the failures.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deltar.cli.errors import USER_ERRORS, format_error, warn

if TYPE_CHECKING:
    from deltar.inference.estimator import DepthEstimator
    from deltar.sensor.zone_frame import ZoneFrame

#: Option that lets frames without a valid zone through as image-only estimates.
ALLOW_NO_ZONES = "--allow-no-zones"


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
        skipped_existing: frames left out because their outputs exist.
        image_only: frames written as image-only estimates (no valid zone).
        failed: (frame file name, error message) of frames that failed.
    """

    written: int = 0
    skipped_existing: int = 0
    image_only: int = 0
    failed: list[tuple[str, str]] = field(default_factory=list)


def plan_jobs(pairs: Sequence[tuple[Path, Path]], out: Path, kinds: Sequence[str], *,
              overwrite: bool, skip_existing: bool) -> tuple[list[FrameJob], int]:
    """The frames to run and the outputs each still needs.

    Args:
        pairs: (image, zone file) pairs.
        out: output folder.
        kinds: requested output kinds.
        overwrite: write every output, replacing existing files.
        skip_existing: keep existing outputs, write only the missing ones.

    Returns:
        (jobs, number of frames whose outputs all exist already).

    Raises:
        ValueError: an output would replace one of the inputs.
        FileExistsError: outputs exist and neither ``overwrite`` nor ``skip_existing``.
    """
    from deltar.cli.checks import existing_outputs
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
    existing_outputs(existing)
    return jobs, complete


def no_zone_message(zone_path: Path, frame: ZoneFrame) -> str:
    """Why a frame without a valid zone is refused, and how to accept it."""
    return (f"{zone_path}: no valid zone (all {frame.zone_count} invalid: error codes, out "
            "of range or flagged invalid), so the depth would be a guess from the image "
            f"alone; pass {ALLOW_NO_ZONES} to write it as an image-only estimate")


def image_only_warning(name: str) -> str:
    """The warning printed for a frame written as an image-only estimate."""
    return (f"{name}: no valid zone: wrote an image-only estimate (metric scale unknown, "
            "uncertainty at least the depth; flagged in the PNG and PLY metadata and the "
            "panel)")


def run_jobs(jobs: Sequence[FrameJob], estimator: DepthEstimator, out: Path, *,
             calibration: Any = None, overwrite: bool = False, keep_going: bool = False,
             allow_no_zones: bool = False, progress: Any = None,
             first: tuple[Any, ZoneFrame] | None = None,
             on_prediction: Any = None) -> JobSummary:
    """Predict and write every job.

    Args:
        jobs: from :func:`plan_jobs`.
        estimator: the depth estimator.
        out: output folder.
        calibration: optional rig calibration.
        overwrite: replace existing outputs.
        keep_going: report a failing frame and go on (else its error stops the run).
        allow_no_zones: write frames without a valid zone as image-only estimates
            (else such a frame fails).
        progress: optional :class:`~deltar.cli.progress.ProgressReport`.
        first: the first job's already decoded (image, zone frame), if any.
        on_prediction: optional ``callable(rgb, prediction)`` called after each written
            frame (e.g. a live viewer).

    Returns:
        A :class:`JobSummary`.
    """
    import warnings

    from deltar.data.rgbd import read_color
    from deltar.inference.outputs import write_prediction
    from deltar.io.zone_file import load_zone_frame

    summary = JobSummary()
    for index, job in enumerate(jobs):
        try:
            if index == 0 and first is not None:
                rgb, frame = first
            else:
                rgb, frame = read_color(job.image), load_zone_frame(job.zones)
            if frame.valid_count == 0 and not allow_no_zones:
                raise ValueError(no_zone_message(job.zones, frame))
            try:
                with warnings.catch_warnings():
                    # Said once per frame below, in the CLI's words.
                    warnings.filterwarnings("ignore", message=".*no valid zone")
                    prediction = estimator.predict(rgb, frame, calibration)
            except ValueError as err:
                raise ValueError(f"{job.image.name} with {job.zones.name}: {err}") from err
            write_prediction(out, job.image.stem, rgb, prediction, kinds=job.kinds,
                             overwrite=overwrite,
                             title=f"{job.image.name} ({estimator.weights})")
            summary.written += 1
            if on_prediction is not None:
                on_prediction(rgb, prediction)
            if prediction.image_only:
                summary.image_only += 1
                warn(image_only_warning(job.image.name))
        except USER_ERRORS as err:
            if not keep_going:
                raise
            summary.failed.append((job.image.name, format_error(err)))
            warn(f"skipped {job.image.name}: {format_error(err)}")
        if progress is not None:
            progress.advance()
    return summary
