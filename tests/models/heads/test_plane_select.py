"""The plane-select head (several targets per zone; the rest in tests/models/test_affinity.py)."""

from __future__ import annotations

import pytest
import torch

from deltar.models.heads.plane_select import PlanarSelectHead


def _edge_scene(second_share: float):
    """Two 16 px zones: a wall at 1 m (left) and one at 3 m (right). The left zone's
    last 6 columns look like the right zone: they are the 3 m surface, and the left
    zone reports it as a second target."""
    rects = torch.tensor([[[0.0, 0.0, 16.0, 16.0], [0.0, 16.0, 16.0, 32.0]]])
    means, valid = torch.tensor([[1.0, 3.0]]), torch.ones(1, 2, dtype=torch.bool)
    descriptors = torch.zeros(1, 2, 16, 32)
    descriptors[:, 0, :, :10] = 1.0
    descriptors[:, 1, :, 10:] = 1.0
    targets = torch.zeros(1, 2, 2, 2)
    targets[0, :, 0, 0] = means[0]
    targets[0, 0, 1, 0] = 2.9  # the far surface as the left zone sees it
    targets[0, :, 0, 1] = 1.0
    targets[0, 0, 0, 1], targets[0, 0, 1, 1] = 1 - second_share, second_share
    return descriptors, means, valid, rects, targets


def test_a_second_target_gives_the_pixels_that_look_like_it_its_depth():
    descriptors, means, valid, rects, targets = _edge_scene(0.4)
    # Spatial prior only (temperature 0 in the cosine) keeps the left zone at 1 m; the
    # affinity alone cannot reach 3 m from inside the left zone's footprint as well.
    head = PlanarSelectHead(temperature=20.0, planar=False)
    plain, _, plain_spread = head(descriptors, means, valid, rects, stride=1.0)
    with_targets, _, spread = head(descriptors, means, valid, rects, stride=1.0,
                                   zone_targets=targets)
    # The left zone's 3 m-looking columns (10-15) move to the second target's 2.9 m.
    assert (with_targets[..., 11:15] - 2.9).abs().max() < 0.15
    assert (plain[..., 11:15] - 2.9).abs().max() > (with_targets[..., 11:15] - 2.9).abs().max()
    # The 1 m-looking columns keep 1 m.
    torch.testing.assert_close(with_targets[..., :6], plain[..., :6], rtol=0.02, atol=0.02)
    assert torch.isfinite(spread).all() and torch.isfinite(plain_spread).all()


def test_targets_scale_exactly_with_the_readings_and_one_target_changes_nothing():
    descriptors, means, valid, rects, targets = _edge_scene(0.3)
    head = PlanarSelectHead(temperature=5.0)
    depth, _, uncertainty = head(descriptors, means, valid, rects, stride=1.0,
                                 zone_targets=targets)
    scaled_targets = targets.clone()
    scaled_targets[..., 0] *= 2.5
    scaled, _, scaled_uncertainty = head(descriptors, 2.5 * means, valid, rects, stride=1.0,
                                         zone_targets=scaled_targets)
    torch.testing.assert_close(scaled, 2.5 * depth, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(scaled_uncertainty, 2.5 * uncertainty, rtol=1e-4, atol=1e-6)
    plain, _, _ = head(descriptors, means, valid, rects, stride=1.0)
    single, _, _ = head(descriptors, means, valid, rects, stride=1.0,
                        zone_targets=targets[:, :, :1])
    torch.testing.assert_close(single, plain)
    empty = targets.clone()
    empty[:, :, 1:] = 0.0  # slots without a target: as if there were none
    same, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_targets=empty)
    torch.testing.assert_close(same, plain, rtol=1e-5, atol=1e-6)


def test_the_share_weighs_the_second_target():
    descriptors, means, valid, rects, _ = _edge_scene(0.0)
    head = PlanarSelectHead(temperature=2.0, planar=False)
    depths = []
    for share in (0.05, 0.5):
        targets = _edge_scene(share)[4]
        depth, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_targets=targets)
        depths.append(depth[..., 11:15].mean())
    assert depths[1] > depths[0] + 0.1


def test_network_takes_zone_targets_and_checks_them():
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 64)).eval()
    assert model.uses_targets
    image = torch.randn(1, 3, 64, 64)
    rows, cols = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    y0, x0 = (rows * 8).reshape(-1).float(), (cols * 8).reshape(-1).float()
    rects = torch.stack([y0, x0, y0 + 8, x0 + 8], dim=-1)[None]
    valid = torch.ones(1, 64, dtype=torch.bool)
    hypotheses = torch.linspace(1.4, 1.6, 16).expand(1, 64, 16).clone()
    targets = torch.zeros(1, 64, 2, 2)
    targets[..., 0, 0], targets[..., 0, 1] = 1.5, 1.0
    with torch.no_grad():
        plain = model(image, hypotheses, rects, valid)["depth"]
        same = model(image, hypotheses, rects, valid, zone_targets=targets)["depth"]
        targets[0, :8, 1] = torch.tensor([3.0, 0.5])  # the top row also sees 3 m
        targets[0, :8, 0, 1] = 0.5
        farther = model(image, hypotheses, rects, valid, zone_targets=targets)["depth"]
    torch.testing.assert_close(same, plain, rtol=1e-5, atol=1e-5)
    assert farther[..., :4, :].mean() > plain[..., :4, :].mean() + 0.05
    with pytest.raises(ValueError, match="zone_targets"):
        model(image, hypotheses, rects, valid, zone_targets=targets[:, :10])
    with pytest.raises(ValueError, match="zone_targets"):
        model(image, hypotheses, rects, valid, zone_targets=torch.full_like(targets, float("nan")))


def test_only_the_frames_largest_further_targets_are_weighed():
    from deltar.models.heads.further_targets import SECONDARY_HYPOTHESES

    torch.manual_seed(3)
    rows, cols = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    y0, x0 = (rows * 4).reshape(-1).float(), (cols * 4).reshape(-1).float()
    rects = torch.stack([y0, x0, y0 + 4, x0 + 4], dim=-1)[None]
    means = torch.rand(1, 64) * 2 + 1.0
    valid = torch.ones(1, 64, dtype=torch.bool)
    descriptors = torch.nn.functional.normalize(torch.randn(1, 6, 32, 32), dim=1)
    targets = torch.zeros(1, 64, 2, 2)
    targets[..., 0, 0] = means
    targets[..., 1, 0] = means + 1.0
    share = torch.rand(1, 64) * 0.5  # every zone reports a second target
    targets[..., 0, 1], targets[..., 1, 1] = 1 - share, share
    head = PlanarSelectHead(temperature=5.0)
    depth, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_targets=targets)
    # The same as a frame whose smaller further targets were never reported (their
    # zones then keep their primary alone, at its full share).
    smallest = torch.argsort(share[0])[: 64 - SECONDARY_HYPOTHESES]
    trimmed = targets.clone()
    trimmed[0, smallest, 1] = 0.0
    trimmed[0, smallest, 0, 1] = 1.0
    expected, _, _ = head(descriptors, means, valid, rects, stride=1.0, zone_targets=trimmed)
    torch.testing.assert_close(depth, expected, rtol=1e-5, atol=1e-5)
    # ...and not the same as with none of them.
    plain, _, _ = head(descriptors, means, valid, rects, stride=1.0)
    assert (depth - plain).abs().max() > 1e-2
