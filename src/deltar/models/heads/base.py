"""The one head interface: :class:`DepthHead`, its inputs :class:`ZoneInputs` and its
output :class:`HeadOutput`, and the bin arithmetic several heads share.

Every head is a :class:`DepthHead`: ``head.predict(features, zones)`` takes the
decoder's features and the frame's :class:`ZoneInputs` and returns a
:class:`HeadOutput` (depth, bin edges, uncertainty in metres), so
:class:`~deltar.models.network.DeltarNet` calls every head the same way. Each head's
``forward`` keeps its own, narrower inputs (what the head itself computes on).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn


def bins_to_depth(
    normalised_widths: torch.Tensor,
    logits: torch.Tensor,
    min_depth: float,
    max_depth: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depth, bin edges and uncertainty from bin widths and per-pixel bin logits.

    The per-pixel bin probabilities are ``softmax(logits, dim=1)``; depth is their
    expectation over the bin centres and the uncertainty their standard deviation.

    Args:
        normalised_widths: (B, N) widths summing to 1.
        logits: (B, N, h, w) per-pixel bin logits. Overwritten in place when
            autograd is off (it is a temporary of the head).
        min_depth: depth of the first edge, metres.
        max_depth: depth of the last edge, metres.

    Returns:
        depth (B, 1, h, w) metres, bin_edges (B, N + 1) metres, and uncertainty
        (B, 1, h, w) metres.
    """
    widths = (max_depth - min_depth) * normalised_widths
    widths = F.pad(widths, (1, 0), mode="constant", value=min_depth)
    edges = torch.cumsum(widths, dim=1)
    centres = 0.5 * (edges[:, :-1] + edges[:, 1:])  # (B, N)
    depth, spread = softmax_moments(logits, centres)
    return depth, edges, spread


def softmax_moments(logits: torch.Tensor, centres: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard deviation of per-pixel softmax distributions over bin centres.

    Computed as three moments with one matrix product over the bins (no softmax
    along the channel axis, which exporters lower to slow transposes).

    Args:
        logits: (B, N, h, w) per-pixel bin logits. Overwritten in place when autograd
            is off (it is a temporary of the head).
        centres: (B, N) or (N,) bin centres, in the unit of the result (metres or
            log-ratio).

    Returns:
        mean (B, 1, h, w) and standard deviation (B, 1, h, w) of the centres under
        ``softmax(logits, dim=1)``.
    """
    batch, bins, height, width = logits.shape
    centres = centres.expand(batch, bins)
    # Unnormalised softmax weights; the normaliser is the zeroth moment below.
    peak = logits.amax(dim=1, keepdim=True)
    if torch.is_grad_enabled():
        weights = torch.exp(logits - peak)
    else:
        weights = logits.sub_(peak).exp_()
    # Moments about a per-image reference keep E[c^2] - E[c]^2 well conditioned.
    reference = centres.mean(dim=1, keepdim=True)
    shifted = centres - reference
    moments = torch.stack([torch.ones_like(shifted), shifted, shifted**2], dim=1)  # (B, 3, N)
    if weights.is_contiguous():
        totals = (moments @ weights.reshape(batch, bins, height * width)).reshape(
            batch, 3, height, width
        )
    else:
        # Channels-last logits (from channels-last convolutions): the bins are the
        # fastest axis, so (h w, N) @ (N, 3) reads them without a layout copy.
        by_pixel = weights.permute(0, 2, 3, 1).reshape(batch, height * width, bins)
        totals = (by_pixel @ moments.transpose(1, 2)).transpose(1, 2).reshape(
            batch, 3, height, width
        )
    mean_shift = totals[:, 1:2] / totals[:, 0:1]
    variance = totals[:, 2:3] / totals[:, 0:1] - mean_shift**2
    return mean_shift + reference[:, :, None, None], variance.clamp_min(0).sqrt()


class HeadOutput(NamedTuple):
    """What every head returns (unpacks as ``depth, bin_edges, uncertainty``).

    Attributes:
        depth: (B, 1, h, w) metres, in the decoder's output grid.
        bin_edges: (B, N + 1) metres (a head without bins reports its depth range).
        uncertainty: (B, 1, h, w) metres, the per-pixel standard deviation.
    """

    depth: torch.Tensor
    bin_edges: torch.Tensor
    uncertainty: torch.Tensor


@dataclass(frozen=True)
class ZoneInputs:
    """The frame's zones as every head receives them (heads read what they need).

    Attributes:
        hypotheses: (B, Z, K) depth hypotheses per zone, metres (as the network sees
            them: divided by the frame's scale with ``zone_scale_norm``).
        valid: (B, Z) bool.
        rects: (B, Z, 4) (y0, x0, y1, x1) zone rectangles in network-input pixels.
        stride: network-input pixels per feature cell of the head's input.
        mean_sigma: optional (B, Z, 2) zone mean and sigma, metres; when None the zone
            mean is the hypotheses' mean.
        no_target: optional (B, Z) bool, zones that reported *no target* (nothing within
            the sensor's range); heads that do not use it ignore it.
        scale_m: optional (B,) metres per unit of ``hypotheses`` and ``mean_sigma`` (the
            frame's scale with ``zone_scale_norm``; None: they are in metres).
        targets: optional (B, Z, T, 2) every target each zone reported, ``[distance,
            share]`` (distance in the units of ``hypotheses``, 0 where a slot is empty;
            target 0 is the primary reading); heads that do not use it ignore it.
    """

    hypotheses: torch.Tensor
    valid: torch.Tensor
    rects: torch.Tensor
    stride: float
    mean_sigma: torch.Tensor | None = None
    no_target: torch.Tensor | None = None
    scale_m: torch.Tensor | None = None
    targets: torch.Tensor | None = None

    def mean_m(self, dtype: torch.dtype) -> torch.Tensor:
        """(B, Z) zone means in metres, as ``dtype``."""
        mean = self.mean_sigma[..., 0] if self.mean_sigma is not None else \
            self.hypotheses.mean(dim=2)
        return mean.to(dtype)


class DepthHead(nn.Module):
    """The interface of every depth head: :meth:`predict`.

    Subclasses implement ``predict`` (and ``forward``, the head's own computation);
    ``traceable`` is set by :meth:`deltar.models.DeltarNet.set_traceable` for export.
    """

    traceable: bool = False
    #: Whether :meth:`predict` reads ``ZoneInputs.no_target`` (an export then takes it).
    uses_no_target: bool = False
    #: Whether :meth:`predict` reads ``ZoneInputs.targets`` (several targets per zone).
    uses_targets: bool = False
    #: Whether the ONNX export may hand the head
    #: :class:`~deltar.models.affinity.FactoredDescriptors` as its features.
    reads_factored_descriptors: bool = False

    def predict(self, features: torch.Tensor, zones: ZoneInputs) -> HeadOutput:
        """Depth, bin edges and uncertainty from decoder features.

        Args:
            features: (B, C, h, w) decoder features.
            zones: the frame's zones (:class:`ZoneInputs`).

        Returns:
            The :class:`HeadOutput`, in metres, on the ``h x w`` grid.
        """
        raise NotImplementedError
