"""Zone selection by image-feature affinity over planar zone hypotheses.

A depth method with almost nothing to learn, built for the case this library meets
most: a new room, no training data from it. Per pixel, depth is a softmax-weighted
geometric mean over the zones of each zone's *local plane* evaluated at that pixel:

- the weights' logits are the zone prior's Gaussian log-weights
  (:func:`~deltar.models.heads.footprints.zone_gaussians`: near zones first) plus a
  temperature times the cosine similarity between the pixel's image descriptor and the
  zone's (its descriptors pooled over its footprint): a pixel takes the depth of the
  zones that look like it, as a joint bilateral filter does with colours, but with the
  frozen ImageNet features of the encoder, which tell surfaces apart better than colour;
- each zone's hypothesis is not a constant but the plane through its reading fitted to
  its neighbours that read alike (:func:`zone_planes`), so slanted floors and walls keep
  their slope inside a zone and past the edge of the sensor's field of view;
- a zone that reports more than one target (a depth edge inside the zone: the sensor
  separates surfaces at least 0.6 m apart) offers each further target as a hypothesis
  of its own (:mod:`deltar.models.heads.further_targets`): the zone's spatial prior,
  a descriptor borrowed from the neighbours that read like that target, and the log of each
  target's share of the zone as prior weight, so a pixel takes the second surface when
  it looks like the neighbours on that surface.

The metric scale comes from the zones alone: every output is a weighted mean of planes
anchored at the zone readings, and the planes are fitted on readings relative to each
zone, so scaling every reading by ``k`` scales the depth by ``k`` exactly.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from deltar.models.affinity import FactoredDescriptors
from deltar.models.heads.base import DepthHead, HeadOutput, ZoneInputs
from deltar.models.heads.footprints import (
    footprint_pool,
    selection_outputs,
    softmax_over_zones,
    zone_gaussians,
    zone_geometry,
    zone_offsets,
)
from deltar.models.heads.further_targets import further_targets
from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M


def zone_planes(zone_mean_m: torch.Tensor, zone_valid: torch.Tensor, zone_rects: torch.Tensor,
                neighbourhood: float = 1.6, similarity: float = 0.05, ridge: float = 0.1
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each zone's local plane: inverse-depth slopes fitted to neighbours that read alike.

    A plane seen through a pinhole camera has an inverse depth that is affine in the
    pixel coordinates, so a zone's plane is ``1 / d(p) = (1 / m_k) (1 + a_k v + b_k u)``
    with (v, u) the pixel's offset from the zone centre in zone heights / widths. The
    slopes (a_k, b_k) are the weighted least-squares fit, through the zone's own
    reading, of its valid neighbours (centres within ``neighbourhood`` zone sizes),
    each weighted by ``exp(-0.5 (log(m_j / m_k) / similarity)^2)`` so that a neighbour
    across a depth edge does not tilt the plane, with a ridge that pulls the slopes of
    zones without enough support to zero (a fronto-parallel plane).

    Args:
        zone_mean_m: (B, Z) zone readings, metres (ignored where not valid).
        zone_valid: (B, Z) bool.
        zone_rects: (B, Z, 4) (y0, x0, y1, x1), pixels.
        neighbourhood: neighbour range, in zone sizes per axis.
        similarity: log-depth difference at which a neighbour's weight falls to e^-0.5.
        ridge: regularisation of the slopes (in the units of the weights' sum).

    Returns:
        ``(slope_y, slope_x)``: (B, Z) relative inverse-depth change per zone height and
        per zone width (0 for invalid zones).
    """
    dy, dx = zone_offsets(zone_rects.to(zone_mean_m.dtype))
    valid = zone_valid.bool()
    log_mean = torch.log(zone_mean_m.clamp_min(1e-3))
    log_ratio = log_mean[:, None, :] - log_mean[:, :, None]  # log(m_j / m_k)
    near = (dy.abs() < neighbourhood) & (dx.abs() < neighbourhood) & valid[:, None, :]
    weight = torch.exp(-0.5 * (log_ratio / similarity) ** 2) * near
    # Relative inverse depth of neighbour j seen from zone k, minus the anchor's 1.
    target = torch.exp(-log_ratio) - 1.0
    syy = (weight * dy * dy).sum(-1) + ridge
    sxx = (weight * dx * dx).sum(-1) + ridge
    sxy = (weight * dy * dx).sum(-1)
    ry = (weight * dy * target).sum(-1)
    rx = (weight * dx * target).sum(-1)
    # The 2x2 normal equations solved in closed form (exports to plain ONNX ops).
    det = syy * sxx - sxy * sxy
    slope_y = (sxx * ry - sxy * rx) / det
    slope_x = (syy * rx - sxy * ry) / det
    return slope_y.masked_fill(~valid, 0.0), slope_x.masked_fill(~valid, 0.0)


