"""Test-time flip averaging: a network run on the inputs and on their left-right mirror."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

#: ``run(image, hypotheses, zone_rects, zone_valid[, zone_no_target[, zone_targets]])
#: -> (depth, uncertainty)``; the optional arguments are passed only when given.
NetworkRun = Callable[..., "tuple[torch.Tensor, torch.Tensor]"]


def flip_averaged(run: NetworkRun, image: torch.Tensor, hypotheses: torch.Tensor,
                  zone_rects: torch.Tensor, zone_valid: torch.Tensor,
                  zone_no_target: torch.Tensor | None = None,
                  zone_targets: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Average of ``run`` on the inputs and on their left-right mirror, in one batch.

    The mirrored pass sees the mirrored image, the zones in mirrored order (zone
    ``(r, c)`` becomes ``(r, n - 1 - c)``) and mirrored rectangles (columns ``[x0, x1)``
    become ``[w - x1, w - x0)``); its output is flipped back. The uncertainty is that of
    the equal mixture of the two per-pixel distributions (mean variance plus the
    variance of the two means).

    Args:
        run: the network call, e.g. a ``DeltarNet`` wrapped to return
            (depth, uncertainty).
        image: (B, 3, h, w) normalised network input.
        hypotheses: (B, Z, K) metres; Z = n * n zones, row-major.
        zone_rects: (B, Z, 4) (y0, x0, y1, x1) in pixels of ``image``.
        zone_valid: (B, Z) bool.
        zone_no_target: optional (B, Z) bool no-target flags, mirrored like the zones.
        zone_targets: optional (B, Z, T, 2) every target of each zone, mirrored like the
            zones.

    Returns:
        (depth, uncertainty), each (B, 1, h', w') metres in ``run``'s output grid.

    Raises:
        ValueError: the zone count is not a square grid.
    """
    import torch

    from deltar.sensor.geometry import mirror_zone_rects

    zones = hypotheses.shape[1]
    grid = math.isqrt(zones)
    if grid * grid != zones:
        raise ValueError(f"hypotheses: zone count Z={zones} is not a square grid")
    order = torch.arange(zones).reshape(grid, grid).flip(1).flatten().to(zone_rects.device)
    width = image.shape[-1]
    mirrored_rects = torch.from_numpy(np.stack([
        mirror_zone_rects(r, width, grid) for r in zone_rects.cpu().numpy()])
    ).to(zone_rects.device)
    flags = tuple(torch.cat([extra, extra[:, order]]) for extra in (zone_no_target, zone_targets)
                  if extra is not None)
    if zone_no_target is None and zone_targets is not None:
        raise ValueError("zone_targets needs zone_no_target (pass all-False flags)")
    depth, spread = run(torch.cat([image, image.flip(-1)]),
                        torch.cat([hypotheses, hypotheses[:, order]]),
                        torch.cat([zone_rects, mirrored_rects]),
                        torch.cat([zone_valid, zone_valid[:, order]]), *flags)
    batch = image.shape[0]
    depth_a, depth_b = depth[:batch], depth[batch:].flip(-1)
    spread_a, spread_b = spread[:batch], spread[batch:].flip(-1)
    mean = 0.5 * (depth_a + depth_b)
    variance = 0.5 * (spread_a**2 + spread_b**2) + 0.25 * (depth_a - depth_b) ** 2
    return mean, variance.sqrt()
