"""Further targets per zone in the plane-select head.

A VL53L5CX/L8CX driver built for several targets per zone reports, beside each zone's
primary reading, the further surfaces it separated (docs/sensor.md). At a depth edge
one zone sees two surfaces; the head lets the frame's largest further targets join the
choice as constant hypotheses, each with a descriptor borrowed from the neighbours that
read like it, and weighs every target by its share of the zone's return
(docs/models.md).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from deltar.models.heads.footprints import zone_offsets

#: Neighbour range (zone sizes per axis) and log-depth similarity of the neighbours a
#: further target borrows its descriptor from (:func:`secondary_descriptors`).
SECONDARY_NEIGHBOURHOOD = 1.6
SECONDARY_SIMILARITY = 0.1
#: Least summed neighbour weight for a borrowed descriptor; below it the target keeps
#: its own zone's descriptor.
SECONDARY_MIN_SUPPORT = 0.05
#: Further targets per frame the head weighs at each pixel, the largest shares first: a
#: fixed count, so the exported graph's extra work is that many hypotheses, not one per
#: zone; more than any protocol frame needs (benchmarks/RESULTS.md, several targets per
#: zone through the network).
SECONDARY_HYPOTHESES = 24


def target_shares(zone_targets: torch.Tensor, zone_valid: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each reported target's share of its zone, and which targets beyond the first exist.

    Args:
        zone_targets: (B, Z, T, 2) per target ``[distance, share]``: the distance in the
            units of the zone readings (0: no target in that slot) and the target's
            share of the zone's footprint (any non-negative scale; normalised here over
            the zone's reported targets; all 0 gives equal shares). Target 0 is the
            zone's primary reading.
        zone_valid: (B, Z) bool.

    Returns:
        ``(share, present)``: (B, Z, T) shares summing to 1 over each valid zone's
        reported targets (target 0 alone: 1), and (B, Z, T - 1) bool, the further targets
        that are reported by a valid zone.
    """
    valid = zone_valid.bool()
    present = (zone_targets[..., 1:, 0] > 0) & valid[..., None]
    reported = torch.cat([valid[..., None], present], dim=-1).to(zone_targets.dtype)
    raw = zone_targets[..., 1].clamp_min(0.0) * reported
    total = raw.sum(-1, keepdim=True)
    count = reported.sum(-1, keepdim=True).clamp_min(1.0)
    share = torch.where(total > 0, raw / total.clamp_min(1e-12), reported / count)
    return share, present


def secondary_descriptors(pooled: torch.Tensor, zone_mean_m: torch.Tensor,
                          zone_valid: torch.Tensor, zone_rects: torch.Tensor,
                          target_m: torch.Tensor) -> torch.Tensor:
    """The descriptor of each further target: borrowed from neighbours that read like it.

    Zone k's further target at distance d is the surface beside the one its primary
    reading describes; the neighbours whose readings lie near d (weight
    ``exp(-0.5 (log(m_j / d) / SECONDARY_SIMILARITY)^2)`` over the valid neighbours
    within :data:`SECONDARY_NEIGHBOURHOOD` zone sizes) show how that surface looks. With
    too little support (< :data:`SECONDARY_MIN_SUPPORT`) the zone's own descriptor is
    kept.

    Args:
        pooled: (B, C, Z) unit zone descriptors.
        zone_mean_m: (B, Z) primary readings (units of ``target_m``).
        zone_valid: (B, Z) bool.
        zone_rects: (B, Z, 4) (y0, x0, y1, x1), pixels.
        target_m: (B, Z, S) further targets' distances (0 where none).

    Returns:
        (B, C, Z * S) unit descriptors, zone-major (zone k's targets at k * S ...).
    """
    batch, zones, slots = target_m.shape
    dy, dx = zone_offsets(zone_rects.to(pooled.dtype))
    index = torch.arange(zones, device=pooled.device)
    eye = index[:, None] == index[None, :]  # (a bool eye exports to ops every runtime has)
    near = (dy.abs() < SECONDARY_NEIGHBOURHOOD) & (dx.abs() < SECONDARY_NEIGHBOURHOOD) & \
        zone_valid.bool()[:, None, :] & ~eye
    log_ratio = torch.log(zone_mean_m.clamp_min(1e-3))[:, None, None, :] - \
        torch.log(target_m.clamp_min(1e-3))[..., None]  # (B, k, s, j)
    weight = torch.exp(-0.5 * (log_ratio / SECONDARY_SIMILARITY) ** 2) * near[:, :, None, :]
    weight = weight.reshape(batch, zones * slots, zones)
    borrowed = pooled @ weight.transpose(1, 2)  # (B, C, Z * S)
    own = pooled.repeat_interleave(slots, dim=2)
    supported = weight.sum(-1) >= SECONDARY_MIN_SUPPORT  # (B, Z * S)
    return F.normalize(torch.where(supported[:, None, :], borrowed, own), dim=1)


