"""Bins-to-depth arithmetic against a direct NumPy computation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.models.heads.base import bins_to_depth
from deltar.models.heads.bins import normalise_bin_widths


@pytest.mark.parametrize("grad", [True, False])
def test_depth_edges_and_uncertainty_match_numpy(rng, grad):
    widths_raw = rng.normal(size=(2, 8)).astype(np.float32)
    logits = rng.normal(scale=3.0, size=(2, 8, 3, 5)).astype(np.float32)
    widths = normalise_bin_widths(torch.from_numpy(widths_raw))

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


@pytest.mark.parametrize("head", ["bins", "mvit", "direct", "zone_prior", "zone_select"])
def test_every_head_has_the_one_interface(head, network_inputs):
    from deltar.models import create_model
    from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs

    torch.manual_seed(0)
    model = create_model("deltar-lite", head=head, design_size=(64, 96)).eval()
    assert isinstance(model.head, DepthHead)
    _, hypotheses, rects, valid = network_inputs(batch=2)
    features = torch.randn(2, model.network_config.decoder.out_channels, 32, 48)
    zones = ZoneInputs(hypotheses, valid, rects, stride=2.0)
    with torch.no_grad():
        out = model.head.predict(features, zones)
    assert isinstance(out, HeadOutput)
    assert out.depth.shape == out.uncertainty.shape == (2, 1, 32, 48)
    assert out.bin_edges.shape[0] == 2 and out.bin_edges.ndim == 2
    assert torch.isfinite(out.depth).all() and (out.depth > 0).all()
    assert (out.uncertainty >= 0).all()


def test_network_output_is_the_heads_predict(network_inputs):
    # DeltarNet hands every head the same ZoneInputs; a head replaced by another
    # DepthHead is called the same way.
    from deltar.models import create_model
    from deltar.models.heads.base import DepthHead, HeadOutput

    class Constant(DepthHead):
        def predict(self, features, zones):
            self.seen = zones
            depth = torch.full_like(features[:, :1], 1.5)
            return HeadOutput(depth, zones.hypotheses.new_zeros(features.shape[0], 3),
                              torch.zeros_like(depth))

    model = create_model("deltar-lite", head="bins", zone_scale_norm=False,
                         design_size=(64, 96)).eval()
    model.head = Constant()
    image, hypotheses, rects, valid = network_inputs(batch=1)
    with torch.no_grad():
        out = model(image, hypotheses, rects, valid)
    assert torch.equal(out["depth"], torch.full_like(out["depth"], 1.5))
    assert model.head.seen.stride == 2.0 and model.head.seen.rects is rects
