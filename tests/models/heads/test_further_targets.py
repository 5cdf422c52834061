"""Further targets per zone: their shares and the ones a frame's choice weighs."""

from __future__ import annotations

import math

import torch

from deltar.models.heads.further_targets import (
    SECONDARY_HYPOTHESES,
    further_targets,
    target_shares,
)


def test_target_shares_normalise_and_default_to_equal():
    targets = torch.tensor([[[[1.0, 3.0], [2.0, 1.0], [0.0, 0.0]],
                             [[1.5, 0.0], [2.5, 0.0], [3.5, 0.0]],
                             [[0.0, 0.0], [2.0, 1.0], [0.0, 0.0]]]])
    valid = torch.tensor([[True, True, False]])
    share, present = target_shares(targets, valid)
    torch.testing.assert_close(share[0, 0], torch.tensor([0.75, 0.25, 0.0]))
    torch.testing.assert_close(share[0, 1], torch.full((3,), 1 / 3))
    assert present.tolist() == [[[True, False], [True, True], [False, False]]]


def test_the_largest_further_targets_are_kept_with_their_zones_and_depths():
    torch.manual_seed(0)
    zones = 40
    rows, cols = torch.meshgrid(torch.arange(5), torch.arange(8), indexing="ij")
    y0, x0 = (rows * 4).reshape(-1).float(), (cols * 4).reshape(-1).float()
    rects = torch.stack([y0, x0, y0 + 4, x0 + 4], dim=-1)[None]
    means = torch.rand(1, zones) + 1.0
    valid = torch.ones(1, zones, dtype=torch.bool)
    targets = torch.zeros(1, zones, 2, 2)
    targets[..., 0, 0] = means
    targets[0, :30, 1, 0] = means[0, :30] + 1.0  # the last ten zones report one target
    share = torch.linspace(0.05, 0.45, 30)
    targets[0, :30, 0, 1], targets[0, :30, 1, 1] = 1 - share, share
    pooled = torch.nn.functional.normalize(torch.randn(1, 6, zones), dim=1)
    centre = torch.log(means).mean(1, keepdim=True)
    further = further_targets(targets, valid, pooled, means, rects, centre)
    assert further.descriptors.shape == (1, 6, SECONDARY_HYPOTHESES)
    kept = sorted(further.zone[0].tolist())
    assert kept == list(range(30 - SECONDARY_HYPOTHESES, 30))  # the largest shares
    assert bool(further.present.all())
    torch.testing.assert_close(further.log_depth[0],
                               torch.log(means[0, further.zone[0]] + 1.0) - centre[0])
    torch.testing.assert_close(further.log_share[0], torch.log(share[further.zone[0]]))
    # The primary's share counts only where its zone keeps a further target.
    primary = further.primary_log_share[0]
    assert torch.all(primary[30:] == 0) and torch.all(primary[:30 - SECONDARY_HYPOTHESES] == 0)
    zone = 29
    assert math.isclose(float(primary[zone]), math.log(1 - float(share[zone])), rel_tol=1e-5)


def test_among_equal_shares_the_first_zones_are_kept_as_the_onnx_export_keeps_them():
    """More further targets than the choice weighs, all of one share (a simulated edge
    along a column of zones, equal signals): the kept ones are the first in zone order,
    as onnxruntime's TopK breaks ties (lower index first), so both backends weigh the
    same targets; torch.topk alone keeps an arbitrary subset of the tied ones."""
    zones = 64
    rows, cols = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    y0, x0 = (rows * 4).reshape(-1).float(), (cols * 4).reshape(-1).float()
    rects = torch.stack([y0, x0, y0 + 4, x0 + 4], dim=-1)[None]
    means = torch.full((1, zones), 1.0)
    valid = torch.ones(1, zones, dtype=torch.bool)
    targets = torch.zeros(1, zones, 2, 2)
    targets[..., 0, 0], targets[..., 0, 1] = means, 0.3
    targets[..., 1, 0], targets[..., 1, 1] = 1.5, 0.7
    pooled = torch.nn.functional.normalize(torch.randn(1, 6, zones), dim=1)
    centre = torch.zeros(1, 1)
    further = further_targets(targets, valid, pooled, means, rects, centre)
    assert further.zone[0].tolist() == list(range(SECONDARY_HYPOTHESES))