class FurtherTargets(NamedTuple):
    """The further targets that join a frame's choice (:func:`further_targets`), K of
    them per frame; tensors (B, ...)."""

    #: (B, C, K) unit descriptors (:func:`secondary_descriptors`).
    descriptors: torch.Tensor
    #: (B, K) log of each one's share of its zone's return.
    log_share: torch.Tensor
    #: (B, K) log distance minus the frame's centre; 0 where the slot holds none.
    log_depth: torch.Tensor
    #: (B, K) bool, the slot holds a reported target.
    present: torch.Tensor
    #: (B, K) long, the zone each belongs to.
    zone: torch.Tensor
    #: (B, Z) the primary's log share where its zone keeps a further target, else 0.
    primary_log_share: torch.Tensor


def further_targets(zone_targets: torch.Tensor, zone_valid: torch.Tensor,
                    pooled: torch.Tensor, zone_mean_m: torch.Tensor,
                    zone_rects: torch.Tensor, centre: torch.Tensor) -> FurtherTargets:
    """The frame's :data:`SECONDARY_HYPOTHESES` largest further targets (by share of
    return; the others, when there are more, are dropped as if not reported).

    Args:
        zone_targets: (B, Z, T, 2) every target of each zone (distance in metres,
            signal), T > 1.
        zone_valid: (B, Z) bool.
        pooled: (B, C, Z) unit zone descriptors.
        zone_mean_m: (B, Z) primary readings, metres (``pooled``'s dtype).
        zone_rects: (B, Z, 4) (y0, x0, y1, x1), pixels.
        centre: (B, 1) the frame's mean log reading of the valid zones.
    """
    dtype = pooled.dtype
    targets = zone_targets.to(dtype)
    share, present = target_shares(targets, zone_valid)
    slots = present.shape[-1]
    descriptors = secondary_descriptors(pooled, zone_mean_m, zone_valid, zone_rects,
                                        targets[..., 1:, 0])
    log_share = torch.log(share.clamp_min(1e-6))
    present = present.flatten(1)  # (B, Z * S), zone-major
    kept = min(SECONDARY_HYPOTHESES, present.shape[1])
    key = torch.where(present, log_share[..., 1:].flatten(1), -1e4)
    # Equal shares keep the lower index, as the exported TopK does (ONNX's tie rule);
    # torch.topk keeps an arbitrary subset of tied values.
    order = (torch.topk(key, kept, dim=1).indices if torch.onnx.is_in_onnx_export() else
             torch.sort(key, dim=1, descending=True, stable=True).indices[:, :kept])  # (B, K)
    present = present.gather(1, order)
    zone_of = torch.div(order, slots, rounding_mode="floor")
    has_more = torch.zeros_like(log_share[..., 0]).scatter_add(
        1, zone_of, present.to(dtype)) > 0
    return FurtherTargets(
        descriptors=descriptors.gather(2, order[:, None, :].expand(-1, descriptors.shape[1],
                                                                   -1)),
        log_share=log_share[..., 1:].flatten(1).gather(1, order),
        log_depth=(torch.log(targets[..., 1:, 0].clamp_min(1e-3)).flatten(1)
                   .gather(1, order) - centre).masked_fill(~present, 0.0),
        present=present, zone=zone_of,
        primary_log_share=torch.where(has_more, log_share[..., 0], 0.0))
