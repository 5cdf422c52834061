"""Training loss: the scaled scale-invariant log loss (Eigen et al. 2014; AdaBins/DELTAR)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def scaled_si_loss(
    pred_m: torch.Tensor,
    target_m: torch.Tensor,
    valid: torch.Tensor | None = None,
    alpha: float = 10.0,
    lam: float = 0.85,
    eps: float = 1e-6,
) -> torch.Tensor:
    """``alpha * sqrt(mean(g^2) - lam * mean(g)^2)``, ``g = log(pred) - log(target)``.

    The means run over all valid pixels of the batch. A prediction of a different
    size is resized bilinearly to the target first.

    Args:
        pred_m: (B, 1, h, w) predicted depth, metres (> 0).
        target_m: (B, 1, H, W) ground-truth depth, metres; 0 marks invalid pixels.
        valid: optional (B, 1, H, W) bool mask; defaults to ``target_m > 0``.
        alpha: scale of the loss (10).
        lam: variance weight lambda (0.85).
        eps: keeps the square root differentiable when the bracket is 0.

    Returns:
        Scalar loss tensor (0 when no pixel is valid).

    Raises:
        ValueError: if the shapes do not match.
    """
    if pred_m.ndim != 4 or target_m.ndim != 4 or pred_m.shape[:2] != target_m.shape[:2]:
        raise ValueError(
            f"pred_m and target_m must be (B, 1, h, w) and (B, 1, H, W), got "
            f"{tuple(pred_m.shape)} and {tuple(target_m.shape)}"
        )
    if pred_m.shape[-2:] != target_m.shape[-2:]:
        pred_m = F.interpolate(pred_m, size=target_m.shape[-2:], mode="bilinear",
                               align_corners=True)
    if valid is None:
        valid = target_m > 0
    elif valid.shape != target_m.shape:
        raise ValueError(f"valid must have the target's shape {tuple(target_m.shape)}")
    valid = valid & (target_m > 0) & (pred_m > 0)
    if not valid.any():
        return pred_m.sum() * 0.0
    g = torch.log(pred_m[valid]) - torch.log(target_m[valid])
    bracket = (g**2).mean() - lam * g.mean() ** 2
    return alpha * torch.sqrt(bracket.clamp_min(0) + eps)
