"""Direct solver of the colorization fill's grid systems (3 x 3 stencils).

:func:`solve_stencil_system` solves ``diagonal_p x_p - sum_k weights[k, p] x_(p + offset_k)
= rhs_p`` on an (h, w) grid, the system :mod:`deltar.inference.colorization` builds from
an image's affinities: a float32 banded LU (LAPACK's, or the compiled one of
:mod:`deltar.inference.stencil_solver_compiled` when numba is installed) refined with
float64 residuals to the accuracy asked for, the float64 LU where that fails, SciPy's
sparse LU where the band would not fit in memory.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
from collections.abc import Callable
from types import ModuleType

import numpy as np
import scipy.linalg
import scipy.linalg.blas
import scipy.linalg.lapack
import scipy.sparse
import scipy.sparse.linalg

from deltar.inference.denormals import flush_denormals

#: The 8 neighbours (dy, dx) of a cell in the colorization system, in a fixed order.
NEIGHBOUR_OFFSETS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                          if (dy, dx) != (0, 0))

#: Default relative accuracy of :func:`solve_stencil_system` (and so of
#: :func:`~deltar.inference.colorization.colorization_fill`): float64's, for the classical
#: ``colorization`` baseline.
EXACT_TOLERANCE = 1e-10

#: Largest banded-matrix buffer (entries) the grid solver builds (about 32 MB in float64).
_MAX_BANDED_ENTRIES = 4_000_000
#: Iterative refinement of the single-precision LU: steps at most (each step shrinks the
#: error by about 1e-4 or more, so the error left is far below float64's 1e-12 needs).
_REFINEMENT_STEPS = 6


def solve_stencil_system(weights: np.ndarray, diagonal: np.ndarray, rhs: np.ndarray,
                         tolerance: float = EXACT_TOLERANCE) -> np.ndarray:
    """Solve ``diagonal_p x_p - sum_k weights[k, p] x_(p + offset_k) = rhs_p`` on a grid.

    Args:
        weights: (8, h, w) neighbour weights (``NEIGHBOUR_OFFSETS`` order; 0 outside).
        diagonal: (h, w) diagonal of the system.
        rhs: (h, w) right-hand side.
        tolerance: relative size of the refinement's last correction
            (:func:`~deltar.inference.colorization.colorization_fill`).

    Returns:
        (h, w) float64 solution.

    Numbered along the shorter side the matrix is banded (half-bandwidth min(h, w) + 1).
    The banded LU (LAPACK ``gbtrf`` of the transposed system, which needs no row swaps)
    runs in float32, which halves
    its memory traffic and doubles its SIMD width against float64, and iterative
    refinement with float64 residuals brings the solution to the accuracy asked for
    (float64's: two or three steps; a system too ill-conditioned for that is solved in
    float64 instead). LAPACK releases the GIL while it factors, so the fill can run
    beside the network in another thread. With numba installed the LU, its solves and
    the refinement run compiled instead (:func:`compiled_solver`), without row swaps on
    the system itself, about three times faster. A large grid, whose band would not fit
    in memory, takes SciPy's sparse LU.
    """
    height, width = diagonal.shape
    if height < width:  # number along the columns: the grid transposed, row-major
        offsets = [(dx, dy) for dy, dx in NEIGHBOUR_OFFSETS]
        solution = _solve_rows_banded(weights.transpose(0, 2, 1), diagonal.T, rhs.T, offsets,
                                      tolerance)
        return solution.T
    return _solve_rows_banded(weights, diagonal, rhs, list(NEIGHBOUR_OFFSETS), tolerance)


def _stencil_product(weights: np.ndarray, diagonal: np.ndarray, values: np.ndarray,
                     offsets: list[tuple[int, int]]) -> np.ndarray:
    """(h, w) ``diagonal * values - sum_k weights[k] * values shifted by offsets[k]``."""
    height, width = values.shape
    padded = np.pad(values, 1)
    product = diagonal * values
    for k, (dy, dx) in enumerate(offsets):
        product -= weights[k] * padded[1 + dy:1 + dy + height, 1 + dx:1 + dx + width]
    return product


def _band_storage(weights: np.ndarray, diagonal: np.ndarray, offsets: list[tuple[int, int]],
                  band: int, dtype: type, transposed: bool = False) -> np.ndarray:
    """LAPACK ``gbtrf`` storage (3 band + 1, n) of the stencil system (or of its transpose),
    unknowns row-major."""
    height, width = diagonal.shape
    size = height * width
    storage = np.zeros((3 * band + 1, size), dtype=dtype)
    storage[2 * band] = diagonal.reshape(-1)
    for k, (dy, dx) in enumerate(offsets):
        # Entry (i, j = i + shift) sits at [2 band + i - j, j]; in the transpose it is
        # entry (j, i), at [2 band + shift, i].
        shift = dy * width + dx
        rows = slice(max(0, -shift), min(size, size - shift))
        # Accumulated: on grids 1 or 2 cells wide two neighbours share a shift (one of
        # them off the grid, with weight 0).
        if transposed:
            storage[2 * band + shift, rows] -= weights[k].reshape(-1)[rows]
        else:
            storage[2 * band - shift, rows.start + shift:rows.stop + shift] -= \
                weights[k].reshape(-1)[rows]
    return storage


def _solve_rows_banded(weights: np.ndarray, diagonal: np.ndarray, rhs: np.ndarray,
                       offsets: list[tuple[int, int]], tolerance: float) -> np.ndarray:
    """:func:`solve_stencil_system` with the unknowns numbered row-major (width <= height)."""
    height, width = diagonal.shape
    size = height * width
    band = width + 1
    if (3 * band + 1) * size > _MAX_BANDED_ENTRIES:
        system = sparse_system(weights, diagonal, offsets)
        return scipy.sparse.linalg.spsolve(system, rhs.reshape(-1),
                                           permc_spec="MMD_AT_PLUS_A").reshape(height, width)
    compiled = compiled_solver()
    solution = _solve_lapack(weights, diagonal, rhs, offsets, tolerance) if compiled is None \
        else _solve_compiled(compiled, weights, diagonal, rhs, offsets, tolerance)
    if solution is not None:
        return solution
    # Too ill-conditioned for single precision: the float64 LU.
    storage = _band_storage(weights, diagonal, offsets, band, np.float64)
    solution, info = scipy.linalg.lapack.dgbsv(band, band, storage, rhs.reshape(-1),
                                               overwrite_ab=True)[2:]
    if info != 0:
        raise np.linalg.LinAlgError(f"colorization system is singular (LAPACK info {info})")
    return solution.reshape(height, width)


@functools.cache
def compiled_solver() -> ModuleType | None:
    """:mod:`deltar.inference.stencil_solver_compiled` when numba is installed (the ``fast``
    extra), else None: the grid solves then take LAPACK's banded LU."""
    if importlib.util.find_spec("numba") is None:
        return None
    try:
        return importlib.import_module("deltar.inference.stencil_solver_compiled")
    except ImportError:  # installed but unusable (e.g. built for another NumPy)
        return None


