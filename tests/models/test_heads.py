"""Bins-to-depth arithmetic against a direct NumPy computation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.models.heads import bins_to_depth, normalise_bin_widths


@pytest.mark.parametrize("grad", [True, False])
def test_depth_edges_and_uncertainty_match_numpy(rng, grad):
    widths_raw = rng.normal(size=(2, 8)).astype(np.float32)
    logits = rng.normal(scale=3.0, size=(2, 8, 3, 5)).astype(np.float32)
    widths = normalise_bin_widths(torch.from_numpy(widths_raw), "linear")

    # Independent reference: relu + 0.1, normalise, edges from 0.5 m, softmax expectation.
    w = np.maximum(widths_raw, 0) + 0.1
    w = w / w.sum(axis=1, keepdims=True) * (4.5 - 0.5)
    edges = 0.5 + np.concatenate([np.zeros((2, 1)), np.cumsum(w, axis=1)], axis=1)
    centres = 0.5 * (edges[:, :-1] + edges[:, 1:])
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    p = p / p.sum(axis=1, keepdims=True)
    depth = np.einsum("bnhw,bn->bhw", p, centres)
    std = np.sqrt(np.einsum("bnhw,bnhw->bhw", p, (centres[:, :, None, None] - depth[:, None]) ** 2))

    with torch.set_grad_enabled(grad):
        got_depth, got_edges, got_std = bins_to_depth(widths, torch.from_numpy(logits), 0.5, 4.5)
    np.testing.assert_allclose(got_edges.numpy(), edges, atol=1e-5)
    np.testing.assert_allclose(got_depth[:, 0].detach().numpy(), depth, atol=1e-5)
    np.testing.assert_allclose(got_std[:, 0].detach().numpy(), std, atol=1e-3)


def test_unknown_norm_raises():
    with pytest.raises(ValueError, match="bin norm"):
        normalise_bin_widths(torch.zeros(1, 4), "cubic")
