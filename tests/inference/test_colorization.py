"""The colorization fill's solver and the blend's fill on a worker thread."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from deltar.inference import colorization, stencil_solver
from deltar.inference.blend import (
    ConfidenceBlend,
    RegionBlend,
    blend_fill,
    blend_weight,
    blend_with_fill,
    zone_grid_mask,
)
from deltar.inference.colorization import colorization_fill
from deltar.inference.fill_schedule import (
    fill_beside_network,
    start_blend_fill,
)
from tests.inference.grid_problems import edge_problem


@pytest.mark.parametrize("shape", [(12, 17), (17, 12)])
def test_single_precision_lu_is_refined_to_the_double_precision_solve(shape, monkeypatch):
    """The float32 LU with float64 refinement and the plain float64 LU give one solution."""
    gray, known, values = edge_problem(np.random.default_rng(11), shape, 0.1)
    refined = colorization_fill(gray, values, known)
    monkeypatch.setattr(stencil_solver, "_REFINEMENT_STEPS", 0)  # straight to float64
    double = colorization_fill(gray, values, known)
    np.testing.assert_allclose(refined, double, rtol=1e-10, atol=1e-12)
    assert refined.min() >= values[known].min() - 1e-9
    assert refined.max() <= values[known].max() + 1e-9


def test_seed_squares_are_painted_in_zone_order(rng):
    """Squares cut at the border; where they overlap the later zone's value, as painting
    each square in turn would leave."""
    height, width, side = 9, 11, 3
    rows, cols = rng.integers(-1, height + 1, 40), rng.integers(-1, width + 1, 40)
    values = rng.uniform(0.5, 4.0, 40)
    known, known_values = colorization._seed_squares(rows, cols, values, side,
                                                     (height, width))
    painted, painted_values = np.zeros((height, width), bool), np.zeros((height, width))
    for row, col, value in zip(rows, cols, values, strict=True):
        square = (slice(max(0, row - 1), max(0, row + 2)), slice(max(0, col - 1),
                                                                 max(0, col + 2)))
        painted[square], painted_values[square] = True, value
    np.testing.assert_array_equal(known, painted)
    np.testing.assert_array_equal(known_values, painted_values)


@pytest.mark.parametrize("swaps", [False, True])
def test_band_solves_from_the_factors_match_lapack(swaps):
    """The triangular band solves read sgbtrf's factors as gbtrs does; a factorisation
    that swapped rows is solved by gbtrs itself."""
    import scipy.linalg.lapack

    rng = np.random.default_rng(5)
    shape, band = (6, 5), 6
    size = shape[0] * shape[1]
    dense = np.zeros((size, size))
    for shift in range(-band, band + 1):
        dense += np.diag(rng.uniform(-1, 1, size - abs(shift)), shift)
    # Diagonally dominant columns need no swaps; a weak diagonal forces them.
    dense[np.diag_indices(size)] = (np.abs(dense).sum(axis=0) + 1) * (0.01 if swaps else 1)
    storage = np.zeros((3 * band + 1, size), np.float32)
    for i, j in zip(*np.nonzero(dense), strict=True):
        storage[2 * band + i - j, j] = dense[i, j]
    factors, pivots, info = scipy.linalg.lapack.sgbtrf(storage, band, band)
    assert info == 0 and np.array_equal(pivots, np.arange(size)) != swaps
    values = rng.uniform(-1, 1, size)
    solved = stencil_solver._factor_solver(factors, pivots, band, shape)(values)
    # The factors are of the transpose: the solve is of the system whose transpose it is.
    np.testing.assert_allclose(dense.T @ solved.reshape(-1), values, atol=2e-4)
    expected = scipy.linalg.lapack.sgbtrs(factors, band, band, values.astype(np.float32),
                                          pivots, trans=1)[0]
    np.testing.assert_allclose(solved.reshape(-1), expected, rtol=1e-5, atol=1e-5)


def test_only_small_grids_keep_their_window_constants(monkeypatch):
    """The solve grids reuse their constants; a full-size image's are not kept (tens of
    MB each), and both ways give the same weights."""
    gray = np.random.default_rng(2).random((30, 40))
    colorization._window_constants.cache_clear()
    cached = colorization._affinity_weights(gray)
    assert colorization._window_constants.cache_info().currsize == 1
    monkeypatch.setattr(colorization, "_CACHED_WINDOW_CELLS", 30 * 40 - 1)
    colorization._window_constants.cache_clear()
    np.testing.assert_array_equal(colorization._affinity_weights(gray), cached)
    assert colorization._window_constants.cache_info().currsize == 0


def _zones(rng: np.random.Generator, height: int = 48, width: int = 64):
    image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    rows, cols = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    zone_h, zone_w = height / 4, width / 4
    rects = np.stack([rows * zone_h, cols * zone_w, (rows + 1) * zone_h, (cols + 1) * zone_w],
                     axis=-1).reshape(16, 4).astype(np.float32)
    means = rng.uniform(0.8, 3.0, 16)
    valid = rng.random(16) > 0.2
    far = ~valid & (rng.random(16) > 0.5)
    return image, means, valid, rects, far


@pytest.mark.parametrize("beside", [True, False])
def test_the_fill_on_the_worker_thread_or_at_once_is_the_fill(rng, beside):
    image, means, valid, rects, far = _zones(rng)
    futures = [start_blend_fill(image, means, valid, rects, far, 5.0, beside=beside)
               for _ in range(3)]
    expected = blend_fill(image, means, valid, rects, far, 5.0)
    for future in futures:
        np.testing.assert_array_equal(future.result(), expected)
    assert start_blend_fill(image, means, np.zeros(16, bool), rects,
                            beside=beside).result() is None
    # A bad argument raises from result(), not from the call, on either schedule.
    failed = start_blend_fill(image, means, valid, rects, far, None, beside=beside)
    with pytest.raises(ValueError, match="far_depth_m"):
        failed.result()


def test_colorize_zones_takes_the_guide_made_earlier(rng):
    from deltar.inference.colorization import colorization_guide, colorize_zones

    image, means, valid, rects, _ = _zones(rng)
    guide = colorization_guide(image, 1200)
    assert guide.gray.shape == (30, 40) and guide.weights.shape == (8, 30, 40)
    np.testing.assert_array_equal(colorize_zones(guide, means, valid, rects, solve_cells=1200),
                                  colorize_zones(image, means, valid, rects, solve_cells=1200))
    with pytest.raises(ValueError, match="image_rgb is a guide for 1200 cells"):
        colorize_zones(guide, means, valid, rects)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX fork")
def test_a_forked_child_gets_its_own_fill_worker(rng):
    """The parent's worker thread does not survive a fork: a fill started in the child
    must run on a worker of the child's (not wait forever on the parent's queue)."""
    image, means, valid, rects, far = _zones(rng)
    expected = start_blend_fill(image, means, valid, rects, far, 5.0).result()  # worker up
    reader, writer = os.pipe()
    child = os.fork()
    if child == 0:  # the child: the fill through the worker, its bytes to the parent
        code = 1
        try:
            fill = start_blend_fill(image, means, valid, rects, far, 5.0).result(timeout=60)
            os.write(writer, fill.astype(np.float32).tobytes())
            code = 0
        finally:
            os._exit(code)
    os.close(writer)
    deadline = time.monotonic() + 90
    while (done := os.waitpid(child, os.WNOHANG))[0] == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    if done[0] == 0:
        os.kill(child, signal.SIGKILL)
        os.waitpid(child, 0)
    received = b""
    while chunk := os.read(reader, 1 << 16):
        received += chunk
    os.close(reader)
    assert done[0] == child and os.waitstatus_to_exitcode(done[1]) == 0
    np.testing.assert_array_equal(np.frombuffer(received, np.float32).reshape(expected.shape),
                                  expected)


def test_the_fill_runs_beside_pytorch_only_with_a_core_to_spare(monkeypatch):
    import torch

    assert fill_beside_network(torch_backend=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert not fill_beside_network(torch_backend=True)
        torch.set_num_threads(1)
        assert fill_beside_network(torch_backend=True)
    finally:
        torch.set_num_threads(previous)


def test_blend_with_fill_is_the_weighted_mixture(rng):
    image, means, valid, rects, _ = _zones(rng)
    depth = rng.uniform(1.0, 3.0, image.shape[:2]).astype(np.float32)
    spread = (0.1 * depth * rng.uniform(0, 2, depth.shape)).astype(np.float32)
    fill = blend_fill(image, means, valid, rects)
    blend = ConfidenceBlend(RegionBlend(-4.0, -2.0), RegionBlend(-2.0, -1.0))
    inside = zone_grid_mask(rects, depth.shape)
    weight = blend_weight(depth, spread, inside, blend).astype(np.float64)
    expected = depth.astype(np.float64) ** weight * fill.astype(np.float64) ** (1 - weight)
    got = blend_with_fill(depth, spread, fill, rects, blend)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert 0.05 < weight.mean() < 0.95  # a mixture, not one side
    with pytest.raises(ValueError, match="fill_m"):
        blend_with_fill(depth, spread, fill[:-1], rects, blend)


def _reference_weights(gray: np.ndarray) -> np.ndarray:
    """The affinity weights as first written: NaN-padded windows, nanvar and nanmin."""
    height, width = gray.shape
    padded = np.pad(gray, 1, mode="constant", constant_values=np.nan)
    neighbours = np.stack([padded[1 + dy:1 + dy + height, 1 + dx:1 + dx + width]
                           for dy, dx in stencil_solver.NEIGHBOUR_OFFSETS])
    inside = ~np.isnan(neighbours)
    variance = np.nanvar(np.concatenate([neighbours, gray[None]]), axis=0)
    sq_diff = (neighbours - gray) ** 2
    scale = np.maximum(np.maximum(0.6 * variance, -np.nanmin(sq_diff, axis=0) / np.log(0.01)),
                       2e-6)
    weights = np.where(inside, np.exp(-np.where(inside, sq_diff, 0.0) / scale), 0.0)
    return weights / weights.sum(axis=0)


@pytest.mark.parametrize("shape", [(60, 80), (7, 3), (1, 6), (2, 2)])
def test_affinity_weights_are_the_nan_window_formula(shape):
    rng = np.random.default_rng(5)
    gray = rng.random(shape)
    gray[:, : shape[1] // 2] = 0.25  # a flat part: the 2e-6 floor of the scale
    np.testing.assert_allclose(colorization._affinity_weights(gray), _reference_weights(gray),
                               rtol=0, atol=1e-12)


def test_the_blend_fill_is_the_baseline_fill_to_a_millionth(rng):
    """The blend's fill stops refining at BLEND_FILL_TOLERANCE; the classical baseline
    refines to float64. On textured frames with edges they agree within 1e-6 of the
    readings' largest value (the float32 LU alone is off by up to ~3e-4 of it). The blend
    solves that system on BLEND_FILL_CELLS cells."""
    from deltar.inference.blend import (
        BLEND_FILL_CELLS,
        BLEND_FILL_SEED_SIDE,
        BLEND_FILL_TOLERANCE,
    )
    from deltar.inference.colorization import colorize_zones

    for _ in range(4):
        image, means, valid, rects, _ = _zones(rng, 96, 128)
        image[:, 40:] //= 4  # a strong edge
        exact = colorize_zones(image, means, valid, rects)
        fast = colorize_zones(image, means, valid, rects, tolerance=BLEND_FILL_TOLERANCE)
        np.testing.assert_allclose(fast, exact, rtol=0, atol=1e-6 * means[valid].max())
        np.testing.assert_array_equal(
            blend_fill(image, means, valid, rects),
            colorize_zones(image, means, valid, rects, solve_cells=BLEND_FILL_CELLS,
                           seed_side=BLEND_FILL_SEED_SIDE, tolerance=BLEND_FILL_TOLERANCE))
    for bad in (0.0, 1.0, -1e-3, "1e-3"):
        with pytest.raises(ValueError, match="tolerance"):
            colorize_zones(image, means, valid, rects, tolerance=bad)


def test_the_blend_fill_reads_a_halved_guide_of_large_images(rng):
    """Above twice the solve grid's resolution the blend's fill reads the image halved
    (2 x 2 area means, while both sides stay even), with the zones scaled to it; the
    grid, and so the solution's resolution, stays the one of the full image."""
    from deltar.inference.blend import (
        BLEND_FILL_CELLS,
        BLEND_FILL_SEED_SIDE,
        BLEND_FILL_TOLERANCE,
        halved_guide,
    )
    from deltar.inference.colorization import colorize_zones
    from deltar.inference.preprocess import scale_rects

    for size, halved in (((480, 640), (120, 160)), ((720, 1280), (90, 160)),
                         ((240, 320), (120, 160)), ((96, 128), (96, 128)),
                         ((481, 640), (481, 640)), ((486, 648), (243, 324))):
        assert halved_guide(np.zeros((*size, 3), np.uint8), BLEND_FILL_CELLS).shape[:2] \
            == halved, size
    image, means, valid, rects, _ = _zones(rng, 480, 640)
    guide = halved_guide(image, BLEND_FILL_CELLS)
    means_4x4 = image.astype(np.float64).reshape(120, 4, 160, 4, 3).mean(axis=(1, 3))
    assert np.abs(guide - means_4x4).max() <= 1.0  # two halvings, each rounded to uint8
    assert np.abs(guide - means_4x4).mean() < 0.5
    small_rects = scale_rects(rects, (480, 640), (120, 160))
    np.testing.assert_array_equal(
        blend_fill(image, means, valid, rects, out_size=(240, 320)),
        colorize_zones(guide, means, valid, small_rects, solve_cells=BLEND_FILL_CELLS,
                       seed_side=BLEND_FILL_SEED_SIDE, tolerance=BLEND_FILL_TOLERANCE,
                       out_size=(240, 320)))
    assert blend_fill(image, means, valid, rects).shape == (480, 640)


