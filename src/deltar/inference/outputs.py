"""Writers for predicted depth: 16-bit PNG, .npy, colour PNG, PLY point cloud, panel.

Every writer is atomic (``deltar.io.atomic``) and refuses to replace an existing file
unless ``overwrite=True``.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.camera import CameraIntrinsics, backproject_pixels, check_image
from deltar.io import ply
from deltar.io.atomic import atomic_path, write_bytes_atomic

if TYPE_CHECKING:
    from deltar.inference.prediction import DepthPrediction

#: Largest depth a 16-bit millimetre PNG can hold, metres.
PNG16_MAX_M = 65.535
#: Output kinds written by :func:`write_prediction`, with their file suffixes.
OUTPUT_KINDS = {"png16": "_depth_mm.png", "npy": "_depth_m.npy", "sigma": "_sigma_m.npy",
                "color": "_depth_color.png", "ply": "_cloud.ply", "panel": "_panel.png"}


def _check_depth(depth_m: np.ndarray, name: str = "depth_m") -> np.ndarray:
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"{name} must be an (H, W) array, got shape {depth.shape}")
    return depth


#: Metadata note of outputs made without any valid zone (PNG ``tEXt`` "deltar", PLY
#: comment, panel title).
IMAGE_ONLY_NOTE = "image-only estimate: no valid zone, metric scale unknown"


def _encode_png(image: np.ndarray, note: str | None = None) -> bytes:
    """PNG bytes of ``image``; ``note`` goes into a ``tEXt`` chunk with keyword "deltar"."""
    import zlib

    import cv2

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    data = data.tobytes()
    if note:
        # Insert the chunk right after IHDR (8-byte signature + 25-byte IHDR chunk).
        body = b"tEXt" + b"deltar\0" + note.encode("latin-1", "replace")
        chunk = (len(body) - 4).to_bytes(4, "big") + body + \
            zlib.crc32(body).to_bytes(4, "big")
        data = data[:33] + chunk + data[33:]
    return data


def depth_to_png16(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) depth in metres -> (H, W) uint16 millimetres; 0 where invalid or not finite.

    Depths beyond 65.535 m are clipped to 65535 mm.
    """
    depth = _check_depth(depth_m).astype(np.float64)
    good = np.isfinite(depth) & (depth > 0)
    mm = np.where(good, np.round(np.clip(depth, 0.0, PNG16_MAX_M) * 1000.0), 0.0)
    return mm.astype(np.uint16)


def write_depth_png16(path: str | os.PathLike, depth_m: np.ndarray, *,
                      overwrite: bool = False, note: str | None = None) -> Path:
    """Write (H, W) depth in metres as a 16-bit PNG in millimetres (0 = invalid).

    ``note``, when given, is stored as a PNG ``tEXt`` chunk with keyword "deltar".
    """
    return write_bytes_atomic(path, _encode_png(depth_to_png16(depth_m), note),
                              overwrite=overwrite)


def write_depth_npy(path: str | os.PathLike, depth_m: np.ndarray, *,
                    overwrite: bool = False) -> Path:
    """Write (H, W) depth as a float32 ``.npy`` file in metres."""
    buffer = io.BytesIO()
    np.save(buffer, _check_depth(depth_m), allow_pickle=False)
    return write_bytes_atomic(path, buffer.getvalue(), overwrite=overwrite)


def colorize(values: np.ndarray, vmin: float | None = None, vmax: float | None = None,
             cmap: str = "turbo") -> np.ndarray:
    """Map an (H, W) array to (H, W, 3) uint8 RGB with a colour map.

    Args:
        values: (H, W) values, e.g. depth in metres; non-finite values come out black.
        vmin, vmax: colour range; by default the 1st and 99th percentiles of the
            finite values.
        cmap: colour map name (matplotlib's; without matplotlib, OpenCV's table of it:
            :func:`deltar.io.render.colormap`).
    """
    from deltar.io.render import colormap

    data = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(data)
    if vmin is None or vmax is None:
        lo, hi = np.percentile(data[finite], [1, 99]) if finite.any() else (0.0, 1.0)
        vmin = lo if vmin is None else vmin
        vmax = hi if vmax is None else vmax
    span = max(float(vmax) - float(vmin), 1e-9)
    scaled = np.clip((np.where(finite, data, vmin) - vmin) / span, 0.0, 1.0)
    rgb = colormap(scaled, cmap)
    rgb[~finite] = 0.0
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def write_color_png(path: str | os.PathLike, depth_m: np.ndarray, *,
                    vmin: float | None = None, vmax: float | None = None,
                    overwrite: bool = False, note: str | None = None) -> Path:
    """Write a colourised depth PNG (turbo colour map, near = blue); ``note`` as tEXt."""
    import cv2

    rgb = colorize(_check_depth(depth_m), vmin, vmax)
    return write_bytes_atomic(path, _encode_png(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), note),
                              overwrite=overwrite)


