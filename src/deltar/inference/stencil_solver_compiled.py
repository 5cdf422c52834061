"""Compiled (numba) banded solver for the colorization fill, when numba is installed.

:mod:`deltar.inference.stencil_solver` solves its grid systems by a float32 LU of the band
and iterative refinement with float64 residuals. LAPACK's banded LU (``sgbtrf``) spends
most of its time on the bookkeeping of its small blocks at the fill's half-bandwidth
(43 on the blend's 42 x 57 grid); the kernels here factor the same band without row
swaps, four pivots at a time, with each target row's update one vectorised pass, and
run the solves and the refinement's residuals in the same compiled code, all without
Python's GIL. Same system, same refinement and stopping rule, so the solution agrees
with the LAPACK path to the tolerance asked for. They need ``numba`` (the ``fast``
extra); without it the LAPACK path runs, and this module is imported only when numba is
(:func:`deltar.inference.stencil_solver.compiled_solver`).

No row swaps are needed: each row of the system has a diagonal at least the sum of its
other entries' sizes, a property elimination keeps, so the pivots stay at least the
rows' other entries and the factors' growth is bounded by 2.

Band storage (:func:`band_rows`): row ``i`` of the matrix is row ``i`` of a
(n, ``band_width(band)``) float32 array, entry (i, j) at column ``j - i + band + PAD``
for ``|j - i| <= band``; the ``PAD`` columns on the left and the ones past the band on
the right stay zero, so the blocked update reads whole 8-wide lanes without tests.
"""

from __future__ import annotations

import numba
import numpy as np

#: Zero columns left of the band: a row below the band's reach of a block's first pivot
#: reads its (zero) multiplier there.
PAD = 4
#: Pivots eliminated together.
_BLOCK = 4
#: Lanes the target-row update is rounded up to.
_LANES = 8


