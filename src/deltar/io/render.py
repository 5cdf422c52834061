"""Colour maps and picture panels, with or without matplotlib.

matplotlib (the ``plots`` extra) draws the panels of ``deltar predict`` and the
evaluation when it is installed. The base install has no matplotlib (it would be an
eighth of the install's size): there :func:`colormap` reads OpenCV's tables of the same
colour maps, and :func:`compose_panel` lays out a panel with OpenCV (titles, colour
bars with their range, zone outlines and readings), with the same content and colour
meaning as the matplotlib one.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deltar.extras import module_available

#: matplotlib colour map name -> OpenCV's table of the same map.
OPENCV_COLORMAPS = {"turbo": "COLORMAP_TURBO", "magma": "COLORMAP_MAGMA",
                    "jet": "COLORMAP_JET", "viridis": "COLORMAP_VIRIDIS",
                    "inferno": "COLORMAP_INFERNO", "plasma": "COLORMAP_PLASMA"}
#: Outline colours (RGB) of zones in panels: valid, no target, invalid.
ZONE_RGB = {"valid": (0, 255, 0), "no_target": (0, 191, 255), "invalid": (255, 0, 0)}

__all__ = ["ColorBar", "Tile", "colormap", "compose_panel", "draw_zones", "has_matplotlib"]


def has_matplotlib() -> bool:
    """Whether matplotlib is installed (the ``plots`` extra)."""
    return module_available("matplotlib")


@functools.cache
def _opencv_table(name: str) -> np.ndarray:
    """(256, 3) float64 RGB in [0, 1] of colour map ``name`` (``_r``: reversed)."""
    import cv2

    base = name[:-2] if name.endswith("_r") else name
    if base not in OPENCV_COLORMAPS:
        raise ValueError(f"cmap must be one of {sorted(OPENCV_COLORMAPS)} (or *_r) without "
                         f"matplotlib, got {name!r}")
    ramp = np.arange(256, dtype=np.uint8)[:, None]
    bgr = cv2.applyColorMap(ramp, getattr(cv2, OPENCV_COLORMAPS[base]))[:, 0]
    table = bgr[:, ::-1].astype(np.float64) / 255.0
    return table[::-1] if name.endswith("_r") else table


def colormap(scaled: np.ndarray, name: str = "turbo") -> np.ndarray:
    """Colours of values already scaled to [0, 1]: (..., 3) float64 RGB in [0, 1].

    Args:
        scaled: (...) values in [0, 1] (clipped).
        name: a colour map name (matplotlib's when it is installed; else one of
            :data:`OPENCV_COLORMAPS`, ``_r`` for reversed).
    """
    values = np.clip(np.asarray(scaled, dtype=np.float64), 0.0, 1.0)
    if has_matplotlib():
        import matplotlib

        if name not in matplotlib.colormaps:
            raise ValueError(f"unknown colour map {name!r}; e.g. turbo, viridis, magma "
                             "(matplotlib's names)")
        return matplotlib.colormaps[name](values)[..., :3]
    # matplotlib's lookup of its 256-entry tables: int(x * 256), the top value in the last.
    index = np.minimum((values * 256).astype(np.int64), 255)
    return _opencv_table(name)[index]


@dataclass(frozen=True)
class ColorBar:
    """A colour bar beside a panel tile: the map, its range and its unit."""

    vmin: float
    vmax: float
    cmap: str
    unit: str = "m"


@dataclass(frozen=True)
class Tile:
    """One picture of a panel: (H, W, 3) uint8 RGB, a title, an optional colour bar."""

    image: np.ndarray
    title: str
    bar: ColorBar | None = None


def scalar_tile(values: np.ndarray, title: str, cmap: str, vmin: float, vmax: float,
                unit: str = "m") -> Tile:
    """A tile of an (H, W) map (e.g. depth in metres) in colour map ``cmap`` over
    ``[vmin, vmax]``; non-finite values are white (left blank), as matplotlib shows NaN."""
    data = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(data)
    span = max(float(vmax) - float(vmin), 1e-9)
    rgb = colormap((np.where(finite, data, vmin) - vmin) / span, cmap)
    rgb[~finite] = 1.0
    image = (rgb * 255.0 + 0.5).astype(np.uint8)
    return Tile(image, title, ColorBar(float(vmin), float(vmax), cmap, unit))


def draw_zones(image: np.ndarray, rects: np.ndarray, valid: np.ndarray,
               no_target: np.ndarray, means_m: np.ndarray | None = None) -> np.ndarray:
    """The image with the zone outlines and readings drawn on it (OpenCV).

    Args:
        image: (H, W, 3) uint8 RGB.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixel-centre coordinates.
        valid: (Z,) bool; no_target: (Z,) bool.
        means_m: (Z,) readings in metres, written in the valid zones.

    Returns:
        A new (H, W, 3) uint8 RGB image: valid zones green, no-target ones blue, other
        invalid ones red (:data:`ZONE_RGB`).
    """
    import cv2

    out = np.ascontiguousarray(image, dtype=np.uint8).copy()
    for i, (y0, x0, y1, x1) in enumerate(np.asarray(rects, dtype=np.float64)):
        kind = "valid" if valid[i] else ("no_target" if no_target[i] else "invalid")
        # A zone covers pixel centres in [x0, x1): its first and last pixels.
        top_left = (round(x0 + 0.5), round(y0 + 0.5))
        bottom_right = (round(x1 - 0.5), round(y1 - 0.5))
        cv2.rectangle(out, top_left, bottom_right, ZONE_RGB[kind], 1, cv2.LINE_8)
        if valid[i] and means_m is not None and len(rects) <= 64:
            text = f"{means_m[i]:.2f}"
            (width, height), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.3, 1)
            centre = ((top_left[0] + bottom_right[0]) // 2, (top_left[1] + bottom_right[1]) // 2)
            origin = (centre[0] - width // 2, centre[1] + height // 2)
            # White on a dark outline: readable on bright and dark surfaces alike.
            for colour, thickness in (((0, 0, 0), 2), ((255, 255, 255), 1)):
                cv2.putText(out, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.3, colour,
                            thickness, cv2.LINE_AA)
    return out


_TITLE_PX = 24
_BAR_PX = 14
_BAR_TEXT_PX = 56
_MARGIN_PX = 8


def _text(canvas: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45
          ) -> None:
    import cv2

    cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1,
                cv2.LINE_AA)


def _tile_canvas(tile: Tile) -> np.ndarray:
    """One tile with its title above and its colour bar to the right, white ground."""
    height, width = tile.image.shape[:2]
    extra = (_MARGIN_PX + _BAR_PX + _BAR_TEXT_PX) if tile.bar is not None else 0
    canvas = np.full((_TITLE_PX + height + _MARGIN_PX, width + extra + 2 * _MARGIN_PX, 3),
                     255, dtype=np.uint8)
    canvas[_TITLE_PX:_TITLE_PX + height, _MARGIN_PX:_MARGIN_PX + width] = tile.image
    _text(canvas, tile.title, (_MARGIN_PX, _TITLE_PX - 8))
    if tile.bar is not None:
        left = _MARGIN_PX + width + _MARGIN_PX
        ramp = colormap(np.linspace(1.0, 0.0, height)[:, None], tile.bar.cmap)
        canvas[_TITLE_PX:_TITLE_PX + height, left:left + _BAR_PX] = \
            (ramp * 255 + 0.5).astype(np.uint8)
        unit = f" {tile.bar.unit}" if tile.bar.unit else ""
        _text(canvas, f"{tile.bar.vmax:.2f}{unit}", (left + _BAR_PX + 4, _TITLE_PX + 10), 0.35)
        _text(canvas, f"{tile.bar.vmin:.2f}{unit}", (left + _BAR_PX + 4, _TITLE_PX + height),
              0.35)
    return canvas


def compose_panel(tiles: Sequence[Tile], columns: int, title: str = "") -> np.ndarray:
    """Lay out tiles in a grid of ``columns`` (OpenCV): (H, W, 3) uint8 RGB.

    Args:
        tiles: the pictures, row by row.
        columns: tiles per row.
        title: text above the grid.
    """
    canvases = [_tile_canvas(tile) for tile in tiles]
    cell_h = max(c.shape[0] for c in canvases)
    cell_w = max(c.shape[1] for c in canvases)
    rows = -(-len(canvases) // columns)
    top = _TITLE_PX if title else 0
    panel = np.full((top + rows * cell_h, columns * cell_w, 3), 255, dtype=np.uint8)
    for index, canvas in enumerate(canvases):
        row, col = divmod(index, columns)
        y, x = top + row * cell_h, col * cell_w
        panel[y:y + canvas.shape[0], x:x + canvas.shape[1]] = canvas
    if title:
        _text(panel, title, (_MARGIN_PX, _TITLE_PX - 6), 0.5)
    return panel


def write_panel_png(path: str | os.PathLike, panel: np.ndarray, *, overwrite: bool = True
                    ) -> Path:
    """Write an (H, W, 3) uint8 RGB panel (:func:`compose_panel`) as a PNG, atomically.

    Raises:
        ValueError: the panel could not be encoded (naming ``path``).
        FileExistsError: ``path`` exists and not ``overwrite``.
    """
    import cv2

    from deltar.io.atomic import write_bytes_atomic

    ok, data = cv2.imencode(".png", cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"could not encode {path} as PNG")
    return write_bytes_atomic(path, data.tobytes(), overwrite=overwrite)
