"""The stencil solver's compiled (numba) banded LU against dense solves and the LAPACK
path."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from deltar.inference import colorization, stencil_solver
from tests.inference.grid_problems import dense_solution, edge_problem

pytest.importorskip("numba")
from deltar.inference import stencil_solver_compiled as compiled


def _band_system(rng: np.random.Generator, size: int, band: int) -> np.ndarray:
    """A dense (size, size) matrix with half-bandwidth ``band`` whose rows are diagonally
    dominant, as the colorization system's are."""
    dense = np.zeros((size, size))
    for shift in range(-band, band + 1):
        if abs(shift) < size:
            dense += np.diag(rng.uniform(-1, 1, size - abs(shift)), shift)
    dense[np.diag_indices(size)] = np.abs(dense).sum(axis=1) + rng.uniform(0, 1, size)
    return dense


@pytest.mark.parametrize(("size", "band"), [(1, 2), (3, 2), (4, 2), (7, 3), (13, 2),
                                            (30, 9), (61, 13), (200, 43)])
def test_factor_and_solve_are_the_dense_solve(size, band):
    """Any size (whole blocks of four pivots or not) and any band (shorter than a block
    or several lanes wide)."""
    rng = np.random.default_rng(size * 100 + band)
    dense = _band_system(rng, size, band)
    # Band storage from the dense matrix, as band_rows lays it out.
    storage = np.zeros((size, compiled.band_width(band)), np.float32)
    base = band + compiled.PAD
    for i, j in zip(*np.nonzero(dense), strict=True):
        storage[i, j - i + base] = dense[i, j]
    compiled.factor(storage, band)
    values = rng.uniform(-1, 1, size).astype(np.float32)
    solved = values.copy()
    compiled.solve(storage, band, solved)
    np.testing.assert_allclose(solved, np.linalg.solve(dense, values), rtol=1e-4, atol=1e-5)
    # The padding stays zero, so the next block's zero multipliers stay zero.
    assert not storage[:, :compiled.PAD].any()


@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (2, 2), (3, 7), (12, 17), (17, 12),
                                   (42, 57)])
def test_compiled_and_lapack_fills_are_the_float64_solve(shape, monkeypatch):
    """Both paths refine the float32 LU to the float64 solution (either orientation)."""
    gray, known, values = edge_problem(np.random.default_rng(7), shape, 0.15)
    weights = colorization._affinity_weights(gray) if gray.size > 1 else np.zeros((8, 1, 1))
    exact = dense_solution(weights, 1.0 + known, known * values)
    assert stencil_solver.compiled_solver() is compiled
    fast = stencil_solver.solve_stencil_system(weights, 1.0 + known, known * values)
    monkeypatch.setattr(stencil_solver, "compiled_solver", lambda: None)
    lapack = stencil_solver.solve_stencil_system(weights, 1.0 + known, known * values)
    np.testing.assert_allclose(fast, exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(lapack, exact, rtol=1e-10, atol=1e-12)


def test_blend_tolerance_solves_agree_between_paths(monkeypatch):
    """At the blend's tolerance both paths stop within a millionth of the values' scale
    of the exact solution (they stop after different corrections, not at one value)."""
    rng = np.random.default_rng(3)
    gray = rng.random((42, 57))
    gray[10:30, 20:] *= 0.2
    known = np.zeros(gray.shape, bool)
    known[2::6, 3::7] = True
    values = np.where(known, rng.uniform(0.5, 6.0, gray.shape), 0.0)
    exact = colorization.colorization_fill(gray, values, known)
    fast = colorization.colorization_fill(gray, values, known, tolerance=1e-3)
    monkeypatch.setattr(stencil_solver, "compiled_solver", lambda: None)
    lapack = colorization.colorization_fill(gray, values, known, tolerance=1e-3)
    for solved in (fast, lapack):
        np.testing.assert_allclose(solved, exact, rtol=0, atol=1e-6 * values.max())


def test_without_refinement_steps_the_float64_lu_solves(monkeypatch):
    """A refinement that does not converge hands over to LAPACK's float64 LU."""
    rng = np.random.default_rng(4)
    gray = rng.random((9, 14))
    known = rng.random(gray.shape) < 0.2
    known[0, 0] = True
    values = rng.uniform(1, 3, gray.shape)
    expected = colorization.colorization_fill(gray, values, known)
    monkeypatch.setattr(stencil_solver, "_REFINEMENT_STEPS", 0)
    calls = []
    original = stencil_solver.scipy.linalg.lapack.dgbsv
    monkeypatch.setattr(stencil_solver.scipy.linalg.lapack, "dgbsv",
                        lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs))
    np.testing.assert_allclose(colorization.colorization_fill(gray, values, known), expected,
                               rtol=1e-10, atol=1e-12)
    assert calls


def test_without_numba_the_lapack_path_solves(monkeypatch):
    real_find_spec = importlib.util.find_spec
    stencil_solver.compiled_solver.cache_clear()
    try:
        with monkeypatch.context() as patch:
            patch.setattr(importlib.util, "find_spec",
                          lambda name, *a: None if name == "numba" else real_find_spec(name, *a))
            assert stencil_solver.compiled_solver() is None
            gray = np.random.default_rng(2).random((6, 9))
            known = np.zeros(gray.shape, bool)
            known[1, 1] = known[4, 7] = True
            filled = colorization.colorization_fill(gray, np.full(gray.shape, 2.0), known)
            np.testing.assert_allclose(filled, 2.0, rtol=1e-12)
    finally:
        stencil_solver.compiled_solver.cache_clear()
    assert stencil_solver.compiled_solver() is compiled


def test_an_unusable_numba_leaves_the_lapack_path(monkeypatch):
    """numba installed but its compiled module failing to import (e.g. built for another
    NumPy): the solves take LAPACK's LU instead of failing."""
    import sys

    stencil_solver.compiled_solver.cache_clear()
    try:
        with monkeypatch.context() as patch:
            patch.setitem(sys.modules, "deltar.inference.stencil_solver_compiled", None)
            assert stencil_solver.compiled_solver() is None
    finally:
        stencil_solver.compiled_solver.cache_clear()
    assert stencil_solver.compiled_solver() is compiled


@pytest.mark.parametrize("path", ["compiled", "lapack"])
def test_a_singular_system_is_refused_the_same_way_on_both_paths(path, monkeypatch):
    """A zero pivot gives non-finite factors in the compiled LU (no exception): the
    refinement refuses them and the float64 LU reports the system singular, as LAPACK's
    path does."""
    if path == "lapack":
        monkeypatch.setattr(stencil_solver, "compiled_solver", lambda: None)
    weights = np.zeros((8, 6, 9))
    diagonal = np.ones((6, 9))
    diagonal[2, 3] = 0.0  # a cell with no neighbour and no data
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        stencil_solver.solve_stencil_system(weights, diagonal, np.ones((6, 9)))
