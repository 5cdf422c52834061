"""Make the board-calibration pictures of docs/calibration.md from the synthetic rig.

Run from the repository root::

    PYTHONPATH=src python docs/images/make_calibration_pictures.py

Everything is rendered (OpenCV's board image warped onto a wall); no recorded data.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

from deltar.calibration.board import parse_board_spec
from deltar.calibration.check import check_calibration, plot_check
from deltar.calibration.rig import RigCalibration
from deltar.calibration.synthetic import look_at
from deltar.calibration.synthetic_board import (
    board_view_poses,
    render_board_image,
    write_board_recording,
)
from deltar.camera import CameraIntrinsics
from deltar.io.recording import Recording
from deltar.sensor.geometry import SensorExtrinsics

HERE = Path(__file__).parent
CAMERA = CameraIntrinsics(500.0, 505.0, 322.0, 238.0, 640, 480)
SPEC = parse_board_spec("charuco:7x5:0.04:0.03:DICT_5X5_100")
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))


def _grid(path: Path, poses: list[np.ndarray], captions: list[str], title: str) -> None:
    fig, axes = plt.subplots(1, len(poses), figsize=(3.2 * len(poses), 2.9))
    for ax, pose, caption in zip(axes, poses, captions, strict=True):
        ax.imshow(render_board_image(SPEC, pose, CAMERA))
        ax.set_title(caption, fontsize=9)
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    print(f"wrote {path}")


def _tilted(yaw_deg: float, pitch_deg: float, distance_m: float) -> np.ndarray:
    a, b = np.radians([yaw_deg, pitch_deg])
    direction = np.array([np.tan(a), np.tan(b), -1.0])
    return look_at(distance_m * direction / np.linalg.norm(direction), np.zeros(3))


def main() -> None:
    _grid(HERE / "calibration_board_good.png",
          [_tilted(-35, 0, 0.6), _tilted(30, -20, 0.7), _tilted(0, 40, 0.8),
           _tilted(28, 28, 0.6)],
          ["35 deg from the left", "from the right, below", "40 deg from above",
           "from the right, above"],
          "good views: the board tilted 25-45 deg in different directions, 0.5-0.9 m")
    _grid(HERE / "calibration_board_bad.png",
          [_tilted(0, 0, 0.7), _tilted(2, -2, 0.8), _tilted(0, 0, 2.2), _tilted(70, 0, 0.6)],
          ["head-on", "head-on again (no new direction)", "too far (2.2 m)", "grazing (70 deg)"],
          "bad views: all from one direction, too far, or grazing")
    with tempfile.TemporaryDirectory() as tmp:
        poses = board_view_poses(12, distance_m=(0.5, 0.9), tilt_deg=45, min_tilt_deg=25,
                                 seed=6)
        write_board_recording(Path(tmp) / "rec", TRUE, CAMERA, SPEC, poses, seed=6)
        bumped = RigCalibration(CAMERA, SensorExtrinsics(
            Rotation.from_euler("x", 3, degrees=True).as_matrix() @ TRUE.rotation,
            TRUE.translation_m + np.array([0.0, 0.0, 0.03])))
        rec = Recording(Path(tmp) / "rec")
        for name, calib in (("fits", RigCalibration(CAMERA, TRUE)), ("bumped", bumped)):
            check = check_calibration(rec, calib, spec=SPEC)
            label = "the true calibration" if name == "fits" else \
                "the rig bumped by 3 deg and 3 cm"
            verdict = "fits" if check.fits else "does not fit"
            path = plot_check(HERE / f"calibration_check_{name}.png", check, overwrite=True,
                              title=f"{label}: {verdict}")
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
