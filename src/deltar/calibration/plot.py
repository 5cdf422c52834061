"""Pictures of the zone layout in the image, before and after calibration."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deltar.calibration.rig import RigCalibration
from deltar.io.atomic import atomic_path
from deltar.sensor.zone_frame import ZoneFrame


def plot_zones_before_after(path: str | os.PathLike, image_rgb: np.ndarray, frame: ZoneFrame,
                            before: RigCalibration, after: RigCalibration, *,
                            title: str = "", overwrite: bool = False) -> Path:
    """Draw the frame's zones over the image with two calibrations, side by side (PNG).

    Args:
        path: output PNG (written atomically).
        image_rgb: (H, W, 3) uint8 RGB image at the calibrated resolution.
        frame: the zone frame (zones are placed at their measured distance; invalid zones
            are dashed).
        before: e.g. the nominal calibration.
        after: the solved calibration.
        title: figure title.
        overwrite: replace an existing file.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    image = np.asarray(image_rgb)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image_rgb must be (H, W, 3), got {image.shape}")
    height, width = image.shape[:2]
    _, _, valid = frame.flat()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, calib, label in ((axes[0], before, "before (nominal)"),
                             (axes[1], after, "after calibration")):
        rects = calib.zone_rects_for(frame, (height, width))
        ax.imshow(image)
        for rect, ok in zip(rects, valid, strict=True):
            y0, x0, y1, x1 = (float(r) for r in rect)
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, linewidth=0.8,
                                   edgecolor="lime" if ok else "red",
                                   linestyle="-" if ok else "--"))
        ax.set_xlim(-0.5, width - 0.5)
        ax.set_ylim(height - 0.5, -0.5)
        ax.set_title(label)
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return Path(path)
