"""The stencil solver's LAPACK path (without numba's compiled one) on grids of any shape."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.inference import colorization, stencil_solver
from tests.inference.grid_problems import dense_solution, edge_problem


@pytest.mark.parametrize("shape", [(1, 6), (2, 2), (2, 9), (9, 2), (3, 7), (14, 11)])
def test_lapack_path_is_the_dense_solve_on_narrow_grids(shape, monkeypatch):
    """On grids one or two cells wide two neighbours share a band diagonal (one of them
    off the grid): their entries add up instead of one replacing the other."""
    monkeypatch.setattr(stencil_solver, "compiled_solver", lambda: None)
    gray, known, values = edge_problem(np.random.default_rng(17), shape, 0.2)
    weights = colorization._affinity_weights(gray)
    exact = dense_solution(weights, 1.0 + known, known * values)
    solved = stencil_solver.solve_stencil_system(weights, 1.0 + known, known * values)
    np.testing.assert_allclose(solved, exact, rtol=1e-10, atol=1e-12)
