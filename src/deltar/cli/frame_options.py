"""Options and parsers shared by the commands that read frames: ``--calib``,
``--allow-no-zones``, ``--outputs``.
"""

from __future__ import annotations

from pathlib import Path

import typer

CalibOption = typer.Option(None, "--calib", help="Rig calibration JSON (deltar calibrate).")
AllowNoZonesOption = typer.Option(False, "--allow-no-zones", help="Write frames without "
                                  "any valid zone as image-only estimates (flagged; metric "
                                  "scale unknown) instead of refusing them.")


def load_calibration(path: Path | None):
    """The :class:`~deltar.calibration.rig.RigCalibration` of ``--calib`` (None without)."""
    if path is None:
        return None
    from deltar.calibration.rig import RigCalibration

    return RigCalibration.load(path)


def check_calibration_fits(calibration, calib: Path, meta, recording: Path) -> None:
    """``--calib`` against a recording's image size and zone grid (its ``meta``), before
    the model is loaded.

    Raises:
        ValueError: naming ``--calib`` and the recording.
    """
    calibration.check_image_size((meta.intrinsics.height, meta.intrinsics.width),
                                 f"the recording {recording}", f"--calib {calib}")
    if calibration.grid != meta.grid:
        raise ValueError(f"--calib {calib} is for a {calibration.grid}x{calibration.grid} zone "
                         f"grid, the recording {recording} has {meta.grid}x{meta.grid}")


def parse_outputs(text: str) -> tuple[str, ...]:
    """The output kinds of a comma list (``--outputs``), each one of ``OUTPUT_KINDS``."""
    from deltar.inference.outputs import OUTPUT_KINDS

    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    unknown = [k for k in kinds if k not in OUTPUT_KINDS]
    if unknown or not kinds:
        raise typer.BadParameter(f"--outputs must be a comma list of {list(OUTPUT_KINDS)}, "
                                 f"got {text!r}")
    return kinds
