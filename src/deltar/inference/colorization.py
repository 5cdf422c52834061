"""Colorization fill of zone readings: Levin et al.'s image-guided completion.

The zone means are placed on small squares at the zone centres and propagated along the
image by solving the colorization system (3x3 affinities, as the NYU toolbox's
``fill_depth_colorization``) on a grid of about :data:`COLORIZATION_SOLVE_CELLS` cells,
whatever the image size, then upsampled. The classical ``colorization`` baseline
(:mod:`deltar.evaluation.baselines`) and the estimator's confidence blend
(:mod:`deltar.inference.blend`) both use :func:`colorize_zones`.
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse

from deltar.camera import check_image
from deltar.inference.stencil_solver import (
    EXACT_TOLERANCE,
    NEIGHBOUR_OFFSETS,
    solve_stencil_system,
    sparse_system,
)

#: Cells of the colorization solve (60 x 80 for a 4:3 image, whatever its size).
COLORIZATION_SOLVE_CELLS = 4800
#: Side, in solve cells, of the square each zone mean is placed on.
COLORIZATION_SEED_SIDE = 3


def _affinity_weights(gray: np.ndarray) -> np.ndarray:
    """(8, h, w) row-normalised neighbour weights of :func:`colorization_matrix`.

    Entry [k, y, x] is ``w_pq`` for p = (y, x) and q = p + ``NEIGHBOUR_OFFSETS[k]``;
    0 where q is outside the image. Each cell's weights sum to 1. Float64 throughout:
    the window statistics are those of NumPy's ``nanvar`` / ``nanmin`` over the cell and
    its neighbours inside the image (the same sums in another order, so equal to a few
    float64 roundings). One plane per neighbour: the sums and minima over the
    neighbours are then element-wise operations on whole planes, not reductions along a
    short last axis, which cost NumPy several times as much.
    """
    height, width = gray.shape
    padded = np.pad(gray, 1)
    neighbours = np.stack([padded[1 + dy:1 + dy + height, 1 + dx:1 + dx + width]
                           for dy, dx in NEIGHBOUR_OFFSETS])  # (8, H, W), 0 outside
    window = _window_constants if height * width <= _CACHED_WINDOW_CELLS \
        else _window_constants.__wrapped__  # a full-size image's would hold tens of MB
    inside, count, outside_penalty = window(height, width)
    # In place where the order of the roundings stays that of the plain expressions.
    mean = neighbours.sum(axis=0)
    mean += gray
    mean /= count
    deviation = neighbours - mean
    deviation *= inside
    deviation *= deviation
    centre = gray - mean
    centre *= centre
    variance = deviation.sum(axis=0)
    variance += centre
    variance /= count
    sq_diff = neighbours  # the neighbours are not needed again
    sq_diff -= gray
    sq_diff *= sq_diff
    penalised = sq_diff + outside_penalty
    min_sq_diff = penalised.min(axis=0)
    variance *= 0.6
    scale = np.maximum(variance, min_sq_diff / -math.log(0.01))
    np.maximum(scale, 2e-6, out=scale)
    weights = np.divide(sq_diff, scale, out=penalised)
    np.negative(weights, out=weights)
    np.exp(weights, out=weights)
    weights *= inside
    weights /= weights.sum(axis=0)
    return weights


#: Grids up to this many cells keep their window constants between calls (the solve
#: grids: 2400 and 4800 cells; about 80 bytes a cell).
_CACHED_WINDOW_CELLS = 20_000


@functools.lru_cache(maxsize=8)
def _window_constants(height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inside, count, outside_penalty) of a grid's 3x3 windows, read-only, kept per size:
    :func:`_inside_mask`, the cells in each window (centre included) and float64's
    largest value where a neighbour is outside (so a minimum over neighbours skips it)."""
    inside = _inside_mask(height, width)
    count = inside.sum(axis=0) + 1.0
    outside_penalty = (1.0 - inside) * np.finfo(np.float64).max
    for constant in (inside, count, outside_penalty):
        constant.setflags(write=False)
    return inside, count, outside_penalty


def _inside_mask(height: int, width: int) -> np.ndarray:
    """(8, h, w) float64: 1 where the neighbour ``NEIGHBOUR_OFFSETS[k]`` is on the grid."""
    rows = np.arange(height)[None, :, None]
    cols = np.arange(width)[None, None, :]
    dy = np.array([dy for dy, _ in NEIGHBOUR_OFFSETS])[:, None, None]
    dx = np.array([dx for _, dx in NEIGHBOUR_OFFSETS])[:, None, None]
    return ((rows + dy >= 0) & (rows + dy < height) & (cols + dx >= 0)
            & (cols + dx < width)).astype(np.float64)


