"""Fixtures for the model tests: small synthetic zone layouts and network inputs."""

from __future__ import annotations

import pytest
import torch


def grid_rects(height: float, width: float, n: int, offset=(0.0, 0.0), span=None) -> torch.Tensor:
    """(n * n, 4) row-major (y0, x0, y1, x1) rectangles tiling ``span`` (default: the image)."""
    span_h, span_w = span if span is not None else (height, width)
    ys = torch.linspace(0, span_h, n + 1) + offset[0]
    xs = torch.linspace(0, span_w, n + 1) + offset[1]
    return torch.stack(
        [torch.stack([ys[i], xs[j], ys[i + 1], xs[j + 1]]) for i in range(n) for j in range(n)]
    )


def make_inputs(batch=2, height=64, width=96, n=8, k=16, seed=0):
    """Random normalised image, hypotheses (metres), per-sample zone layouts, validity."""
    generator = torch.Generator().manual_seed(seed)
    image = torch.randn(batch, 3, height, width, generator=generator)
    hypotheses = torch.rand(batch, n * n, k, generator=generator) * 3.0 + 0.2
    layouts = [
        grid_rects(height, width, n, offset=(-5.0 + 3 * b, -7.0 - 11 * b), span=(height, width - 8))
        for b in range(batch)
    ]
    rects = torch.stack(layouts)
    valid = torch.rand(batch, n * n, generator=generator) > 0.3
    hypotheses = hypotheses * valid[..., None]
    return image, hypotheses, rects, valid


@pytest.fixture
def rects_on_grid():
    """The :func:`grid_rects` function."""
    return grid_rects


@pytest.fixture
def network_inputs():
    """The :func:`make_inputs` function."""
    return make_inputs


@pytest.fixture(autouse=True)
def single_thread():
    """Run model tests on one torch thread (restored afterwards).

    On a busy machine, two OpenMP threads waiting on each other make these small
    forwards many times slower; the parity test asks for two threads itself.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
