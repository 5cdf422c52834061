"""Scaled scale-invariant loss against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from deltar.models import scaled_si_loss


def test_constant_log_ratio_gives_closed_form():
    # g = log 2 everywhere: mean(g^2) - 0.85 mean(g)^2 = 0.15 (log 2)^2.
    target = torch.full((1, 1, 4, 4), 1.5)
    loss = scaled_si_loss(2.0 * target, target, eps=0.0)
    assert loss.item() == pytest.approx(10.0 * math.sqrt(0.15) * math.log(2.0), rel=1e-5)


def test_matches_numpy_reference_with_mask(rng):
    pred = rng.uniform(0.5, 5.0, size=(2, 1, 6, 8)).astype(np.float32)
    target = rng.uniform(0.5, 5.0, size=(2, 1, 6, 8)).astype(np.float32)
    target[0, 0, :2] = 0.0  # invalid ground truth must be ignored
    g = np.log(pred[target > 0]) - np.log(target[target > 0])
    expected = 10.0 * np.sqrt(np.mean(g**2) - 0.85 * np.mean(g) ** 2)
    loss = scaled_si_loss(torch.from_numpy(pred), torch.from_numpy(target), eps=0.0)
    assert loss.item() == pytest.approx(float(expected), rel=1e-5)


def test_prediction_is_resized_and_gradients_flow():
    pred = torch.full((1, 1, 4, 4), 2.0, requires_grad=True)
    target = torch.rand(1, 1, 8, 8) + 0.5
    scaled_si_loss(pred, target).backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_no_valid_pixel_gives_zero_and_bad_shapes_raise():
    pred = torch.ones(1, 1, 4, 4, requires_grad=True)
    assert scaled_si_loss(pred, torch.zeros(1, 1, 4, 4)).item() == 0.0
    with pytest.raises(ValueError, match="pred_m"):
        scaled_si_loss(torch.ones(4, 4), torch.ones(4, 4))