def depth_to_points(depth_m: np.ndarray, intrinsics: CameraIntrinsics,
                    image: np.ndarray | None = None, stride: int = 1
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a depth map to a coloured point cloud in the camera frame.

    :func:`deltar.camera.backproject_pixels` with the colours of the kept pixels.

    Args:
        depth_m: (H, W) z-depth in metres; pixels that are 0 or infinite are skipped.
        intrinsics: intrinsics of the (H, W) image.
        image: optional (H, W, 3) uint8 RGB colours (grey when None).
        stride: keep every ``stride``-th pixel in each direction.

    Returns:
        points (N, 3) float32 metres (x right, y down, z forward) and colours (N, 3) uint8.
    """
    points, rows, cols = backproject_pixels(_check_depth(depth_m), intrinsics, stride=stride)
    if image is None:
        colors = np.full((points.shape[0], 3), 200, dtype=np.uint8)
    else:
        colors = np.asarray(image, dtype=np.uint8)[rows, cols]
    return points.astype(np.float32), colors


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray,
              intrinsics: CameraIntrinsics | None = None, *, overwrite: bool = False,
              note: str | None = None) -> Path:
    """Write a predicted point cloud as binary little-endian PLY (:func:`deltar.io.ply.write_ply`).

    Args:
        points: (N, 3) points in metres, camera frame (x right, y down, z forward).
        colors: (N, 3) uint8 RGB colours.
        intrinsics: when given, a header comment ``intrinsics fx fy cx cy width height``.
        note: another header comment (e.g. :data:`IMAGE_ONLY_NOTE`).
    """
    comments = ["written by deltar", "frame camera (x right, y down, z forward), metres"]
    if intrinsics is not None:
        i = intrinsics
        comments.append(f"intrinsics {i.fx!r} {i.fy!r} {i.cx!r} {i.cy!r} {i.width} {i.height}")
    if note:
        comments.append(note)
    return ply.write_ply(path, points, colors, comments=comments, overwrite=overwrite)


def zone_outline_style(valid: bool, no_target: bool) -> dict[str, str]:
    """Matplotlib edge colour and line style of a zone's outline in a panel: green solid
    when valid, blue dotted when it reported no target, red dashed otherwise."""
    if valid:
        return {"edgecolor": "lime", "linestyle": "-"}
    if no_target:
        return {"edgecolor": "deepskyblue", "linestyle": ":"}
    return {"edgecolor": "red", "linestyle": "--"}


def write_panel(path: str | os.PathLike, image: np.ndarray, prediction: DepthPrediction, *,
                title: str = "", overwrite: bool = False) -> Path:
    """Write a four-panel PNG: image, zones over the image, depth, uncertainty (metres).

    Args:
        path: output ``.png``.
        image: (H, W, 3) uint8 RGB input.
        prediction: the estimator's result for ``image``.
        title: figure title (e.g. the frame name and the weights).
        overwrite: replace an existing file.

    Drawn with matplotlib when it is installed (the ``plots`` extra), else with OpenCV
    (:mod:`deltar.io.render`: the same four pictures, colour maps and zone colours).
    """
    from deltar.io.render import has_matplotlib

    if not has_matplotlib():
        return _write_panel_opencv(path, image, prediction, title, overwrite)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import patheffects
    from matplotlib.patches import Rectangle

    frame = prediction.zone_frame
    mean, valid, far_zones, vmax, zones_title = _panel_zones_and_range(prediction)
    depth = prediction.depth_m
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    try:
        axes[0, 0].imshow(image)
        axes[0, 0].set_title("image")
        axes[0, 1].imshow(image)
        for (y0, x0, y1, x1), value, ok, far in zip(prediction.zone_rects, mean, valid,
                                                    far_zones, strict=True):
            axes[0, 1].add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False,
                                           linewidth=0.8, **zone_outline_style(ok, far)))
            if ok and frame.grid <= 8:
                label = axes[0, 1].text((x0 + x1) / 2, (y0 + y1) / 2, f"{value:.2f}",
                                        color="white", fontsize=5, ha="center", va="center")
                # A dark outline keeps the label readable on bright surfaces.
                label.set_path_effects([patheffects.withStroke(linewidth=1.5,
                                                                foreground="black")])
        axes[0, 1].set_xlim(-0.5, image.shape[1] - 0.5)
        axes[0, 1].set_ylim(image.shape[0] - 0.5, -0.5)
        axes[0, 1].set_title(zones_title)
        shown = axes[1, 0].imshow(depth, cmap="turbo", vmin=0.0, vmax=vmax)
        fig.colorbar(shown, ax=axes[1, 0], label="m")
        axes[1, 0].set_title("depth")
        shown = axes[1, 1].imshow(prediction.uncertainty_m, cmap="magma")
        fig.colorbar(shown, ax=axes[1, 1], label="m")
        axes[1, 1].set_title("uncertainty (std)")
        for ax in axes.ravel():
            ax.set_axis_off()
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        with atomic_path(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def _write_panel_opencv(path: str | os.PathLike, image: np.ndarray,
                        prediction: DepthPrediction, title: str, overwrite: bool) -> Path:
    """:func:`write_panel` without matplotlib (:func:`deltar.io.render.compose_panel`)."""
    from deltar.io.render import Tile, compose_panel, draw_zones, scalar_tile, write_panel_png

    mean, valid, far_zones, vmax, zones_title = _panel_zones_and_range(prediction)
    depth, spread = prediction.depth_m, prediction.uncertainty_m
    finite = np.isfinite(spread)
    low, high = (float(spread[finite].min()), float(spread[finite].max())) if finite.any() \
        else (0.0, 1.0)
    rgb = np.ascontiguousarray(image, dtype=np.uint8)
    panel = compose_panel([Tile(rgb, "image"),
                           Tile(draw_zones(rgb, prediction.zone_rects, valid, far_zones,
                                           mean if prediction.zone_frame.grid <= 8 else None),
                                zones_title),
                           scalar_tile(depth, "depth", "turbo", 0.0, vmax),
                           scalar_tile(spread, "uncertainty (std)", "magma", low, high)],
                          columns=2, title=title)
    return write_panel_png(path, panel, overwrite=overwrite)


def _panel_zones_and_range(prediction: DepthPrediction
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, str]:
    """What both panel renderers draw the zones and depth with: the zones' means (m),
    validity, no-target flags, the depth colour scale's top (99th percentile, m) and
    the zone tile's title."""
    frame = prediction.zone_frame
    mean, _, valid = frame.flat()
    # The flags the prediction used: inferred ones too, for a frame that carried none.
    far_zones = (frame.flat_no_target() if prediction.zone_no_target is None
                 else np.asarray(prediction.zone_no_target, dtype=bool))
    depth = prediction.depth_m
    vmax = float(np.percentile(depth[np.isfinite(depth)], 99)) if np.isfinite(depth).any() \
        else 1.0
    title = ("zones (m; blue = no target, red = invalid)" if far_zones.any()
             else "zones (m; red = invalid)")
    return mean, valid, far_zones, vmax, title


def write_prediction(out_dir: str | os.PathLike, stem: str, image: np.ndarray,
                     prediction: DepthPrediction, *, kinds: tuple[str, ...] = tuple(OUTPUT_KINDS),
                     title: str = "", overwrite: bool = False, ply_stride: int = 1
                     ) -> dict[str, Path]:
    """Write the chosen outputs of one prediction as ``out_dir/<stem><suffix>``.

    Args:
        out_dir: output folder (created if missing).
        stem: file-name stem, e.g. the input image's stem.
        image: (H, W, 3) uint8 RGB input (colours of the point cloud, panel).
        prediction: the estimator's result.
        kinds: any of :data:`OUTPUT_KINDS` (``png16``, ``npy``, ``sigma``: the per-pixel
            uncertainty as float32 metres, ``color``, ``ply``, ``panel``).
        title: panel title.
        overwrite: replace existing outputs (default: ``FileExistsError``).
        ply_stride: point-cloud subsampling stride in pixels.

    A prediction made without any valid zone (``prediction.image_only``) is flagged in
    every format that has metadata: :data:`IMAGE_ONLY_NOTE` in a PNG ``tEXt`` chunk
    (keyword "deltar"), a PLY comment and the panel title.

    Returns:
        dict kind -> written path.
    """
    unknown = set(kinds) - set(OUTPUT_KINDS)
    if unknown:
        raise ValueError(f"unknown output kinds {sorted(unknown)}; known: {list(OUTPUT_KINDS)}")
    # Everything checked before the first file: a failure never leaves some outputs.
    if not hasattr(prediction, "depth_m") or not hasattr(prediction, "uncertainty_m"):
        raise ValueError(f"prediction must be a DepthPrediction, got {type(prediction).__name__}")
    check_image(image, "image", prediction.depth_m.shape)
    if Path(stem).name != stem or stem in ("", ".", ".."):
        raise ValueError(f"stem must be a file name without folders, got {stem!r}")
    note = IMAGE_ONLY_NOTE if getattr(prediction, "image_only", False) else None
    if note:
        title = f"{title} - {note.upper()}" if title else note.upper()
    out = Path(out_dir)
    paths = {kind: out / f"{stem}{OUTPUT_KINDS[kind]}" for kind in kinds}
    if not overwrite:
        existing = [str(p) for p in paths.values() if p.exists()]
        if existing:
            raise FileExistsError(f"refusing to overwrite existing outputs: {existing}")
    depth = prediction.depth_m
    if "png16" in paths:
        write_depth_png16(paths["png16"], depth, overwrite=overwrite, note=note)
    if "npy" in paths:
        write_depth_npy(paths["npy"], depth, overwrite=overwrite)
    if "sigma" in paths:
        write_depth_npy(paths["sigma"], prediction.uncertainty_m, overwrite=overwrite)
    if "color" in paths:
        write_color_png(paths["color"], depth, overwrite=overwrite, note=note)
    if "ply" in paths:
        points, colors = depth_to_points(depth, prediction.intrinsics, image, ply_stride)
        write_ply(paths["ply"], points, colors, prediction.intrinsics, overwrite=overwrite,
                  note=note)
    if "panel" in paths:
        write_panel(paths["panel"], image, prediction, title=title, overwrite=overwrite)
    return paths