class PlanarSelectHead(DepthHead):
    """Depth as an affinity-weighted choice among the zones' local planes (log depth).

    Args:
        temperature: initial weight of the cosine affinity against the Gaussian prior
            (learned; 0 gives the prior's purely spatial weights).
        planar: use each zone's plane (:func:`zone_planes`); False uses constant zone
            readings, as :class:`~deltar.models.heads.zone_select.ZoneSelectHead` does.
        max_ratio: a plane's depth is clamped to within this factor of its zone reading
            (extrapolated far from its zone a plane would run off to infinity).
        n_bins: number of entries of the reported ``bin_edges`` (N + 1 edges).
        min_depth, max_depth: output clamp, metres.
        no_target_depth: depth in metres of the hypothesis a zone that reported *no
            target* offers (ST status 255: nothing returned within the sensor's range, so
            the surface is farther than the range); absolute, not scaled with the
            readings. None: the head ignores the flags (weights saved before they
            existed load that way).
    """

    uses_targets = True
    #: The ONNX export may hand :meth:`forward` :class:`FactoredDescriptors`.
    reads_factored_descriptors = True

    def __init__(self, temperature: float = 5.0, planar: bool = True, max_ratio: float = 2.0,
                 n_bins: int = 64, min_depth: float = 1e-3, max_depth: float = 10.0,
                 no_target_depth: float | None = NO_TARGET_DEPTH_M) -> None:
        super().__init__()
        if max_ratio <= 1.0:
            raise ValueError(f"max_ratio must be > 1, got {max_ratio}")
        if no_target_depth is not None and not (
                math.isfinite(no_target_depth) and min_depth < no_target_depth <= max_depth):
            raise ValueError(f"no_target_depth must lie in ({min_depth}, {max_depth}] m, got "
                             f"{no_target_depth}")
        self.uses_no_target = no_target_depth is not None
        self.no_target_depth = None if no_target_depth is None else float(no_target_depth)
        self.planar = bool(planar)
        self.max_ratio = float(max_ratio)
        self.min_depth, self.max_depth = min_depth, max_depth
        self.temperature = nn.Parameter(torch.tensor(float(temperature)))
        limit = math.log(3.0)
        self.register_buffer("edges", torch.linspace(-limit, limit, n_bins + 1),
                             persistent=False)

    def forward(self, descriptors: torch.Tensor, zone_mean_m: torch.Tensor,
                zone_valid: torch.Tensor, zone_rects: torch.Tensor, stride: float,
                zone_no_target: torch.Tensor | None = None,
                zone_scale_m: torch.Tensor | None = None,
                zone_targets: torch.Tensor | None = None) -> HeadOutput:
        """Depth, bin edges and uncertainty: the inputs and outputs of
        :meth:`~deltar.models.heads.zone_select.ZoneSelectHead.forward`, with unit-length
        pixel descriptors (B, C, h, w)
        (:class:`~deltar.models.affinity.EncoderDescriptors`) as the features; the
        uncertainty is the spread of the chosen planes' log depths.

        ``zone_no_target`` (B, Z) bool, optional: zones that reported no target; each
        (where not valid) joins the choice with the constant hypothesis
        ``no_target_depth``. Valid zones alone set the planes and the frame's centre.
        ``zone_scale_m`` (B,), optional: metres per unit of ``zone_mean_m`` (when the
        readings were divided by the frame's scale), to place that absolute depth.
        ``zone_targets`` (B, Z, T, 2), optional: every target each zone reported,
        ``[distance, share]`` (:func:`~deltar.models.heads.further_targets.target_shares`;
        distances in the units of ``zone_mean_m``); the frame's largest targets beyond
        the first join the choice as constant hypotheses with borrowed descriptors
        (:func:`~deltar.models.heads.further_targets.further_targets`), and every
        target's log share is added to its weight's logit.
        """
        if torch.onnx.is_in_onnx_export() and self.planar:
            return self._export_forward(descriptors, zone_mean_m, zone_valid, zone_rects,
                                        stride, zone_no_target, zone_scale_m, zone_targets)
        if isinstance(descriptors, FactoredDescriptors):
            descriptors = descriptors.materialise()
        _, _, height, width = descriptors.shape
        dtype = descriptors.dtype
        valid, chosen, means, log_mean, centre = self._zone_log_depths(
            zone_mean_m, zone_valid, zone_no_target, zone_scale_m, dtype)
        log_wy, log_wx = zone_gaussians(zone_rects, chosen, (height, width), stride, dtype)
        pooled = F.normalize(footprint_pool(descriptors, log_wy, log_wx), dim=1)  # (B, C, Z)
        pixels = descriptors.flatten(2).transpose(1, 2)  # (B, h*w, C)
        cosine = pixels @ pooled  # (B, h*w, Z)
        prior_logits = (log_wy[:, :, None, :] + log_wx[:, None, :, :]).flatten(1, 2)
        logits = prior_logits + self.temperature.to(dtype) * cosine
        log_extra = None  # (B, K) the further targets' log depths
        if zone_targets is not None and zone_targets.shape[2] > 1:
            further = further_targets(zone_targets, valid, pooled, means, zone_rects, centre)
            logits = logits + further.primary_log_share[:, None, :]
            cosine_2 = pixels @ further.descriptors  # (B, h*w, K)
            logits_2 = prior_logits.gather(2, further.zone[:, None, :].expand(
                -1, prior_logits.shape[1], -1)) + self.temperature.to(dtype) * cosine_2 + \
                further.log_share[:, None, :]
            logits_2 = logits_2.masked_fill(~further.present[:, None, :], -1e4)
            logits = torch.cat([logits, logits_2], dim=-1)
            log_extra = further.log_depth  # constant hypotheses
        weights = softmax_over_zones(logits)
        if self.planar:
            hypotheses = log_mean[:, None, :] - torch.log(
                self._plane_ratio(means, valid, zone_rects.to(dtype), (height, width), stride))
            if log_extra is not None:
                hypotheses = torch.cat(
                    [hypotheses, log_extra[:, None, :].expand(-1, hypotheses.shape[1], -1)],
                    dim=-1)
            # (B, h*w, Z). No mask needed: a zone that is not chosen has log_mean 0 and
            # slopes 0, so its hypothesis is log(1) = 0 already.
            log_depth = (weights * hypotheses).sum(-1, keepdim=True)
        else:
            if log_extra is not None:
                log_mean = torch.cat([log_mean, log_extra], dim=-1)
            hypotheses = log_mean[:, None, :]
            log_depth = weights @ log_mean[..., None]
        # The variance from the deviations: the difference of second moments cancels
        # where one zone dominates, leaving float32 rounding (a spread of about 3e-4 in
        # place of nearly 0) that differs between runtimes and moves the confidence blend.
        deviation = hypotheses - log_depth
        spread = (weights * deviation * deviation).sum(-1, keepdim=True).sqrt()
        low, high = self._output_range(zone_scale_m, dtype)
        return selection_outputs(log_depth + centre[:, :, None], spread, chosen,
                                 (height, width), self.edges, low, high)

    def _export_forward(self, descriptors: torch.Tensor, zone_mean_m: torch.Tensor,
                        zone_valid: torch.Tensor, zone_rects: torch.Tensor, stride: float,
                        zone_no_target: torch.Tensor | None,
                        zone_scale_m: torch.Tensor | None,
                        zone_targets: torch.Tensor | None) -> HeadOutput:
        """:meth:`forward` (planar) as the ONNX export writes it: the same values to float32
        rounding, in fewer passes over the (B, h, w, N) per-cell tensors, which onnxruntime
        runs one operator at a time.

        Every hypothesis, a zone's plane or a further target's constant depth, is one
        *column* described by small per-column tensors: its descriptor (scaled by the
        temperature), its prior's row and column log-weights (with its log share and,
        for an unreported target slot, the -1e4 of a masked logit folded in), its log
        depth and its plane's inverse-depth ratio along rows and columns (slopes 0 for a
        constant). The per-cell work is then one product, two broadcast sums, the
        clamped softmax and one chain for the hypotheses, on all columns at once: no
        gathers, concatenations or masks on per-cell tensors. A constant's ratio is 1,
        so its hypothesis is exactly its log depth.

        ``descriptors`` may be :class:`~deltar.models.affinity.FactoredDescriptors` (the
        export of :class:`~deltar.models.affinity.EncoderDescriptors`): the footprint sums
        and the per-cell dot products are then computed from the coarse encoder maps,
        the descriptors never formed.
        """
        batch, _, height, width = descriptors.shape
        dtype = descriptors.dtype
        valid, chosen, means, log_mean, centre = self._zone_log_depths(
            zone_mean_m, zone_valid, zone_no_target, zone_scale_m, dtype)
        rects = zone_rects.to(dtype)
        log_wy, log_wx = zone_gaussians(zone_rects, chosen, (height, width), stride, dtype)
        if isinstance(descriptors, FactoredDescriptors):
            # Footprints up to each zone's largest, floored at e^-30 per axis (a change
            # of ~1e-13 after the normalisation below): their products with the
            # descriptors' factors must stay far from subnormal floats, which make the
            # matrix products many times slower.
            pooled = descriptors.pool(
                *(torch.exp((w - w.amax(dim=1, keepdim=True)).clamp_min(-30.0))
                  for w in (log_wy, log_wx)))
        else:
            pooled = footprint_pool(descriptors, log_wy, log_wx)
        pooled = F.normalize(pooled, dim=1)  # (B, C, Z)
        # The planes' inverse-depth ratio, separable: ratio_y (B, h, Z) + ratio_x (B, w, Z).
        slope_y, slope_x = zone_planes(means, valid, rects)
        centre_y, centre_x, zone_h, zone_w = zone_geometry(rects)
        rows = (torch.arange(height, dtype=dtype) + 0.5) * stride
        cols = (torch.arange(width, dtype=dtype) + 0.5) * stride
        ratio_y = 1.0 + slope_y[:, None, :] * (
            (rows[None, :, None] - centre_y[:, None, :]) / zone_h[:, None])
        ratio_x = slope_x[:, None, :] * ((cols[None, :, None] - centre_x[:, None, :])
                                         / zone_w[:, None])
        table = pooled * self.temperature.to(dtype)
        if zone_targets is not None and zone_targets.shape[2] > 1:
            further = further_targets(zone_targets, valid, pooled, means, zone_rects, centre)
            present, zone_of = further.present[:, None, :], further.zone[:, None, :]
            log_wy_1 = log_wy + further.primary_log_share[:, None, :]
            # An unreported slot's logit sits at -1e4 (as the masked logit does): the
            # clamped softmax gives it the same floor weight.
            log_wy_2 = torch.where(present, log_wy.gather(2, zone_of.expand(-1, height, -1))
                                   + further.log_share[:, None, :],
                                   torch.tensor(-1e4, dtype=dtype))
            log_wx_2 = torch.where(present, log_wx.gather(2, zone_of.expand(-1, width, -1)),
                                   torch.tensor(0.0, dtype=dtype))
            log_extra = further.log_depth
            table = torch.cat([table, self.temperature.to(dtype) * further.descriptors], dim=2)
            log_wy = torch.cat([log_wy_1, log_wy_2], dim=2)
            log_wx = torch.cat([log_wx, log_wx_2], dim=2)
            log_mean = torch.cat([log_mean, log_extra], dim=1)
            ratio_y = torch.cat([ratio_y, torch.ones_like(log_wy_2)], dim=2)
            ratio_x = torch.cat([ratio_x, torch.zeros_like(log_wx_2)], dim=2)
        columns = table.shape[2]
        if isinstance(descriptors, FactoredDescriptors):
            affinity = descriptors.dot(table)  # (B, h, w, N)
        else:
            affinity = (descriptors.flatten(2).transpose(1, 2) @ table).reshape(
                batch, height, width, columns)
        logits = affinity + log_wy[:, :, None, :] + log_wx[:, None, :, :]
        # softmax_over_zones' clamp, as a floor: the softmax subtracts the same peak.
        peak = logits.amax(dim=-1, keepdim=True)
        weights = torch.softmax(torch.maximum(logits, peak - 80.0), dim=-1)
        ratio = (ratio_y[:, :, None, :] + ratio_x[:, None, :, :]).clamp(
            1.0 / self.max_ratio, self.max_ratio)
        hypotheses = log_mean[:, None, None, :] - torch.log(ratio)
        log_depth = (weights * hypotheses).sum(-1, keepdim=True)
        deviation = hypotheses - log_depth
        spread = (weights * deviation * deviation).sum(-1, keepdim=True).sqrt()
        low, high = self._output_range(zone_scale_m, dtype)
        return selection_outputs(log_depth.reshape(batch, height * width, 1) + centre[:, :, None],
                                 spread.reshape(batch, height * width, 1), chosen,
                                 (height, width), self.edges, low, high)

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """The choice among the zones' planes (:meth:`forward`), descriptors as features."""
        return self(features, zones.mean_m(features.dtype), zones.valid, zones.rects,
                    zones.stride, zones.no_target, zones.scale_m, zones.targets)

    def _output_range(self, zone_scale_m: torch.Tensor | None, dtype: torch.dtype
                      ) -> tuple[float | torch.Tensor, float | torch.Tensor]:
        """The output clamp (low, high) in the readings' units: metres, or (B,) when the
        readings were divided by the frame's scale ``zone_scale_m``."""
        low, high = self.min_depth, self.max_depth
        if zone_scale_m is not None:
            scale = zone_scale_m.to(dtype)
            low, high = low / scale, high / scale
        return low, high

    def _zone_log_depths(self, zone_mean_m: torch.Tensor, zone_valid: torch.Tensor,
                         zone_no_target: torch.Tensor | None,
                         zone_scale_m: torch.Tensor | None, dtype: torch.dtype
                         ) -> tuple[torch.Tensor, ...]:
        """The zones' log depths, relative to the frame's mean valid reading.

        Returns:
            ``(valid, chosen, means, log_mean, centre)``: (B, Z) bool valid zones; (B, Z)
            bool zones that join the choice (the valid ones, and the no-target ones for
            a head that reads the flags); (B, Z) readings in metres; (B, Z) log readings
            minus ``centre`` (no-target zones at the range limit, other invalid zones 0);
            (B, 1) ``centre``, the mean log reading of the valid zones.
        """
        valid = zone_valid.bool()
        far = None if zone_no_target is None or not self.uses_no_target else \
            zone_no_target.bool() & ~valid
        chosen = valid if far is None else valid | far
        means = zone_mean_m.to(dtype)
        log_mean = torch.log(means.clamp_min(1e-3))
        # Relative to the frame's mean valid reading: small numbers, so the sums over
        # pixels keep float32's relative precision.
        centre = (log_mean * valid).sum(1, keepdim=True) / valid.sum(1, keepdim=True).clamp_min(1)
        log_mean = (log_mean - centre).masked_fill(~valid, 0.0)
        if far is not None:
            # Absolute: the range limit does not scale with the scene.
            log_far = math.log(self.no_target_depth) - centre
            if zone_scale_m is not None:
                log_far = log_far - torch.log(zone_scale_m.to(dtype))[:, None]
            log_mean = torch.where(far, log_far.to(dtype), log_mean)
        return valid, chosen, means, log_mean, centre

    def _plane_ratio(self, means: torch.Tensor, valid: torch.Tensor, rects: torch.Tensor,
                     size: tuple[int, int], stride: float) -> torch.Tensor:
        """(B, h*w, Z) inverse depth of each zone's plane at each cell, over its reading."""
        slope_y, slope_x = zone_planes(means, valid, rects)
        centre_y, centre_x, zone_h, zone_w = zone_geometry(rects)
        rows = (torch.arange(size[0], device=rects.device, dtype=rects.dtype) + 0.5) * stride
        cols = (torch.arange(size[1], device=rects.device, dtype=rects.dtype) + 0.5) * stride
        offset_y = (rows[None, :, None] - centre_y[:, None, :]) / zone_h[:, None]  # (B, h, Z)
        offset_x = (cols[None, :, None] - centre_x[:, None, :]) / zone_w[:, None]  # (B, w, Z)
        ratio = 1.0 + (slope_y[:, None, :] * offset_y)[:, :, None, :] + \
            (slope_x[:, None, :] * offset_x)[:, None, :, :]  # (B, h, w, Z)
        return ratio.clamp(1.0 / self.max_ratio, self.max_ratio).flatten(1, 2)
