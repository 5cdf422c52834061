"""The zone-prior head: prior interpolation and an untrained head returning the prior."""

from __future__ import annotations

import math

import pytest
import torch

from deltar.models import create_model
from deltar.models.heads.footprints import NO_ZONE_PRIOR_DEPTH, footprint_pool, zone_prior_map
from deltar.models.heads.zone_prior import ZonePriorHead


def _grid_rects(grid: int, zone_px: int) -> torch.Tensor:
    rows, cols = torch.meshgrid(torch.arange(grid), torch.arange(grid), indexing="ij")
    y0, x0 = (rows * zone_px).reshape(-1), (cols * zone_px).reshape(-1)
    return torch.stack([y0, x0, y0 + zone_px, x0 + zone_px], dim=-1).float()[None]


def test_constant_zones_give_a_constant_prior():
    rects = _grid_rects(4, 16)
    means = torch.full((1, 16), 2.5)
    prior = zone_prior_map(means, torch.ones(1, 16, dtype=torch.bool), rects, (32, 32), 2.0)
    assert prior.shape == (1, 1, 32, 32)
    torch.testing.assert_close(prior, torch.full_like(prior, 2.5))


def test_prior_follows_each_zone_near_its_centre_and_extrapolates_outside():
    rects = _grid_rects(2, 32)  # 2x2 zones of 32 px over a 64x64 input
    means = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    valid = torch.ones(1, 4, dtype=torch.bool)
    prior = zone_prior_map(means, valid, rects, (64, 64), 1.0)[0, 0]
    # At a zone centre the own zone weighs e^2 (~7.4x) more than a neighbour one
    # zone width away: the prior is pulled most of the way toward the own mean.
    assert abs(prior[15, 15].item() - 1.0) < 0.5 and abs(prior[47, 47].item() - 4.0) < 0.6
    assert prior[15, 15] < prior[15, 47] < prior[47, 47]
    # Far right of the zones the right column dominates (no zero, no NaN): at row 15
    # only zones 1 (2 m, centre row 15.5) and 3 (4 m, centre row 47.5) keep weight,
    # Gaussian in the row distance with sigma = 16 px.
    far = zone_prior_map(means, valid, rects, (64, 400), 1.0)[0, 0]
    assert torch.isfinite(far).all()
    w1, w3 = math.exp(-0.5 * (0.5 / 16) ** 2), math.exp(-0.5 * (32.5 / 16) ** 2)
    expected = math.exp((w1 * math.log(2.0) + w3 * math.log(4.0)) / (w1 + w3))
    assert far[15, 399].item() == pytest.approx(expected, rel=1e-4)


def test_invalid_zones_are_ignored_and_no_valid_zone_gives_the_fallback():
    rects = _grid_rects(2, 32)
    means = torch.tensor([[1.0, 50.0, 50.0, 50.0], [1.0, 2.0, 3.0, 4.0]])
    valid = torch.tensor([[True, False, False, False], [False, False, False, False]])
    prior = zone_prior_map(means, valid, rects, (16, 16), 4.0)
    torch.testing.assert_close(prior[0], torch.ones_like(prior[0]))
    torch.testing.assert_close(prior[1], torch.full_like(prior[1], NO_ZONE_PRIOR_DEPTH))


def test_untrained_head_returns_the_prior_with_finite_uncertainty():
    head = ZonePriorHead(in_channels=8, n_bins=16, hidden_channels=8, max_ratio=3.0)
    prior = torch.rand(2, 1, 6, 7) * 3 + 0.5
    depth, edges, uncertainty = head(torch.randn(2, 8, 6, 7), prior)
    torch.testing.assert_close(depth, prior)
    assert edges.shape == (2, 17) and torch.all(edges[:, 1:] > edges[:, :-1])
    # A uniform distribution over log-ratios in [-ln 3, ln 3] has std ~ ln 3 / sqrt(3).
    expected = prior * math.log(3.0) / math.sqrt(3.0)
    torch.testing.assert_close(uncertainty, expected, rtol=0.02, atol=1e-4)


def test_network_with_zone_prior_head_trains_toward_the_target():
    torch.manual_seed(0)
    model = create_model("deltar-lite", head="zone_prior", design_size=(64, 64))
    rects = _grid_rects(4, 16).repeat(2, 1, 1)
    valid = torch.ones(2, 16, dtype=torch.bool)
    hypotheses = torch.full((2, 16, 16), 2.0)
    image = torch.randn(2, 3, 64, 64)
    target = torch.full((2, 1, 32, 32), 2.6)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(8):
        depth = model(image, hypotheses, rects, valid)["depth"]
        loss = (torch.log(depth) - torch.log(target)).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert losses[0] == pytest.approx(math.log(2.6 / 2.0), rel=1e-3)
    assert losses[-1] < 0.5 * losses[0]


def test_untrained_zone_select_head_is_the_prior_and_stays_within_the_readings():
    from deltar.models.heads.zone_select import ZoneSelectHead

    torch.manual_seed(0)
    head = ZoneSelectHead(in_channels=8, key_channels=4, n_bins=16)
    rects = _grid_rects(4, 8).repeat(2, 1, 1)
    means = torch.rand(2, 16) * 3 + 0.5
    valid = torch.rand(2, 16) > 0.2
    features = torch.randn(2, 8, 16, 16)
    depth, edges, spread = head(features, means, valid, rects, stride=2.0)
    torch.testing.assert_close(depth, zone_prior_map(means, valid, rects, (16, 16), 2.0),
                               rtol=1e-5, atol=1e-6)
    assert edges.shape == (2, 17) and (spread >= 0).all()
    # Any learned affinity keeps every pixel inside its frame's range of valid readings.
    with torch.no_grad():
        head.query.weight.normal_(0.0, 3.0)
    depth, _, _ = head(features, means, valid, rects, stride=2.0)
    for b in range(2):
        low, high = means[b][valid[b]].min(), means[b][valid[b]].max()
        assert depth[b].min() >= low - 1e-4 and depth[b].max() <= high + 1e-4
    none = torch.zeros_like(valid)
    fallback, _, _ = head(features, means, none, rects, stride=2.0)
    torch.testing.assert_close(fallback, torch.full_like(fallback, NO_ZONE_PRIOR_DEPTH))


