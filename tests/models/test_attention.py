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


def test_feature_map_is_the_release_float32_elu_bit_for_bit():
    # The release computes elu(x) + 1 in float32, which is exactly 0 far below zero;
    # exp(x) is not (4e-8 at -17), and that alone moves depth by millimetres.
    x = torch.linspace(-200.0, 50.0, 250_001)
    ours = elu_feature_map(x)
    assert ours.dtype == torch.float32
    assert torch.equal(ours, F.elu(x) + 1.0)
    assert torch.all(ours[x < -20.0] == 0.0)


def test_attention_layer_uses_the_release_feature_map_for_very_negative_queries():
    from deltar.models.attention import LinearAttentionLayer

    torch.manual_seed(0)
    layer = LinearAttentionLayer(dim=8, num_heads=2).eval()
    with torch.no_grad():
        layer.query_proj.weight.mul_(80.0)  # queries down to about -100
    x, source = torch.randn(1, 6, 8), torch.randn(1, 5, 8)

    def reference(x, source):
        q = (F.elu(layer.query_proj(x)) + 1.0).reshape(1, 6, 2, 4).transpose(1, 2)
        k = (F.elu(layer.key_proj(source)) + 1.0).reshape(1, 5, 2, 4).transpose(1, 2)
        v = layer.value_proj(source).reshape(1, 5, 2, 4).transpose(1, 2)
        message = linear_attention(q, k, v).transpose(1, 2).reshape(1, 6, 8)
        message = layer.norm_message(layer.out_proj(message))
        return x + layer.norm_out(layer.ffn(torch.cat([x, message], dim=2)))

    with torch.no_grad():
        assert layer.query_proj(x).min() < -30.0
        torch.testing.assert_close(layer(x, source), reference(x, source), atol=1e-6, rtol=1e-6)
