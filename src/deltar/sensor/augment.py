"""Training-time augmentations of the zone signal and the training zone layout.

Defaults are those of the official release's NYU training configuration: drop 34% of
the valid zones, add N(0.17 m, 0.20 m) to a zone's mean with probability 0.3, and a 6x6
grid of 64 px zones centred in the crop. See docs/sensor.md for where this code
deliberately differs from what the release's loader effectively does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class SignalAugmentation:
    """Randomly drop zones and perturb zone means, as when training DELTAR.

    Attributes:
        drop_fraction: fraction of each frame's valid zones made invalid,
            ``floor(drop_fraction * n_valid)`` zones chosen without replacement.
        noise_prob: probability that a (remaining) valid zone's mean gets noise.
        noise_mean_m: mean of the Gaussian noise added to a zone mean, metres.
        noise_std_m: standard deviation of that noise, metres.
    """

    drop_fraction: float = 0.34
    noise_prob: float = 0.3
    noise_mean_m: float = 0.17
    noise_std_m: float = 0.20

    def __post_init__(self) -> None:
        for name in ("drop_fraction", "noise_prob"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"SignalAugmentation.{name} must be in [0, 1], got {value}")
        if not np.isfinite(self.noise_mean_m):
            raise ValueError(f"SignalAugmentation.noise_mean_m must be finite, got "
                             f"{self.noise_mean_m}")
        if not (np.isfinite(self.noise_std_m) and self.noise_std_m >= 0):
            raise ValueError(f"SignalAugmentation.noise_std_m must be >= 0, got "
                             f"{self.noise_std_m}")

    def __call__(self, mean_m: torch.Tensor, sigma_m: torch.Tensor, valid: torch.Tensor,
                 generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Augment one frame (Z,) or a batch (..., Z) of zone signals.

        Args:
            mean_m: (..., Z) zone means in metres.
            sigma_m: (..., Z) zone standard deviations in metres.
            valid: (..., Z) bool validity.
            generator: torch generator (CPU) that drives every random choice.

        Returns:
            New ``(mean_m, sigma_m, valid)`` tensors of the same shapes; the inputs are
            not modified. Dropped zones are invalid with mean and sigma 0; noisy means
            are clamped at 0 m.
        """
        import torch

        mean = torch.as_tensor(mean_m)
        sigma = torch.as_tensor(sigma_m)
        valid = torch.as_tensor(valid)
        if not mean.is_floating_point() or mean.ndim < 1:
            raise ValueError(f"mean_m must be a float tensor of shape (..., Z), got "
                             f"{mean.dtype} {tuple(mean.shape)}")
        if sigma.shape != mean.shape:
            raise ValueError(f"sigma_m has shape {tuple(sigma.shape)}, expected "
                             f"{tuple(mean.shape)}")
        if valid.dtype != torch.bool or valid.shape != mean.shape:
            raise ValueError(f"valid must be a bool tensor of shape {tuple(mean.shape)}")
        if not isinstance(generator, torch.Generator):
            raise ValueError("generator must be a torch.Generator (seed it for reproducible "
                             "training)")
        device = mean.device
        shape = mean.shape

        # Drop: rank the valid zones of each frame in random order, drop the first k.
        keys = torch.rand(shape, generator=generator).to(device)
        keys = torch.where(valid, keys, torch.full_like(keys, 2.0))  # invalid zones last
        rank = torch.argsort(torch.argsort(keys, dim=-1), dim=-1)
        n_drop = torch.floor(valid.sum(-1, keepdim=True) * self.drop_fraction + 1e-9)
        kept = valid & (rank >= n_drop)

        # Noise on the means of the zones that are still valid.
        hit = torch.rand(shape, generator=generator).to(device) < self.noise_prob
        noise = torch.randn(shape, generator=generator, dtype=torch.float64).to(device)
        noise = (noise * self.noise_std_m + self.noise_mean_m).to(mean.dtype)
        noisy_mean = torch.where(kept & hit, (mean + noise).clamp(min=0.0), mean)

        zero = torch.zeros((), dtype=mean.dtype, device=device)
        return (torch.where(kept, noisy_mean, zero), torch.where(kept, sigma, zero.to(sigma.dtype)),
                kept)


def training_zone_rects(height: int, width: int, grid: int = 6, zone_px: int = 64,
                        max_offset_px: int = 0,
                        generator: np.random.Generator | torch.Generator | None = None,
                        ) -> np.ndarray:
    """Square zone grid centred in the image, as the release simulates for training.

    The grid starts at ``(int((height - grid * zone_px) / 2), int((width - grid * zone_px)
    / 2))``; with ``max_offset_px > 0`` it is shifted by an integer offset drawn uniformly
    from ``[-max_offset_px, max_offset_px]``, independently for rows and columns. The
    release's evaluation layout is ``grid=8, zone_px=56`` (at 480x640: from (16, 96)).

    Args:
        height, width: image size in pixels.
        grid: zones per side.
        zone_px: zone side in pixels.
        max_offset_px: largest random shift of the whole grid in pixels.
        generator: numpy or torch generator; required when ``max_offset_px > 0``.

    Returns:
        (grid * grid, 4) float32 rectangles (y0, x0, y1, x1) in pixels, row-major; they
        may run past the image when it is smaller than the grid.
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    if grid <= 0 or zone_px <= 0:
        raise ValueError(f"grid and zone_px must be positive, got grid={grid}, "
                         f"zone_px={zone_px}")
    if max_offset_px < 0:
        raise ValueError(f"max_offset_px must be >= 0, got {max_offset_px}")
    offset_y = offset_x = 0
    if max_offset_px > 0:
        if isinstance(generator, np.random.Generator):
            offset_y, offset_x = (int(v) for v in generator.integers(
                -max_offset_px, max_offset_px + 1, size=2))
        elif type(generator).__module__.startswith("torch"):  # a torch.Generator
            import torch

            offset_y, offset_x = (int(v) for v in torch.randint(
                -max_offset_px, max_offset_px + 1, (2,), generator=generator))
        else:
            raise ValueError("generator (numpy or torch) is required when max_offset_px > 0")
    top = int((height - grid * zone_px) / 2) + offset_y
    left = int((width - grid * zone_px) / 2) + offset_x
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    y0 = top + rows.reshape(-1) * zone_px
    x0 = left + cols.reshape(-1) * zone_px
    return np.stack([y0, x0, y0 + zone_px, x0 + zone_px], axis=1).astype(np.float32)