def test_zone_select_learns_which_zone_a_pixel_belongs_to():
    # Two zones read 1 m and 3 m; the image says the left half belongs to the 3 m zone
    # (its colour): the head must learn to pick by appearance, not by distance.
    from deltar.models.heads.zone_select import ZoneSelectHead

    torch.manual_seed(0)
    head = ZoneSelectHead(in_channels=2, key_channels=4, n_bins=8)
    rects = torch.tensor([[[0.0, 0.0, 8.0, 8.0], [0.0, 8.0, 8.0, 16.0]]])
    means, valid = torch.tensor([[1.0, 3.0]]), torch.ones(1, 2, dtype=torch.bool)
    features = torch.zeros(1, 2, 8, 16)
    features[:, 0, :, :4] = 1.0  # left quarter looks like the right zone
    features[:, 1, :, 4:] = 1.0
    features[:, 0, :, 8:] = 1.0
    features[:, 1, :, 8:] = 0.0
    target = torch.full((1, 1, 8, 16), 1.0)
    target[..., :4] = 3.0
    target[..., 8:] = 3.0
    optimiser = torch.optim.Adam(head.parameters(), lr=0.05)
    for _ in range(150):
        depth, _, _ = head(features, means, valid, rects, stride=1.0)
        loss = (torch.log(depth) - torch.log(target)).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    depth, _, _ = head(features, means, valid, rects, stride=1.0)
    assert depth[..., :3].mean() > 2.5 and depth[..., 5:7].mean() < 1.5


def test_zone_select_matches_the_dense_footprint_formula_where_weights_underflow():
    # Zone features are pooled axis by axis with log-weights floored 40 below each
    # zone's peak (subnormal floats are many times slower); on a map large enough for
    # far zones' Gaussians to underflow, the head must still equal the dense formula:
    # footprint = normalised outer product of the two axes' Gaussians, in float64.
    from deltar.models.heads.footprints import zone_gaussians
    from deltar.models.heads.zone_select import ZoneSelectHead

    torch.manual_seed(0)
    head = ZoneSelectHead(in_channels=6, key_channels=4, n_bins=8)
    with torch.no_grad():
        head.query.weight.normal_(0.0, 1.0)
    rects = _grid_rects(8, 20)  # 8x8 zones of 20x20 px over a 160x160 input
    means = torch.rand(1, 64) * 3 + 0.5
    valid = torch.rand(1, 64) > 0.1
    features = torch.randn(1, 6, 80, 80)
    depth, _, _ = head(features, means, valid, rects, stride=2.0)

    f64 = features.double()
    log_wy, log_wx = zone_gaussians(rects.double(), valid, (80, 80), 2.0)
    log_footprint = log_wy[:, :, None, :] + log_wx[:, None, :, :]  # (1, h, w, Z)
    footprint = torch.exp(log_footprint - log_footprint.amax(dim=(1, 2), keepdim=True))
    footprint = footprint / footprint.sum(dim=(1, 2), keepdim=True)
    pooled = torch.einsum("bchw,bhwz->bzc", f64, footprint)
    keys = pooled @ head.key.weight.double().T + head.key.bias.double()
    queries = torch.einsum("bchw,dc->bhwd", f64, head.query.weight.double()[:, :, 0, 0])
    queries = queries + head.query.bias.double()
    logits = (log_wy[:, :, None, :] + log_wx[:, None, :, :]) + \
        torch.einsum("bhwd,bzd->bhwz", queries, keys) * head.scale
    weights = torch.softmax(logits, dim=-1)
    log_mean = torch.log(means.double()).masked_fill(~valid, 0.0)
    expected = torch.exp(torch.einsum("bhwz,bz->bhw", weights, log_mean))[:, None]
    torch.testing.assert_close(depth.double(), expected, rtol=1e-5, atol=1e-5)


def test_footprint_pool_is_the_weighted_mean_over_each_zone_footprint():
    generator = torch.Generator().manual_seed(4)
    features = torch.randn(2, 5, 6, 7, generator=generator)
    log_wy = torch.randn(2, 6, 3, generator=generator)
    log_wx = torch.randn(2, 7, 3, generator=generator)
    wy = torch.softmax(log_wy, dim=1)
    wx = torch.softmax(log_wx, dim=1)
    footprint = wy[:, :, None, :] * wx[:, None, :, :]  # (B, h, w, Z), sums to 1 per zone
    expected = torch.einsum("bchw,bhwz->bcz", features.double(), footprint.double())
    pooled = footprint_pool(features, log_wy, log_wx)
    torch.testing.assert_close(pooled.double(), expected, rtol=1e-5, atol=1e-6)
    # Channels-last input (the optimised encoder's layout) gives the same.
    torch.testing.assert_close(
        footprint_pool(features.contiguous(memory_format=torch.channels_last), log_wy, log_wx),
        pooled, rtol=1e-6, atol=1e-7)