def colorization_matrix(gray: np.ndarray) -> scipy.sparse.csr_matrix:
    """Levin et al.'s affinity Laplacian (3x3 windows), as in the NYU toolbox's fill.

    Args:
        gray: (h, w) float intensity image in [0, 1].

    Returns:
        (h*w, h*w) sparse CSR matrix over the pixels in row-major order. Row p is
        ``x_p - sum_q w_pq x_q`` with ``w_pq`` proportional to ``exp(-(I_p - I_q)^2 / s_p)``,
        ``s_p`` = 0.6 x the local intensity variance, bounded below so that the closest
        neighbour keeps a weight of at least 1 % (and by 2e-6).
    """
    gray = np.asarray(gray, dtype=np.float64)
    return sparse_system(_affinity_weights(gray), np.ones(gray.shape),
                          list(NEIGHBOUR_OFFSETS)).tocsr()


def colorization_fill(gray: np.ndarray, known_values: np.ndarray, known_mask: np.ndarray,
                      alpha: float = 1.0, tolerance: float = EXACT_TOLERANCE) -> np.ndarray:
    """Fill a sparse map guided by an intensity image (Levin et al. colorization).

    Solves ``(L + alpha D) x = alpha D v`` where L is the colorization affinity Laplacian
    of ``gray`` (:func:`colorization_matrix`), D the diagonal of ``known_mask`` and v the
    known values. The solution is a weighted average of the known values, so it stays
    inside their range. The solve is direct
    (:func:`~deltar.inference.stencil_solver.solve_stencil_system`): with the default
    ``tolerance`` the result is the exact solution up to float64 rounding.

    Args:
        gray: (h, w) float intensity image in [0, 1].
        known_values: (h, w) values at the known pixels (e.g. depth in metres).
        known_mask: (h, w) bool, True where the value is known (at least one pixel).
        alpha: weight of the data term.
        tolerance: the refinement of the single-precision solve stops once a correction
            is at most this fraction of the solution's largest value; the error left is
            then that correction times the refinement's contraction (1e-4 to 1e-3 on
            image grids), so 1e-3 leaves about 1e-7 of the values' scale (one step).

    Returns:
        (h, w) float64 filled map.
    """
    gray = np.asarray(gray, dtype=np.float64)
    known_mask = np.asarray(known_mask, dtype=bool)
    if gray.ndim != 2 or known_mask.shape != gray.shape or known_values.shape != gray.shape:
        raise ValueError(f"gray, known_values and known_mask must be (h, w) arrays of one "
                         f"shape, got {gray.shape}, {known_values.shape}, {known_mask.shape}")
    if not known_mask.any():
        raise ValueError("known_mask must mark at least one pixel")
    _check_tolerance(tolerance)
    return _fill(_affinity_weights(gray), known_values, known_mask, alpha, tolerance)


def _fill(weights: np.ndarray, known_values: np.ndarray, known_mask: np.ndarray,
          alpha: float, tolerance: float) -> np.ndarray:
    """:func:`colorization_fill` with the grid's (8, h, w) affinity weights given."""
    data = alpha * known_mask.astype(np.float64)
    rhs = data * np.where(known_mask, known_values, 0.0)
    return solve_stencil_system(weights, 1.0 + data, rhs, float(tolerance))


def _check_tolerance(tolerance: float) -> None:
    if isinstance(tolerance, bool) or not (isinstance(tolerance, numbers.Real)
                                           and 0.0 < tolerance < 1.0):
        raise ValueError(f"tolerance must be a fraction in (0, 1), got {tolerance!r}")


@dataclass(frozen=True, eq=False)
class ColorizationGuide:
    """The image's part of :func:`colorize_zones`, which needs no zone: the solve grid's
    intensities and affinity weights (:func:`colorization_guide`). A stream can make it
    while the zones are still being read and placed.

    Attributes:
        image_size: (H, W) pixels of the image the grid was resized from (the zone
            rectangles given with it are in its pixels).
        solve_cells: the ``solve_cells`` it was made for.
        gray: (h, w) float64 grid intensities in [0, 1].
        weights: (8, h, w) float64 affinity weights of the grid
            (:func:`colorization_matrix`'s, in ``NEIGHBOUR_OFFSETS`` order).
        source_size: (H, W) pixels of the image the caller started from, before any
            halving (:func:`deltar.inference.blend.blend_fill` halves it); ``image_size``
            by default.
    """

    image_size: tuple[int, int]
    solve_cells: int
    gray: np.ndarray
    weights: np.ndarray
    source_size: tuple[int, int]


