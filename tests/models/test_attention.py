"""Linear attention pieces against direct formulas."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from deltar.models.attention import elu_feature_map, linear_attention


def test_feature_map_equals_elu_plus_one_with_finite_gradients():
    x = torch.cat([torch.linspace(-50, 50, 1001), torch.tensor([500.0, -500.0])])
    x.requires_grad_(True)
    y = elu_feature_map(x)
    y.sum().backward()
    reference = x.detach().clone().requires_grad_(True)
    (F.elu(reference) + 1).sum().backward()
    torch.testing.assert_close(y, F.elu(reference) + 1)
    torch.testing.assert_close(x.grad, reference.grad)


def test_linear_attention_matches_explicit_kernel_attention():
    generator = torch.Generator().manual_seed(0)
    q = elu_feature_map(torch.randn(2, 4, 5, 3, generator=generator))
    k = elu_feature_map(torch.randn(2, 4, 7, 3, generator=generator))
    v = torch.randn(2, 4, 7, 6, generator=generator)
    mask = torch.rand(2, 7, generator=generator) > 0.4
    # Explicit form: weights q_l . k_s over the unmasked keys, normalised per query.
    weights = torch.einsum("nhld,nhsd->nhls", q, k) * mask[:, None, None, :]
    expected = weights @ v / (weights.sum(-1, keepdim=True) + 1e-6)
    torch.testing.assert_close(linear_attention(q, k, v, mask), expected, atol=1e-5, rtol=1e-4)