def update_length(band: int) -> int:
    """Entries of a target row one block of pivots updates, rounded up to whole lanes."""
    return -(-band // _LANES) * _LANES


def band_width(band: int) -> int:
    """Columns of the band storage for half-bandwidth ``band``."""
    return band + PAD + 1 + update_length(band)


#: Compiled without the GIL, cached on disk (next to this file, or in numba's user-wide
#: cache where that is read-only). Fast-math reassociation and contraction (the vectorised
#: updates and dot products) but not its no-NaN / no-infinity assumptions, and NumPy's
#: division (a zero pivot gives infinities, not an exception): a degenerate system shows
#: as a non-finite solution, which is refused so the float64 LU takes over.
_jit = numba.njit(nogil=True, fastmath={"reassoc", "contract", "arcp", "nsz"},
                  error_model="numpy", boundscheck=False, cache=True)


@_jit
def band_rows(weights, diagonal, shifts, band, width):
    """(n, width) float32 band storage (module docstring) of the stencil system
    ``diagonal_i x_i - sum_k weights[k, i] x_(i + shifts[k])``.

    Args:
        weights: (K, n) float64 neighbour weights over the row-major unknowns; 0 where
            the neighbour is off the grid.
        diagonal: (n,) float64.
        shifts: (K,) int64 flat index offset of each neighbour, at most ``band``.
        band: half-bandwidth; width: :func:`band_width` of it.
    """
    n = diagonal.shape[0]
    base = band + PAD
    out = np.zeros((n, width), np.float32)
    for i in range(n):
        out[i, base] = diagonal[i]
        for k in range(shifts.shape[0]):
            j = i + shifts[k]
            if 0 <= j < n:  # on grids 1 or 2 wide two neighbours share a shift
                out[i, base + shifts[k]] -= weights[k, i]
    return out


@_jit
def _block_multipliers(row, o, pivots):
    """A target row's multipliers of one block's four pivots, stored in place at
    ``row[o:o + 4]`` (the row's entries in the block's columns, eliminated in turn).
    ``pivots``: the four pivots' reciprocals, then U's entries (0, 1), (0, 2), (0, 3),
    (1, 2), (1, 3), (2, 3) within the block."""
    l0 = row[o] * pivots[0]
    l1 = (row[o + 1] - l0 * pivots[4]) * pivots[1]
    l2 = (row[o + 2] - l0 * pivots[5] - l1 * pivots[7]) * pivots[2]
    l3 = (row[o + 3] - l0 * pivots[6] - l1 * pivots[8] - l2 * pivots[9]) * pivots[3]
    row[o] = l0
    row[o + 1] = l1
    row[o + 2] = l2
    row[o + 3] = l3
    return l0, l1, l2, l3


@_jit
def factor(a, band):
    """LU of :func:`band_rows`' storage ``a`` in place, without row swaps: L's multipliers
    below the diagonal (unit diagonal implied), U on and above it."""
    n = a.shape[0]
    base = band + PAD
    length = a.shape[1] - (band + PAD + 1)  # update_length(band): band_width's rest
    rows = np.zeros((_BLOCK, length), np.float32)
    pivots = np.zeros(10, np.float32)
    k = 0
    while k + _BLOCK <= n:
        # The block's own rows, eliminated among themselves first.
        for r in range(k + 1, k + _BLOCK):
            row = a[r]
            for p in range(k, r):
                o = p - r + base
                multiplier = row[o] / a[p, base]
                row[o] = multiplier
                target = row[o + 1:o + 1 + band]
                pivot = a[p, base + 1:base + 1 + band]
                for j in range(band):
                    target[j] -= multiplier * pivot[j]
        # The pivot rows' parts right of the block, aligned on one column range and
        # zero past each row's band.
        for s in range(_BLOCK):
            count = max(0, min(band + s - _BLOCK + 1, length))
            source = a[k + s, base + _BLOCK - s:base + _BLOCK - s + count]
            kept = rows[s]
            for j in range(count):
                kept[j] = source[j]
            for j in range(count, length):
                kept[j] = np.float32(0.0)
        u0, u1, u2, u3 = rows[0], rows[1], rows[2], rows[3]
        pivots[0] = np.float32(1.0) / a[k, base]
        pivots[1] = np.float32(1.0) / a[k + 1, base]
        pivots[2] = np.float32(1.0) / a[k + 2, base]
        pivots[3] = np.float32(1.0) / a[k + 3, base]
        pivots[4], pivots[5], pivots[6] = a[k, base + 1], a[k, base + 2], a[k, base + 3]
        pivots[7], pivots[8], pivots[9] = a[k + 1, base + 1], a[k + 1, base + 2], \
            a[k + 2, base + 1]
        i = k + _BLOCK
        last = min(k + _BLOCK - 1 + band, n - 1)
        while i <= last:
            row = a[i]
            o = k - i + base
            l0, l1, l2, l3 = _block_multipliers(row, o, pivots)
            target = row[o + _BLOCK:o + _BLOCK + length]
            if i < last:  # two rows a pass: each lane of the pivot rows loaded once for both
                below = a[i + 1]
                m0, m1, m2, m3 = _block_multipliers(below, o - 1, pivots)
                target_below = below[o - 1 + _BLOCK:o - 1 + _BLOCK + length]
                for j in range(length):
                    x0, x1, x2, x3 = u0[j], u1[j], u2[j], u3[j]
                    target[j] -= l0 * x0 + l1 * x1 + l2 * x2 + l3 * x3
                    target_below[j] -= m0 * x0 + m1 * x1 + m2 * x2 + m3 * x3
                i += 2
            else:
                for j in range(length):
                    target[j] -= l0 * u0[j] + l1 * u1[j] + l2 * u2[j] + l3 * u3[j]
                i += 1
        k += _BLOCK
    for p in range(k, n):  # the last pivots, one at a time
        for r in range(p + 1, min(p + band, n - 1) + 1):
            o = p - r + base
            multiplier = a[r, o] / a[p, base]
            a[r, o] = multiplier
            for j in range(1, band + 1):
                a[r, o + j] -= multiplier * a[p, base + j]

@_jit
def solve(a, band, values):
    """``values`` ((n,) float32) replaced by x with ``L U x = values`` (:func:`factor`'s
    ``a``)."""
    n = a.shape[0]
    base = band + PAD
    for i in range(n):
        m = min(i, band)
        coefficients = a[i, base - m:base]
        known = values[i - m:i]
        total = np.float32(0.0)
        for j in range(m):
            total += coefficients[j] * known[j]
        values[i] -= total
    for i in range(n - 1, -1, -1):
        m = min(n - 1 - i, band)
        coefficients = a[i, base + 1:base + 1 + m]
        known = values[i + 1:i + 1 + m]
        total = np.float32(0.0)
        for j in range(m):
            total += coefficients[j] * known[j]
        values[i] = (values[i] - total) / a[i, base]

@_jit
def residual(weights, diagonal, shifts, solution, rhs, out):
    """``out`` ((n,) float64) = ``rhs - system @ solution`` for :func:`band_rows`'
    system. A neighbour off the grid has weight 0, whatever cell its flat index reaches."""
    n = diagonal.shape[0]
    for i in range(n):
        total = rhs[i] - diagonal[i] * solution[i]
        for k in range(shifts.shape[0]):
            j = i + shifts[k]
            if 0 <= j < n:
                total += weights[k, i] * solution[j]
        out[i] = total

@_jit
def solve_refined(a, band, weights, diagonal, shifts, rhs, tolerance, steps):
    """Solve the system with :func:`factor`'s float32 factors ``a`` and at most ``steps``
    refinement steps on float64 residuals (arguments as :func:`band_rows`'; ``rhs``
    (n,) float64).

    Returns:
        ((n,) float64 solution, converged): converged once a correction is at most
        ``tolerance`` times the solution's largest value (the LAPACK path's rule); never
        with a non-finite value.
    """
    n = rhs.shape[0]
    work = rhs.astype(np.float32)
    solve(a, band, work)
    solution = work.astype(np.float64)
    remaining = np.empty(n)
    for _ in range(steps):
        residual(weights, diagonal, shifts, solution, rhs, remaining)
        for i in range(n):
            work[i] = remaining[i]
        solve(a, band, work)
        largest_correction = 0.0
        largest_value = 0.0
        for i in range(n):
            solution[i] += work[i]
            largest_correction = max(largest_correction, abs(np.float64(work[i])))
            largest_value = max(largest_value, abs(solution[i]))
        if not _all_finite(solution):
            return solution, False
        if largest_correction <= tolerance * largest_value:
            return solution, True
    return solution, False


@_jit
def _all_finite(values):
    """Whether no float64 value is NaN or infinite, read from the exponent bits (fast-math
    reassociation lets the compiler assume ``isfinite``)."""
    bits = values.view(np.int64)
    for i in range(bits.shape[0]):
        if (bits[i] >> 52) & 0x7FF == 0x7FF:
            return False
    return True

