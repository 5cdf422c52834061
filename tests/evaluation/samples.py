"""Tiny ZJU-L5-layout frames for the evaluation-loop and CLI tests."""

from __future__ import annotations

import numpy as np

from deltar.data.zju_l5 import ZJUL5Sample

HEIGHT, WIDTH, GRID, ZONE = 32, 48, 4, 8.0


def make_sample(name: str, seed: int, *, empty_gt: bool = False) -> ZJUL5Sample:
    """A 32 x 48 frame whose ground truth is constant in each of 4 x 4 zones of 8 px.

    The zones cover the middle 32 x 32 pixels (columns 8..39); columns outside repeat the
    nearest zone's depth, so the ``nearest`` baseline reproduces the ground truth exactly.
    """
    rng = np.random.default_rng(seed)
    means = rng.uniform(0.5, 3.0, (GRID, GRID))
    block = np.kron(means, np.ones((int(ZONE), int(ZONE))))
    depth = np.pad(block, ((0, 0), (8, 8)), mode="edge").astype(np.float32)
    if empty_gt:
        depth[:] = 0.0
    rects = np.array([[r * ZONE, 8 + c * ZONE, (r + 1) * ZONE, 8 + (c + 1) * ZONE]
                      for r in range(GRID) for c in range(GRID)], dtype=np.float32)
    mean_sigma = np.stack([means.reshape(-1), np.full(GRID * GRID, 0.05)], axis=1)
    rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    return ZJUL5Sample(rgb=rgb, depth_m=depth, zone_mean_sigma=mean_sigma, zone_rects=rects,
                       zone_valid=np.ones(GRID * GRID, bool), name=name)