def _solve_compiled(compiled: ModuleType, weights: np.ndarray, diagonal: np.ndarray,
                    rhs: np.ndarray, offsets: list[tuple[int, int]], tolerance: float
                    ) -> np.ndarray | None:
    """:func:`_solve_rows_banded`'s float32 LU and refinement in compiled code
    (:mod:`deltar.inference.stencil_solver_compiled`); None when the refinement does not
    converge."""
    height, width = diagonal.shape
    band = width + 1
    shifts = np.array([dy * width + dx for dy, dx in offsets], dtype=np.int64)
    flat_weights = np.ascontiguousarray(weights.reshape(len(offsets), -1), dtype=np.float64)
    flat_diagonal = np.ascontiguousarray(diagonal.reshape(-1), dtype=np.float64)
    flat_rhs = np.ascontiguousarray(rhs.reshape(-1), dtype=np.float64)
    factors = compiled.band_rows(flat_weights, flat_diagonal, shifts, band,
                                 compiled.band_width(band))
    with flush_denormals():  # as for LAPACK's LU (deltar.inference.denormals)
        compiled.factor(factors, band)
        solution, converged = compiled.solve_refined(factors, band, flat_weights,
                                                     flat_diagonal, shifts, flat_rhs,
                                                     tolerance, _REFINEMENT_STEPS)
    return solution.reshape(height, width) if converged else None


