"""The zone-prior head: prior interpolation and an untrained head returning the prior."""

from __future__ import annotations

import math

import pytest
import torch

from deltar.models import create_model
from deltar.models.zone_prior import NO_ZONE_PRIOR_DEPTH, ZonePriorHead, zone_prior_map


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