def colorization_guide(image_rgb: np.ndarray, solve_cells: int = COLORIZATION_SOLVE_CELLS,
                       source_size: tuple[int, int] | None = None) -> ColorizationGuide:
    """The :class:`ColorizationGuide` of an image: resized by area means to about
    ``solve_cells`` cells with its aspect, to gray, and the grid's affinity weights.

    Args:
        image_rgb: (H, W, 3) uint8 RGB image.
        solve_cells: cells of the solve grid (integer >= 4; clipped to the pixel count).
        source_size: (H, W) of the image the caller started from, when ``image_rgb`` is
            a reduced copy of it; ``image_rgb``'s size by default.

    Raises:
        ValueError: a bad image or ``solve_cells``.
    """
    _check_solve_cells(solve_cells)
    image_rgb = check_image(image_rgb, "image_rgb")
    height, width = image_rgb.shape[0], image_rgb.shape[1]
    scale = min(1.0, math.sqrt(solve_cells / (height * width)))
    small_h = max(2, round(height * scale))
    small_w = max(2, round(width * scale))
    image = cv2.resize(image_rgb, (small_w, small_h), interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0
    size = (height, width)
    return ColorizationGuide(image_size=size, solve_cells=int(solve_cells), gray=gray,
                             weights=_affinity_weights(gray),
                             source_size=size if source_size is None
                             else (int(source_size[0]), int(source_size[1])))


def _check_solve_cells(solve_cells: int) -> None:
    if isinstance(solve_cells, bool) or not isinstance(solve_cells, numbers.Integral) \
            or solve_cells < 4:
        raise ValueError(f"solve_cells must be an integer >= 4, got {solve_cells!r}")


def colorize_zones(image_rgb: np.ndarray | ColorizationGuide, zone_mean_m: np.ndarray,
                   zone_valid: np.ndarray,
                   zone_rects: np.ndarray, solve_cells: int = COLORIZATION_SOLVE_CELLS,
                   seed_side: int = COLORIZATION_SEED_SIDE,
                   tolerance: float = EXACT_TOLERANCE,
                   out_size: tuple[int, int] | None = None) -> np.ndarray | None:
    """Dense depth from zone readings by colorization: seeds at zone centres, filled, upsampled.

    The fill is solved on a grid of about ``solve_cells`` cells with the image's aspect
    (60 x 80 for 480 x 640 or 240 x 320 images), so its result and its cost do not
    depend on the image size. Each valid zone's mean is placed on a square of
    ``seed_side`` x ``seed_side`` cells at its centre (about 3/8 of a zone at 60 x 80 with
    8 x 8 zones): a single cell per zone would leave spikes, as harmonic fills do around
    isolated points. A centre outside the image is moved to the nearest cell inside its
    zone's overlap with the image; zones that do not overlap the image are skipped.

    Args:
        image_rgb: (H, W, 3) uint8 RGB image (the guide), or its
            :class:`ColorizationGuide` made earlier for the same ``solve_cells`` (then
            (H, W) is its ``image_size``: for a guide of a halved image, as
            :func:`~deltar.inference.blend.blend_fill` makes, the halved one, and
            ``zone_rects`` are in its pixels; ``blend_fill`` scales them).
        zone_mean_m: (Z,) zone readings, metres.
        zone_valid: (Z,) bool, at least one True.
        zone_rects: (Z, 4) (y0, x0, y1, x1) zone rectangles in image pixels.
        solve_cells: number of cells of the linear solve (speed; clipped to the image's
            pixel count).
        seed_side: side of each seed square in cells (odd).
        tolerance: accuracy of the solve (:func:`colorization_fill`); the default gives
            the float64 solution, as the classical ``colorization`` baseline reports it.
        out_size: (h, w) pixels of the returned map, which covers the whole image
            (e.g. a network's output grid); the image's (H, W) by default.

    Returns:
        (H, W) (or ``out_size``) float32 depth in metres within the range of the valid
        readings, or None when no valid zone overlaps the image.

    Raises:
        ValueError: bad ``solve_cells`` / ``seed_side`` / ``tolerance``, an image that
            is not (H, W, 3) uint8 or a guide made for other ``solve_cells``, zone arrays
            of mismatched shapes, no valid zone, or a non-finite or non-positive valid
            reading (the message names the argument).
    """
    _check_solve_cells(solve_cells)
    if isinstance(seed_side, bool) or not isinstance(seed_side, numbers.Integral) \
            or seed_side < 1 or seed_side % 2 == 0:
        raise ValueError(f"seed_side must be a positive odd integer (cells), got {seed_side!r}")
    _check_tolerance(tolerance)
    if isinstance(image_rgb, ColorizationGuide):
        if image_rgb.solve_cells != solve_cells:
            raise ValueError(f"image_rgb is a guide for {image_rgb.solve_cells} cells, "
                             f"solve_cells is {solve_cells}")
    else:
        image_rgb = check_image(image_rgb, "image_rgb")
    if out_size is not None and not (len(out_size) == 2 and all(
            isinstance(v, numbers.Integral) and not isinstance(v, bool) and v > 0
            for v in out_size)):
        raise ValueError(f"out_size must be (h, w) positive integers (pixels), got {out_size!r}")
    zone_mean_m = np.asarray(zone_mean_m, dtype=np.float64).reshape(-1)
    zone_valid = np.asarray(zone_valid, dtype=bool).reshape(-1)
    zone_rects = np.asarray(zone_rects, dtype=np.float64)
    count = zone_mean_m.size
    if count == 0 or zone_valid.size != count or zone_rects.shape != (count, 4):
        raise ValueError(f"zone_mean_m (Z,), zone_valid (Z,) and zone_rects (Z, 4) must "
                         f"describe the same Z > 0 zones, got {zone_mean_m.shape}, "
                         f"{zone_valid.shape}, {zone_rects.shape}")
    if not zone_valid.any():
        raise ValueError("colorize_zones needs at least one valid zone (zone_valid)")
    if not (np.all(np.isfinite(zone_mean_m[zone_valid])) and np.all(zone_mean_m[zone_valid] > 0)
            and np.all(np.isfinite(zone_rects))):
        raise ValueError("zone_mean_m must be finite and > 0 where zone_valid, and zone_rects "
                         "finite")
    guide = image_rgb if isinstance(image_rgb, ColorizationGuide) \
        else colorization_guide(image_rgb, solve_cells)
    height, width = guide.image_size
    small_h, small_w = guide.gray.shape
    sy, sx = small_h / height, small_w / width
    # Pixel centres sit at integer coordinates, so coordinates scale about -0.5.
    rects = zone_rects[zone_valid]
    y0, y1 = (rects[:, 0] + 0.5) * sy - 0.5, (rects[:, 2] + 0.5) * sy - 0.5
    x0, x1 = (rects[:, 1] + 0.5) * sx - 0.5, (rects[:, 3] + 0.5) * sx - 0.5
    values = zone_mean_m[zone_valid]
    # The fill is a weighted mean of the seeds; the clip bounds the upsampling.
    low, high = float(values.min()), float(values.max())
    overlaps = (y1 > -0.5) & (y0 < small_h - 0.5) & (x1 > -0.5) & (x0 < small_w - 0.5)
    if not overlaps.any():
        return None
    y0, y1, x0, x1, values = y0[overlaps], y1[overlaps], x0[overlaps], x1[overlaps], \
        values[overlaps]
    # Centre of each zone's part inside the image, in integer cells.
    cy = np.clip(np.rint(0.5 * (np.clip(y0, 0, small_h - 1) + np.clip(y1, 0, small_h - 1))),
                 0, small_h - 1).astype(int)
    cx = np.clip(np.rint(0.5 * (np.clip(x0, 0, small_w - 1) + np.clip(x1, 0, small_w - 1))),
                 0, small_w - 1).astype(int)
    known, known_values = _seed_squares(cy, cx, values, seed_side, (small_h, small_w))
    filled = _fill(guide.weights, known_values, known, 1.0, tolerance)
    out_h, out_w = (height, width) if out_size is None else (int(v) for v in out_size)
    depth = cv2.resize(filled.astype(np.float32), (out_w, out_h),
                       interpolation=cv2.INTER_LINEAR)
    return np.clip(depth, low, high)


def _seed_squares(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, side: int,
                  shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Each value on the ``side`` x ``side`` square of cells centred at (row, col), the
    part of it on the grid; where squares overlap, the later zone's value (as painting
    the squares in turn leaves it).

    Returns:
        (known, known_values): (h, w) bool and float64 maps.
    """
    height, width = shape
    steps = np.arange(side) - side // 2
    square_rows = np.asarray(rows)[:, None, None] + steps[None, :, None]
    square_cols = np.asarray(cols)[:, None, None] + steps[None, None, :]
    on_grid = (square_rows >= 0) & (square_rows < height) & (square_cols >= 0) \
        & (square_cols < width)
    cells = (square_rows * width + square_cols)[on_grid]
    zones = np.broadcast_to(np.arange(len(values))[:, None, None], on_grid.shape)[on_grid]
    # The highest zone index covering a cell wins, as if the squares were painted in turn.
    winner = np.full(height * width, -1)
    np.maximum.at(winner, cells, zones)
    known = winner >= 0
    known_values = np.where(known, np.asarray(values, dtype=np.float64)[winner], 0.0)
    return known.reshape(shape), known_values.reshape(shape)
