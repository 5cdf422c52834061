"""Subnormal floats flushed to zero around the colorization fill's LU."""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import pytest
import scipy.linalg.lapack

from deltar.inference import colorization, stencil_solver
from deltar.inference.denormals import flush_denormals, flush_supported

SUBNORMAL = np.float32(1e-39)


def _blocky_image(seed: int = 0) -> np.ndarray:
    """(60, 80) intensities: overlapping flat rectangles (sharp edges, as real rooms have)."""
    rng = np.random.default_rng(seed)
    image = np.zeros((60, 80))
    for _ in range(12):
        y, x = rng.integers(0, 60), rng.integers(0, 80)
        image[y:y + 15, x:x + 20] = rng.uniform()
    return image


def test_flush_reads_subnormals_as_zero_and_restores_the_mode():
    if not flush_supported():
        with flush_denormals():  # a no-op where the mode cannot be set
            assert np.array([SUBNORMAL]) * np.float32(1.0) == SUBNORMAL
        pytest.skip("flush-to-zero is not settable on this platform")
    value = np.array([SUBNORMAL])
    with flush_denormals():
        assert (value * np.float32(1.0))[0] == 0.0
    assert (value * np.float32(1.0))[0] == SUBNORMAL
    with pytest.raises(KeyError), flush_denormals():
        raise KeyError("inside")
    assert (value * np.float32(1.0))[0] == SUBNORMAL  # restored after an exception


def test_flush_is_per_thread():
    if not flush_supported():
        pytest.skip("flush-to-zero is not settable on this platform")
    seen = []
    inside, done = threading.Event(), threading.Event()

    def other():
        inside.wait()
        seen.append((np.array([SUBNORMAL]) * np.float32(1.0))[0])
        done.set()

    thread = threading.Thread(target=other)
    thread.start()
    with flush_denormals():
        inside.set()
        done.wait(10)
    thread.join()
    assert seen == [SUBNORMAL]


def test_fill_is_the_same_with_subnormals_flushed(monkeypatch):
    image = _blocky_image()
    weights = colorization._affinity_weights(image)
    offsets = [(dx, dy) for dy, dx in stencil_solver.NEIGHBOUR_OFFSETS]
    storage = stencil_solver._band_storage(weights.transpose(0, 2, 1), np.full((80, 60), 1.5),
                                         offsets, 61, np.float32, transposed=True)
    factors = scipy.linalg.lapack.sgbtrf(storage, 61, 61)[0]
    tiny = np.finfo(np.float32).tiny
    assert np.sum((factors != 0) & (np.abs(factors) < tiny)) > 100  # the case at stake
    known = np.zeros(image.shape, bool)
    known[5::10, 5::10] = True
    values = np.where(known, 1.0 + 3.0 * image, 0.0)
    # The float64 solution, and the blend's one refinement step (about 1e-7 of the
    # values' scale from it either way).
    for tolerance, atol in ((colorization.EXACT_TOLERANCE, 1e-9), (1e-3, 1e-6)):
        flushed = colorization.colorization_fill(image, values, known, tolerance=tolerance)
        with monkeypatch.context() as patch:
            patch.setattr(stencil_solver, "flush_denormals", contextlib.nullcontext)
            exact = colorization.colorization_fill(image, values, known, tolerance=tolerance)
        np.testing.assert_allclose(flushed, exact, rtol=0, atol=atol)
