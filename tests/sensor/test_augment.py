"""Tests of the training-time signal augmentations (deltar.sensor.augment)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.sensor import SignalAugmentation, training_zone_rects


def _signal(batch: int = 4, zones: int = 36, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    mean = 0.5 + 3 * torch.rand(batch, zones, generator=gen)
    sigma = 0.2 * torch.rand(batch, zones, generator=gen)
    valid = torch.rand(batch, zones, generator=gen) > 0.2
    return mean, sigma, valid


def test_drops_floor_of_the_fraction_of_valid_zones():
    mean, sigma, valid = _signal()
    before = (mean.clone(), sigma.clone(), valid.clone())
    aug = SignalAugmentation(drop_fraction=0.34, noise_prob=0.0)
    out_mean, out_sigma, out_valid = aug(mean, sigma, valid, torch.Generator().manual_seed(1))
    for frame in range(4):
        n_valid = int(valid[frame].sum())
        assert int(out_valid[frame].sum()) == n_valid - int(np.floor(0.34 * n_valid))
    assert not (out_valid & ~valid).any()  # never revives an invalid zone
    dropped = valid & ~out_valid
    assert (out_mean[~out_valid] == 0).all() and (out_sigma[~out_valid] == 0).all()
    assert torch.equal(out_mean[out_valid], mean[out_valid])
    assert dropped.any()
    for original, now in zip(before, (mean, sigma, valid), strict=True):
        assert torch.equal(original, now)  # inputs untouched


def test_same_seed_same_output_and_different_seed_differs():
    mean, sigma, valid = _signal()
    aug = SignalAugmentation()
    first = aug(mean, sigma, valid, torch.Generator().manual_seed(7))
    again = aug(mean, sigma, valid, torch.Generator().manual_seed(7))
    other = aug(mean, sigma, valid, torch.Generator().manual_seed(8))
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(first[2], other[2]) or not torch.equal(first[0], other[0])


def test_noise_always_applied_with_zero_spread_adds_the_mean():
    mean, sigma, valid = _signal()
    aug = SignalAugmentation(drop_fraction=0.0, noise_prob=1.0, noise_mean_m=0.17,
                             noise_std_m=0.0)
    out_mean, out_sigma, out_valid = aug(mean, sigma, valid, torch.Generator().manual_seed(0))
    assert torch.equal(out_valid, valid)
    torch.testing.assert_close(out_mean[valid], mean[valid] + 0.17)
    assert torch.equal(out_sigma[valid], sigma[valid])


def test_noise_statistics():
    zones = 20000
    mean = torch.full((zones,), 2.0, dtype=torch.float64)
    aug = SignalAugmentation(drop_fraction=0.0)
    out_mean, _, _ = aug(mean, torch.full_like(mean, 0.1), torch.ones(zones, dtype=torch.bool),
                         torch.Generator().manual_seed(3))
    changed = out_mean != mean
    # Binomial(20000, 0.3): std of the fraction is 0.0032, so 0.02 is a > 6-sigma margin.
    assert abs(changed.double().mean().item() - 0.3) < 0.02
    noise = (out_mean - mean)[changed]
    assert abs(noise.mean().item() - 0.17) < 0.02
    assert abs(noise.std().item() - 0.20) < 0.02


def test_identity_when_disabled_and_clamp_at_zero():
    mean, sigma, valid = _signal()
    off = SignalAugmentation(drop_fraction=0.0, noise_prob=0.0)
    out = off(mean, sigma, valid, torch.Generator().manual_seed(0))
    assert torch.equal(out[0], torch.where(valid, mean, 0.0))
    assert torch.equal(out[2], valid)
    pull = SignalAugmentation(drop_fraction=0.0, noise_prob=1.0, noise_mean_m=-10.0,
                              noise_std_m=0.0)
    out_mean, _, _ = pull(mean, sigma, valid, torch.Generator().manual_seed(0))
    assert (out_mean == 0).all()


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="drop_fraction"):
        SignalAugmentation(drop_fraction=1.5)
    with pytest.raises(ValueError, match="noise_prob"):
        SignalAugmentation(noise_prob=-0.1)
    with pytest.raises(ValueError, match="noise_std_m"):
        SignalAugmentation(noise_std_m=-1.0)
    mean, sigma, valid = _signal()
    aug = SignalAugmentation()
    with pytest.raises(ValueError, match="generator"):
        aug(mean, sigma, valid, 0)
    with pytest.raises(ValueError, match="valid"):
        aug(mean, sigma, valid.float(), torch.Generator())
    with pytest.raises(ValueError, match="sigma_m"):
        aug(mean, sigma[:, :3], valid, torch.Generator())


def test_training_rects_release_layouts(parity_fixture_path):
    rects = training_zone_rects(416, 544)  # the release's training crop: 6x6 zones of 64 px
    assert rects.shape == (36, 4) and rects.dtype == np.float32
    # int((416 - 384) / 2) = 16, int((544 - 384) / 2) = 80
    assert rects[0].tolist() == [16, 80, 80, 144]
    assert rects[1].tolist() == [16, 144, 80, 208]  # row-major: next zone to the right
    assert rects[6].tolist() == [80, 80, 144, 144]
    assert rects[-1].tolist() == [336, 400, 400, 464]
    # The evaluation layout (8x8 zones of 56 px at 480x640) is the fixture's simulated case.
    fixture = torch.load(parity_fixture_path, weights_only=False)
    case = next(c for c in fixture["cases"] if c["name"] == "aligned_simulation_56px")
    np.testing.assert_array_equal(training_zone_rects(480, 640, grid=8, zone_px=56),
                                  case["zone_rects_yxyx"].numpy())


def test_training_rects_random_offset():
    base = training_zone_rects(416, 544)
    shifts = set()
    for seed in range(30):
        rects = training_zone_rects(416, 544, max_offset_px=8,
                                    generator=np.random.default_rng(seed))
        shift = rects - base
        dy, dx = shift[0, 0], shift[0, 1]
        assert np.all(shift[:, [0, 2]] == dy) and np.all(shift[:, [1, 3]] == dx)
        assert abs(dy) <= 8 and abs(dx) <= 8
        shifts.add((int(dy), int(dx)))
    assert len(shifts) > 10
    same = [training_zone_rects(416, 544, max_offset_px=8,
                                generator=torch.Generator().manual_seed(5)) for _ in range(2)]
    np.testing.assert_array_equal(*same)
    with pytest.raises(ValueError, match="generator"):
        training_zone_rects(416, 544, max_offset_px=8)
    with pytest.raises(ValueError):
        training_zone_rects(0, 544)
