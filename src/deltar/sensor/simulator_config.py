"""The zone simulator's parameters: :class:`SimulatorConfig` (histogram bins, range,
ignored bins, noise floor), shared by the simulator (:mod:`deltar.sensor.simulate`), its
per-zone histograms (:mod:`deltar.sensor.zone_histograms`) and the CNH histogram model
(:mod:`deltar.sensor.cnh`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class SimulatorConfig:
    """Parameters of the zone simulator (defaults: the DELTAR paper and release).

    Attributes:
        bin_width_m: histogram bin width in metres (0.04).
        max_range_m: upper end of the histogram in metres (4.0); farther depth is not seen.
        ignored_bins: number of leading bins zeroed before clustering (1: depth < 4 cm).
        noise_floor_counts: counts subtracted from every bin, clipped at 0 (20 pixels).
        target_separation_m: with several targets per zone (``max_targets`` > 1), the
            smallest distance between two reported targets, metres (0.6: ST's user
            manual for the VL53L8CX, UM3109, reports two surfaces less than 600 mm apart
            as one target). Unused with one target per zone.
    """

    bin_width_m: float = 0.04
    max_range_m: float = 4.0
    ignored_bins: int = 1
    noise_floor_counts: float = 20.0
    target_separation_m: float = 0.6

    def __post_init__(self) -> None:
        if not (math.isfinite(self.bin_width_m) and self.bin_width_m > 0):
            raise ValueError(f"SimulatorConfig.bin_width_m must be > 0, got {self.bin_width_m}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > self.bin_width_m):
            raise ValueError(f"SimulatorConfig.max_range_m must exceed bin_width_m, got "
                             f"{self.max_range_m}")
        ratio = self.max_range_m / self.bin_width_m
        if abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(f"SimulatorConfig.max_range_m ({self.max_range_m}) must be a "
                             f"whole number of bins of {self.bin_width_m} m")
        if not 0 <= self.ignored_bins < self.num_bins:
            raise ValueError(f"SimulatorConfig.ignored_bins must be in [0, {self.num_bins}), "
                             f"got {self.ignored_bins}")
        if not (math.isfinite(self.noise_floor_counts) and self.noise_floor_counts >= 0):
            raise ValueError(f"SimulatorConfig.noise_floor_counts must be >= 0, got "
                             f"{self.noise_floor_counts}")
        if not (math.isfinite(self.target_separation_m) and self.target_separation_m > 0):
            raise ValueError(f"SimulatorConfig.target_separation_m must be > 0, got "
                             f"{self.target_separation_m}")

    @property
    def num_bins(self) -> int:
        """Number of histogram bins (100 by default)."""
        return round(self.max_range_m / self.bin_width_m)

    def bin_edges_m(self) -> torch.Tensor:
        """(num_bins + 1,) float64 torch bin edges in metres, from 0 to ``max_range_m``."""
        import torch

        return torch.arange(self.num_bins + 1, dtype=torch.float64) * self.bin_width_m
