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
   bins' centres; a zone with no counts left is invalid;
6. with ``max_targets`` > 1, also report the other clusters as further targets, the
   way ST's driver reports several targets per zone (clusters closer than
   ``target_separation_m`` = 0.6 m merged, see
   :func:`~deltar.sensor.simulate_frame.secondary_targets`).

Everything is vectorised over zones and over a batch of depth maps. Step 1 is
:mod:`deltar.sensor.zone_histograms`; the parameters are
:class:`~deltar.sensor.simulator_config.SimulatorConfig`. One frame as a ``ZoneFrame``,
without PyTorch: :func:`deltar.sensor.simulate_frame.simulate_zone_frame` (its numpy
twin, also importable from here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from deltar.sensor import compiled as compiled_kernels
from deltar.sensor.simulate_frame import (
    check_target_options,
    secondary_targets,
    simulate_zone_frame,
    target_signal,
)
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.zone_histograms import use_compiled, zone_histograms, zone_pixel_bounds

__all__ = ["SimulatedZones", "simulate_zone_frame", "simulate_zones", "strongest_cluster"]


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
        no_target: (B, Z) bool, invalid zones that would report *no target* (ST status
            255): more of their pixels with depth lie beyond ``max_range_m`` than within
            it. Invalid zones without it carry no information (e.g. no depth at all).
        target_mean_m: (B, Z, T) float32, every reported target's distance in metres (0
            where not valid), T = ``max_targets``; ``[..., 0]`` is the primary reading
            (``mean_m``), the others in ``target_order``.
        target_sigma_m: (B, Z, T) float32 standard deviations in metres (0 where not valid).
        target_valid: (B, Z, T) bool; ``[..., 0]`` is ``valid``.
        target_signal: (B, Z, T) float32 each target's simulated return signal
            (:func:`~deltar.sensor.simulate_frame.target_signal`; 0 where not valid).
        target_order: order of targets 1.. (``"strongest"`` or ``"closest"``).
    """

    mean_m: torch.Tensor
    sigma_m: torch.Tensor
    valid: torch.Tensor
    histogram: torch.Tensor
    cluster: torch.Tensor
    bin_edges_m: torch.Tensor
    no_target: torch.Tensor
    target_mean_m: torch.Tensor | None = None
    target_sigma_m: torch.Tensor | None = None
    target_valid: torch.Tensor | None = None
    target_order: str = "strongest"
    target_signal: torch.Tensor | None = None


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
                   config: SimulatorConfig | None = None, compiled: bool | None = None,
                   max_targets: int = 1, target_order: str = "strongest") -> SimulatedZones:
    """Simulate the zone signals a multi-zone ToF sensor would report.

    Args:
        depth_m: (B, H, W) or (H, W) float depth map in metres, 0 = invalid pixel.
        rects: (B, Z, 4) or (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels of the depth
            map; a (Z, 4) array is shared by the whole batch. Rectangles may run past the
            image: only the pixels inside count.
        config: simulator parameters; ``SimulatorConfig()`` when None.
        compiled: run the per-pixel counting, the zone sums and the cluster moments in
            the compiled kernels of :mod:`deltar.sensor.compiled` (numba, CPU; the same
            counts, moments equal to float rounding); None uses them when numba is
            installed and the depth is on the CPU.
        max_targets: targets per zone to report, 1..4 (ST's
            ``VL53L5CX_NB_TARGET_PER_ZONE``). Target 0 is the primary reading (the
            strongest cluster, as with 1); the others are the remaining clusters,
            ``config.target_separation_m`` apart (computed from the histograms with
            :func:`~deltar.sensor.simulate_frame.secondary_targets`, on the CPU).
        target_order: order of targets 1.. : ``"strongest"`` first or ``"closest"`` first.

    Returns:
        ``SimulatedZones`` with (B, Z) tensors and (B, Z, max_targets) target tensors, or
        (Z,) and (Z, max_targets) for an unbatched ``depth_m``, on ``depth_m``'s device.

    Raises:
        ValueError: wrong shapes, batch sizes that do not match, NaN or infinite values,
            ``max_targets`` not in 1..4, an unknown ``target_order``.
    """
    cfg = config or SimulatorConfig()
    check_target_options(max_targets, target_order)
    depth = torch.as_tensor(depth_m)
    boxes = torch.as_tensor(rects)
    if depth.ndim not in (2, 3) or not depth.is_floating_point():
        raise ValueError(f"depth_m must be a float (B, H, W) or (H, W) map, got dtype "
                         f"{depth.dtype} and shape {tuple(depth.shape)}")
    if depth.numel() == 0:
        raise ValueError(f"depth_m is empty: shape {tuple(depth.shape)}")
    depth = depth.to(torch.float32)
    compiled = use_compiled(compiled, depth)
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

    histogram = zone_histograms(depth, boxes, cfg, compiled)
    edges = cfg.bin_edges_m().to(depth.device)
    centres = (edges[1:] + edges[:-1]) / 2
    if compiled:
        moments = compiled_kernels.cluster_moments(histogram.numpy(), cfg.ignored_bins,
                                                   cfg.noise_floor_counts, centres.numpy())
        mean, sigma, valid, cluster = (torch.from_numpy(array) for array in moments)
    else:
        cleaned = histogram.clone()
        cleaned[..., : cfg.ignored_bins] = 0.0
        cleaned = (cleaned - cfg.noise_floor_counts).clamp(min=0.0)
        cluster = strongest_cluster(cleaned)
        weights = cluster.to(torch.float64)
        total = weights.sum(-1)
        valid = total > 0
        safe_total = torch.where(valid, total, torch.ones_like(total))
        mean = (weights * centres).sum(-1) / safe_total
        variance = (weights * (centres - mean[..., None]) ** 2).sum(-1) / safe_total
        mean = torch.where(valid, mean, 0.0).to(torch.float32)
        sigma = torch.where(valid, variance.sqrt(), 0.0).to(torch.float32)

    no_target = _no_target(depth, boxes, valid, histogram, cfg)
    targets = [mean[..., None], sigma[..., None], valid[..., None], None]
    if max_targets > 1:
        targets = _with_secondary_targets(histogram, cluster, targets, cfg, max_targets,
                                          target_order)
    out = SimulatedZones(mean_m=mean, sigma_m=sigma, valid=valid, histogram=histogram,
                         cluster=cluster, bin_edges_m=edges.to(torch.float32),
                         no_target=no_target, target_mean_m=targets[0],
                         target_sigma_m=targets[1], target_valid=targets[2],
                         target_signal=targets[3],
                         target_order=target_order)
    if not batched:
        for name in ("mean_m", "sigma_m", "valid", "histogram", "cluster", "no_target",
                     "target_mean_m", "target_sigma_m", "target_valid", "target_signal"):
            if getattr(out, name) is not None:
                setattr(out, name, getattr(out, name)[0])
    return out


def _with_secondary_targets(histogram: torch.Tensor, cluster: torch.Tensor,
                            primary: list[torch.Tensor], config: SimulatorConfig,
                            max_targets: int, target_order: str) -> list[torch.Tensor]:
    """(B, Z, T) mean, sigma, valid and signal: the primary ``[..., :1]`` and the other
    targets.

    The other targets come from the numpy function the single-frame simulator uses
    (:func:`~deltar.sensor.simulate_frame.secondary_targets`), so both agree; the
    cleaning repeats the simulator's steps 2-3 in the same float32 arithmetic.
    """
    hist = histogram.detach().cpu().numpy()
    cleaned = hist.copy()
    cleaned[..., : config.ignored_bins] = 0.0
    cleaned = np.maximum(cleaned - np.float32(config.noise_floor_counts), np.float32(0.0))
    bins = hist.shape[-1]
    centres = (np.arange(bins, dtype=np.float64) + 0.5) * config.bin_width_m
    more = secondary_targets(cleaned.reshape(-1, bins),
                             cluster.detach().cpu().numpy().reshape(-1, bins), centres,
                             config.target_separation_m, max_targets - 1, target_order)
    shape = (*histogram.shape[:-1], max_targets - 1)
    out = [torch.cat([first, torch.from_numpy(rest.reshape(shape)).to(first.device)], dim=-1)
           for first, rest in zip(primary[:3], more[:3], strict=True)]
    counts = np.concatenate([cluster.detach().cpu().numpy().reshape(-1, bins).sum(-1,
                                                                                 keepdims=True),
                             more[3]], axis=1)
    signal = target_signal(counts, out[0].detach().cpu().numpy().reshape(-1, max_targets),
                           np.maximum(hist.reshape(-1, bins).sum(-1), 1.0))
    return [*out, torch.from_numpy(signal.reshape(*shape[:-1], max_targets)).to(out[0].device)]


def _no_target(depth: torch.Tensor, rects: torch.Tensor, valid: torch.Tensor,
               histogram: torch.Tensor, config: SimulatorConfig) -> torch.Tensor:
    """(B, Z) bool: invalid zones with more pixels beyond the range than within it.

    Counted only for the invalid zones (few in most frames), from the depth map itself:
    the histogram holds the in-range pixels only.
    """
    candidates = torch.nonzero(~valid).tolist()
    if not candidates:
        return torch.zeros_like(valid)
    bounds = zone_pixel_bounds(rects, depth.shape[-2], depth.shape[-1]).tolist()
    in_range = histogram.sum(-1).tolist()
    limit = np.float32(config.max_range_m)
    # numpy slices cost a few microseconds each, torch's several times more.
    pixels = depth.cpu().numpy()
    flags = np.zeros(tuple(valid.shape), dtype=bool)
    for b, z in candidates:
        y0, x0, y1, x1 = bounds[b][z]
        flags[b, z] = np.count_nonzero(pixels[b, y0:y1, x0:x1] > limit) > in_range[b][z]
    return torch.from_numpy(flags).to(valid.device)
