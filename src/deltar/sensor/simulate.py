"""Simulate multi-zone ToF readings (VL53L5CX-like) from a metric depth map.

Follows the simulation of the official DELTAR release (its NYU data loader), per zone:

1. histogram the ground-truth depth of the zone's pixels in ``bin_width_m`` bins over
   ``[0, max_range_m]`` (depth beyond the range is left out; a depth exactly at
   ``max_range_m`` falls into the last bin, as with ``torch.histc``);
2. zero the first ``ignored_bins`` bins (< 4 cm by default: invalid or too close);
3. subtract ``noise_floor_counts`` from every bin, clipping at zero;
4. split the non-empty bins into clusters of consecutive bins and keep only the cluster
   with the largest total count (the first one on ties);
5. report the count-weighted mean and (population) standard deviation of the kept
   bins' centres; a zone with no counts left is invalid.

Everything is vectorised over zones and over a batch of depth maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from deltar.sensor.zone_frame import ZoneFrame


@dataclass(frozen=True)
class SimulatorConfig:
    """Parameters of the zone simulator (defaults: the DELTAR paper and release).

    Attributes:
        bin_width_m: histogram bin width in metres (0.04).
        max_range_m: upper end of the histogram in metres (4.0); farther depth is not seen.
        ignored_bins: number of leading bins zeroed before clustering (1: depth < 4 cm).
        noise_floor_counts: counts subtracted from every bin, clipped at 0 (20 pixels).
    """

    bin_width_m: float = 0.04
    max_range_m: float = 4.0
    ignored_bins: int = 1
    noise_floor_counts: float = 20.0

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

    @property
    def num_bins(self) -> int:
        """Number of histogram bins (100 by default)."""
        return round(self.max_range_m / self.bin_width_m)

    def bin_edges_m(self) -> torch.Tensor:
        """(num_bins + 1,) float64 bin edges in metres, from 0 to ``max_range_m``."""
        return torch.arange(self.num_bins + 1, dtype=torch.float64) * self.bin_width_m


@dataclass
class SimulatedZones:
    """Simulated zone signals; ``B`` is absent for an unbatched call.

    Attributes:
        mean_m: (B, Z) float32 zone distance in metres (0 where invalid).
        sigma_m: (B, Z) float32 standard deviation in metres (0 where invalid).
        valid: (B, Z) bool, zones with signal left after the noise floor.
        histogram: (B, Z, bins) float32 raw per-zone pixel counts per depth bin (before
            ignoring bins and subtracting the noise floor).
        cluster: (B, Z, bins) float32 counts of the kept cluster after the noise floor
            (zero outside it); ``mean_m`` and ``sigma_m`` are its moments.
        bin_edges_m: (bins + 1,) float32 bin edges in metres.
    """

    mean_m: torch.Tensor
    sigma_m: torch.Tensor
    valid: torch.Tensor
    histogram: torch.Tensor
    cluster: torch.Tensor
    bin_edges_m: torch.Tensor


def zone_pixel_bounds(rects: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Torch twin of ``geometry.zone_rects_to_pixel_bounds`` (same semantics).

    Args:
        rects: (..., 4) float rectangles (y0, x0, y1, x1) in pixels.
        height, width: image size in pixels.

    Returns:
        (..., 4) int64 half-open pixel bounds clipped to the image; a pixel belongs to
        the zone when its centre lies in ``[y0, y1) x [x0, x1)``.
    """
    r = torch.ceil(rects.to(torch.float64))
    y0, y1 = r[..., 0].clamp(0, height), r[..., 2].clamp(0, height)
    x0, x1 = r[..., 1].clamp(0, width), r[..., 3].clamp(0, width)
    y1, x1 = torch.maximum(y1, y0), torch.maximum(x1, x0)
    return torch.stack([y0, x0, y1, x1], dim=-1).to(torch.int64)


def depth_bin_index(depth_m: torch.Tensor, config: SimulatorConfig) -> torch.Tensor:
    """Histogram bin of every depth value, ``bins`` (one past the last) where not counted.

    Uses the float32 arithmetic of ``torch.histc(depth, bins, 0, max_range_m)`` so that
    values on bin edges land in the same bin as in the official release.

    Args:
        depth_m: (...) depth in metres; 0 (invalid) and negative values are not counted,
            nor is depth beyond ``max_range_m``.
        config: simulator parameters.

    Returns:
        (...) int32 bin indices in ``[0, bins)``, or ``bins`` for values not counted.
    """
    depth = depth_m.to(torch.float32)
    bins = config.num_bins
    max_range = float(np.float32(config.max_range_m))
    # (depth * bins) / max_range in float32, then truncation: torch.histc's arithmetic.
    # int32 keeps the clamp cheap; the clamp closes the last bin like histc does.
    index = (depth * bins).div_(max_range).to(torch.int32).clamp_(max=bins - 1)
    not_counted = depth <= 0
    not_counted |= depth > max_range
    return index.masked_fill_(not_counted, bins)


