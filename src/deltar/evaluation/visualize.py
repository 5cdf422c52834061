"""PNG panels of one frame: image, zones over the image, prediction, error map."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.io.atomic import atomic_path

if TYPE_CHECKING:
    from deltar.data.zju_l5 import ZJUL5Sample


def safe_filename(name: str) -> str:
    """A frame or method name as one file-name component (``/`` and ``:`` become ``__``)."""
    cleaned = re.sub(r"[/\\:]+", "__", name)
    cleaned = re.sub(r"[^A-Za-z0-9._+-]", "_", cleaned).strip(".")
    return cleaned or "frame"


def save_frame_panel(path: str | Path, sample: ZJUL5Sample, depth_m: np.ndarray,
                     method: str, *, max_depth_m: float | None = None,
                     max_error_m: float | None = None) -> Path:
    """Write a four-panel PNG for one frame and one method, atomically.

    Panels: the RGB image; the image with the zone rectangles (green = valid, labelled
    with the zone mean in metres; red dashed = invalid); the predicted depth (metres,
    colour bar); the absolute error ``|pred - gt|`` on pixels with ground truth (metres,
    colour bar, pixels without ground truth left blank).

    Args:
        path: output ``.png`` path; its folder is created if needed.
        sample: the frame (``rgb`` (H, W, 3), ``depth_m`` (H, W), zones).
        depth_m: (H, W) predicted depth in metres.
        method: method name for the title.
        max_depth_m: top of the depth colour scale; default the 99th percentile of the
            ground truth and prediction.
        max_error_m: top of the error colour scale; default the 99th percentile of the
            error.

    Drawn with matplotlib when it is installed (the ``plots`` extra), else with OpenCV
    (:mod:`deltar.io.render`: the same four pictures, colour maps and zone colours).

    Returns:
        The written path.
    """
    from deltar.io.render import has_matplotlib

    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.shape != sample.depth_m.shape:
        raise ValueError(f"depth_m shape {depth.shape} does not match the frame "
                         f"{sample.depth_m.shape}")
    gt = sample.depth_m
    has_gt = gt > 0
    error = np.where(has_gt, np.abs(depth - gt), np.nan)
    if max_depth_m is None:
        values = np.concatenate([gt[has_gt], depth.reshape(-1)])
        max_depth_m = float(np.percentile(values, 99)) if values.size else 1.0
    if max_error_m is None:
        max_error_m = float(np.nanpercentile(error, 99)) if has_gt.any() else 1.0
    max_error_m = max(max_error_m, 1e-3)
    flags = (np.zeros_like(sample.zone_valid) if sample.zone_no_target is None
             else sample.zone_no_target)
    zones_title = ("zones (green valid, blue no target, red invalid)" if flags.any()
                   else "zones (green valid, red invalid)")
    means = sample.zone_mean_sigma[:, 0]
    if not has_matplotlib():
        from deltar.io.render import (
            Tile,
            compose_panel,
            draw_zones,
            scalar_tile,
            write_panel_png,
        )

        panel = compose_panel([Tile(sample.rgb, sample.name),
                               Tile(draw_zones(sample.rgb, sample.zone_rects, sample.zone_valid,
                                               flags, means), zones_title),
                               scalar_tile(depth, f"{method}: depth (m)", "magma_r", 0.0,
                                           max_depth_m),
                               scalar_tile(error, "|pred - gt| (m)", "jet", 0.0, max_error_m)],
                              columns=4)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        return write_panel_png(path, panel)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from deltar.inference.outputs import zone_outline_style

    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2), constrained_layout=True)
    axes[0].imshow(sample.rgb)
    axes[0].set_title(sample.name)
    axes[1].imshow(sample.rgb)
    axes[1].set_title(zones_title)
    for (y0, x0, y1, x1), valid, far, mean in zip(sample.zone_rects, sample.zone_valid,
                                                  flags, means, strict=True):
        # Rectangles are in pixel-centre coordinates, as imshow's axes are.
        axes[1].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, linewidth=1,
                                    **zone_outline_style(valid, far)))
        if valid:
            axes[1].text(0.5 * (x0 + x1), 0.5 * (y0 + y1), f"{mean:.2f}", color="white",
                         fontsize=6, ha="center", va="center", clip_on=True)
    image = axes[2].imshow(depth, cmap="magma_r", vmin=0.0, vmax=max_depth_m)
    axes[2].set_title(f"{method}: depth (m)")
    fig.colorbar(image, ax=axes[2], fraction=0.046)
    image = axes[3].imshow(error, cmap="jet", vmin=0.0, vmax=max_error_m)
    axes[3].set_title("|pred - gt| (m)")
    fig.colorbar(image, ax=axes[3], fraction=0.046)
    height, width = gt.shape
    for axis in axes:
        axis.set_xlim(-0.5, width - 0.5)
        axis.set_ylim(height - 0.5, -0.5)
        axis.set_xticks([])
        axis.set_yticks([])
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=80)
    plt.close(fig)
    return Path(path)
