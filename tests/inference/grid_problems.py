"""Small colorization problems on a grid for the fill's solver tests."""

from __future__ import annotations

import numpy as np

from deltar.inference import stencil_solver


def edge_problem(rng: np.random.Generator, shape: tuple[int, int], known_fraction: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gray, known, values): (h, w) intensities with a vertical edge (the weights across
    it are small), a random mask of known cells (the first always known) and values
    0.5-4 m."""
    gray = rng.random(shape)
    gray[:, shape[1] // 2:] += 0.8
    known = rng.random(shape) < known_fraction
    known[0, 0] = True
    return gray, known, rng.uniform(0.5, 4.0, shape)


def dense_solution(weights: np.ndarray, diagonal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The stencil system's (h, w) solution by a dense float64 solve (the reference)."""
    system = stencil_solver.sparse_system(weights, diagonal,
                                          list(stencil_solver.NEIGHBOUR_OFFSETS))
    return np.linalg.solve(system.toarray(), rhs.reshape(-1)).reshape(diagonal.shape)