def test_the_fill_at_another_output_size_is_the_same_solution_resampled(rng):
    """``out_size`` resamples the one solution: the estimator asks for its network's
    output grid; the map covers the whole image either way."""
    import cv2

    from deltar.inference.colorization import colorize_zones

    image, means, valid, rects, _ = _zones(rng, 96, 128)
    image[:, 40:] //= 4
    full = colorize_zones(image, means, valid, rects)
    half = colorize_zones(image, means, valid, rects, out_size=(48, 64))
    assert half.shape == (48, 64) and half.dtype == np.float32
    # Both are bilinear resamplings of the same small solution: the full map shrunk by
    # area averaging is within the interpolation's difference of the half-size one.
    shrunk = cv2.resize(full, (64, 48), interpolation=cv2.INTER_AREA)
    assert np.median(np.abs(shrunk - half)) < 1e-3 * means[valid].max()
    assert half.min() >= means[valid].min() - 1e-6 and half.max() <= means[valid].max() + 1e-6
    assert blend_fill(image, means, valid, rects, out_size=(30, 40)).shape == (30, 40)
    for bad in ((0, 64), (48,), (48.0, 64), "48x64"):
        with pytest.raises(ValueError, match="out_size"):
            colorize_zones(image, means, valid, rects, out_size=bad)