def zone_histograms(depth_m: torch.Tensor, rects: torch.Tensor,
                    config: SimulatorConfig) -> torch.Tensor:
    """Per-zone depth histograms, vectorised over the batch and the zones.

    Args:
        depth_m: (B, H, W) depth in metres, 0 = invalid pixel.
        rects: (B, Z, 4) zone rectangles (y0, x0, y1, x1) in pixels.
        config: simulator parameters.

    Returns:
        (B, Z, bins) float32 pixel counts.
    """
    batch, height, width = depth_m.shape
    zones = rects.shape[1]
    bins = config.num_bins
    bounds = zone_pixel_bounds(rects, height, width)  # (B, Z, 4)
    y0, x0, y1, x1 = bounds.unbind(-1)
    zone_h, zone_w = y1 - y0, x1 - x0
    max_h, max_w = int(zone_h.max()), int(zone_w.max())
    device = depth_m.device
    if max_h == 0 or max_w == 0:  # every zone is outside the image
        return torch.zeros(batch, zones, bins, dtype=torch.float32, device=device)
    pixels = batch * height * width
    # int32 indices keep the per-pixel work light; int64 only for huge batches (indices
    # below reach 2 * pixels, keys batch * zones * (bins + 1)).
    small = max(2 * pixels, batch * zones * (bins + 1)) < 2**31
    index_dtype = torch.int32 if small else torch.int64
    # Bin of every pixel, plus one trailing "not counted" entry that window pixels
    # outside their zone are pointed at.
    bin_image = depth_bin_index(depth_m, config).reshape(-1).to(index_dtype)
    bin_image = torch.cat([bin_image, bin_image.new_full((1,), bins)])
    # Each zone reads a (max_h, max_w) window from its top-left pixel: flat index =
    # row term + column term, where rows / columns beyond the zone's own size get an
    # offset of ``pixels`` so their sum lands at or past the trailing entry.
    frame_start = (torch.arange(batch, device=device) * (height * width))[:, None]
    dy = torch.arange(max_h, device=device)
    dx = torch.arange(max_w, device=device)
    row_term = frame_start[..., None] + (y0[..., None] + dy) * width  # (B, Z, max_h)
    row_term = torch.where(dy < zone_h[..., None], row_term, pixels)
    col_term = torch.where(dx < zone_w[..., None], x0[..., None] + dx, pixels)  # (B, Z, max_w)
    flat = row_term.to(index_dtype)[..., :, None] + col_term.to(index_dtype)[..., None, :]
    flat = flat.clamp_(max=pixels).reshape(-1)
    zone_bins = bin_image.index_select(0, flat).reshape(batch * zones, -1)
    # One bincount over (frame, zone, bin) keys: each zone owns bins + 1 slots.
    zone_offset = torch.arange(batch * zones, dtype=index_dtype, device=device)[:, None]
    zone_offset *= bins + 1
    keys = zone_bins.add_(zone_offset).reshape(-1)
    counts = torch.bincount(keys, minlength=batch * zones * (bins + 1))
    return counts.reshape(batch, zones, bins + 1)[..., :bins].to(torch.float32)


def strongest_cluster(counts: torch.Tensor) -> torch.Tensor:
    """Keep only the run of consecutive non-empty bins with the largest total count.

    Args:
        counts: (..., bins) non-negative counts.

    Returns:
        (..., bins) counts, zero outside the strongest run (the first one on ties); all
        zero when ``counts`` is all zero.
    """
    nonzero = counts > 0
    previous = torch.nn.functional.pad(nonzero[..., :-1], (1, 0), value=False)
    run_start = nonzero & ~previous
    run_id = torch.cumsum(run_start.to(torch.int64), dim=-1) * nonzero  # 0 = empty bin
    run_sum = torch.zeros(*counts.shape[:-1], counts.shape[-1] + 1, dtype=torch.float64,
                          device=counts.device)
    run_sum.scatter_add_(-1, run_id, counts.to(torch.float64))
    run_sum[..., 0] = -1.0  # the empty bins never win
    best = torch.argmax(run_sum, dim=-1, keepdim=True)  # first maximum on ties
    return torch.where(run_id == best, counts, torch.zeros_like(counts))