def _solve_lapack(weights: np.ndarray, diagonal: np.ndarray, rhs: np.ndarray,
                  offsets: list[tuple[int, int]], tolerance: float) -> np.ndarray | None:
    """:func:`_solve_rows_banded`'s float32 LU (LAPACK) and refinement; None when the
    factorisation fails or the refinement does not converge."""
    height, width = diagonal.shape
    band = width + 1
    # The transpose is factored: each row of the system has a diagonal at least the sum
    # of its other entries' sizes, so each column of the transpose does, and partial
    # pivoting swaps no rows there. Without swaps U keeps the band's width instead of
    # growing towards twice it (the system itself took a few hundred swaps and 1.3-1.4x
    # the time on image grids); the solves use the factors transposed.
    storage = _band_storage(weights, diagonal, offsets, band, np.float32, transposed=True)
    # Subnormal fill-in read as zero (deltar.inference.denormals): the factors differ
    # by less than 1.2e-38 an entry, which the refinement corrects, and x86 cores slow
    # down on subnormals.
    with flush_denormals():
        factors, pivots, info = scipy.linalg.lapack.sgbtrf(storage, band, band,
                                                           overwrite_ab=True)
    if info == 0:
        solve = _factor_solver(factors, pivots, band, (height, width))
        solution = solve(rhs).astype(np.float64)
        for _ in range(_REFINEMENT_STEPS):
            correction = solve(rhs - _stencil_product(weights, diagonal, solution, offsets))
            solution += correction
            if np.abs(correction).max() <= tolerance * np.abs(solution).max():
                return solution
    return None


def _factor_solver(factors: np.ndarray, pivots: np.ndarray, band: int,
                   shape: tuple[int, int]) -> Callable[[np.ndarray], np.ndarray]:
    """``values -> x`` with ``system @ x = values`` (float32, ``shape``) from ``sgbtrf``'s
    factors of the system's transpose.

    Without row swaps the transpose is ``L U`` with both factors ``band`` wide, and the
    system ``U^T L^T``: two triangular band solves (BLAS ``tbsv``) on those widths. LAPACK's
    ``gbtrs`` instead reads U as twice as wide (room for swaps' fill-in) and applies L a
    column at a time, which took twice as long on the fill's 42 x 57 grid. With a swap,
    ``gbtrs`` solves. SciPy's wrappers of both hold Python's GIL while they solve (its
    ``gbtrf`` releases it), so the shorter solves also hold it for less.
    """
    if not np.array_equal(pivots, np.arange(pivots.size)):  # scipy's pivots count from 0
        def solve_swapped(values: np.ndarray) -> np.ndarray:
            with flush_denormals():
                return scipy.linalg.lapack.sgbtrs(factors, band, band,
                                                  values.reshape(-1).astype(np.float32),
                                                  pivots, trans=1)[0].reshape(shape)
        return solve_swapped
    # gbtrf's storage (3 band + 1 rows): U's diagonal in row 2 band with its band
    # superdiagonals above it, L's multipliers below; tbsv reads each as (band + 1, n).
    upper = np.asfortranarray(factors[band:2 * band + 1])
    lower = np.asfortranarray(factors[2 * band:])

    def solve(values: np.ndarray) -> np.ndarray:
        with flush_denormals():
            partial = scipy.linalg.blas.stbsv(band, upper, values.reshape(-1).astype(np.float32),
                                              trans=1)
            return scipy.linalg.blas.stbsv(band, lower, partial, lower=1, trans=1, diag=1,
                                           overwrite_x=1).reshape(shape)
    return solve


def sparse_system(weights: np.ndarray, diagonal: np.ndarray,
                   offsets: list[tuple[int, int]]) -> scipy.sparse.csc_matrix:
    """The stencil system as a sparse CSC matrix over the row-major unknowns."""
    height, width = diagonal.shape
    index = np.arange(height * width).reshape(height, width)
    padded_index = np.pad(index, 1, mode="constant", constant_values=-1)
    neighbour_index = np.stack([padded_index[1 + dy:1 + dy + height, 1 + dx:1 + dx + width]
                                for dy, dx in offsets])
    inside = neighbour_index >= 0
    rows = np.broadcast_to(index[None], weights.shape)[inside]
    size = height * width
    affinity = scipy.sparse.csr_matrix((weights[inside], (rows, neighbour_index[inside])),
                                       shape=(size, size))
    return (scipy.sparse.diags(diagonal.reshape(-1)) - affinity).tocsc()