def simulate_zones(depth_m: torch.Tensor | np.ndarray, rects: torch.Tensor | np.ndarray,
                   config: SimulatorConfig | None = None) -> SimulatedZones:
    """Simulate the zone signals a multi-zone ToF sensor would report.

    Args:
        depth_m: (B, H, W) or (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (B, Z, 4) or (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels of the depth
            map; a (Z, 4) array is shared by the whole batch. Rectangles may run past the
            image: only the pixels inside count.
        config: simulator parameters; ``SimulatorConfig()`` when None.

    Returns:
        ``SimulatedZones`` with (B, Z) tensors, or (Z,) for an unbatched ``depth_m``, on
        ``depth_m``'s device.

    Raises:
        ValueError: wrong shapes, batch sizes that do not match, NaN or infinite values.
    """
    cfg = config or SimulatorConfig()
    depth = torch.as_tensor(depth_m)
    boxes = torch.as_tensor(rects)
    if depth.ndim not in (2, 3) or not depth.is_floating_point():
        raise ValueError(f"depth_m must be a float (B, H, W) or (H, W) map, got dtype "
                         f"{depth.dtype} and shape {tuple(depth.shape)}")
    if depth.numel() == 0:
        raise ValueError(f"depth_m is empty: shape {tuple(depth.shape)}")
    depth = depth.to(torch.float32)
    # A cheap sum first; the element-wise test only runs when the sum is not finite.
    if not torch.isfinite(depth.sum()) and not torch.isfinite(depth).all():
        raise ValueError("depth_m has NaN or infinite values; mark invalid pixels with 0.0")
    if boxes.ndim not in (2, 3) or boxes.shape[-1] != 4 or boxes.shape[-2] == 0:
        raise ValueError(f"rects must have shape (B, Z, 4) or (Z, 4), got {tuple(boxes.shape)}")
    if not torch.isfinite(boxes).all():
        raise ValueError("rects has NaN or infinite values")
    batched = depth.ndim == 3
    if not batched and boxes.ndim == 3:
        raise ValueError("rects is batched (B, Z, 4) but depth_m is a single (H, W) map")
    if not batched:
        depth = depth[None]
    if boxes.ndim == 2:
        boxes = boxes[None].expand(depth.shape[0], -1, -1)
    if boxes.shape[0] != depth.shape[0]:
        raise ValueError(f"rects has batch size {boxes.shape[0]} but depth_m has "
                         f"{depth.shape[0]}")
    boxes = boxes.to(depth.device)

    histogram = zone_histograms(depth, boxes, cfg)
    cleaned = histogram.clone()
    cleaned[..., : cfg.ignored_bins] = 0.0
    cleaned = (cleaned - cfg.noise_floor_counts).clamp(min=0.0)
    cluster = strongest_cluster(cleaned)

    edges = cfg.bin_edges_m().to(depth.device)
    centres = (edges[1:] + edges[:-1]) / 2
    weights = cluster.to(torch.float64)
    total = weights.sum(-1)
    valid = total > 0
    safe_total = torch.where(valid, total, torch.ones_like(total))
    mean = (weights * centres).sum(-1) / safe_total
    variance = (weights * (centres - mean[..., None]) ** 2).sum(-1) / safe_total
    mean = torch.where(valid, mean, 0.0).to(torch.float32)
    sigma = torch.where(valid, variance.sqrt(), 0.0).to(torch.float32)

    out = SimulatedZones(mean_m=mean, sigma_m=sigma, valid=valid, histogram=histogram,
                         cluster=cluster, bin_edges_m=edges.to(torch.float32))
    if not batched:
        for name in ("mean_m", "sigma_m", "valid", "histogram", "cluster"):
            setattr(out, name, getattr(out, name)[0])
    return out


def simulate_zone_frame(depth_m: np.ndarray, rects: np.ndarray,
                        config: SimulatorConfig | None = None,
                        timestamp_s: float | None = None) -> ZoneFrame:
    """Simulate one sensor reading as a ``ZoneFrame``.

    Args:
        depth_m: (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels, row-major over the
            zone grid as it appears in the image; Z = 16 (4x4) or 64 (8x8).
        config: simulator parameters; ``SimulatorConfig()`` when None.
        timestamp_s: optional capture time stored in the frame.

    Returns:
        A ``ZoneFrame`` with mean, sigma and validity per zone, and the raw per-zone
        histogram (``hist_counts``, ``hist_edges_m``).
    """
    depth = np.asarray(depth_m)
    boxes = np.asarray(rects, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be a single (H, W) map, got shape {depth.shape}")
    if boxes.ndim != 2 or boxes.shape[0] not in (16, 64):
        raise ValueError(f"rects must have shape (16, 4) or (64, 4), got {boxes.shape}")
    zones = simulate_zones(torch.from_numpy(depth.astype(np.float32)), torch.from_numpy(boxes),
                           config)
    return ZoneFrame(mean_m=zones.mean_m.numpy(), sigma_m=zones.sigma_m.numpy(),
                     valid=zones.valid.numpy(), hist_edges_m=zones.bin_edges_m.numpy(),
                     hist_counts=zones.histogram.numpy(), timestamp_s=timestamp_s,
                     sensor_model="simulated")
