"""Write tiny sets in the THDR3K layout (``<root>_rgb.jpg``, ``_depth.png``, ``_tof.json``)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from deltar.sensor.cnh import CNHConfig

STALE_MM = 300.0  # what a zone without a target still reports (the sensor does not clear it)


def zone_truth(seed: int) -> tuple[np.ndarray, tuple[int, int]]:
    """(8, 8) zone depths in image orientation (whole millimetres) and one no-target zone.

    The no-target zone and its eight neighbours share one depth, so a reader that masks
    the zone lets the ``nearest`` baseline fill it exactly; its stale reading is far off.
    """
    rng = np.random.default_rng(seed)
    means = np.round(rng.uniform(0.8, 3.5, (8, 8)), 3)
    r, c = 3, 4
    means[r - 1:r + 2, c - 1:c + 2] = means[r, c]
    return means, (r, c)


def write_sample(root: Path, seed: int, height: int = 240, width: int = 320,
                 config: CNHConfig | None = None, write_config: bool = False) -> np.ndarray:
    """Write one sample whose ground truth is constant in each zone; return the (8, 8) truth.

    The zones cover the ``height`` x ``height`` square from x = 60 / 640 of the width
    (THDR3K's layout scaled); the columns outside repeat the nearest zone's depth. The
    ToF file holds the values in the sensor's order: the image grid turned back by 90
    degrees (``rot90(k=-1)``).
    """
    cfg = config or CNHConfig()
    means, (r, c) = zone_truth(seed)
    side = height // 8
    block = np.kron(means, np.ones((side, side)))
    pad = round(60 * width / 640)
    depth = np.pad(block, ((0, 0), (pad, width - height - pad)), mode="edge")
    rng = np.random.default_rng(seed + 1000)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    targets = np.ones((8, 8), dtype=int)
    targets[r, c] = 0
    distance = means * 1000.0
    distance[r, c] = STALE_MM
    edges = cfg.edges_m()
    peak = np.clip(np.searchsorted(edges, means.reshape(-1)) - 1, 0, cfg.num_bins - 1)
    bins = rng.uniform(-0.05, 0.02, (64, cfg.num_bins))
    bins[np.arange(64), peak] += 5.0
    sensor = {  # image grid -> sensor order: undo rot90(k=1)
        "distance_mm": np.rot90(distance, k=-1).reshape(-1).tolist(),
        "nb_target_detected": np.rot90(targets, k=-1).reshape(-1).tolist(),
        "cnh_data": {"bin_values": np.rot90(bins.reshape(8, 8, -1), k=-1, axes=(0, 1))
                     .reshape(64, -1).tolist()},
    }
    if write_config:
        sensor["cnh_data"].update(start_bin=cfg.start_bin, num_bins=cfg.num_bins,
                                  sub_sample=cfg.sub_sample)
    root.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root.with_name(root.name + "_rgb.jpg")), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(root.with_name(root.name + "_depth.png")),
                np.round(depth * 1000).astype(np.uint16))
    root.with_name(root.name + "_tof.json").write_text(json.dumps(sensor), encoding="utf-8")
    return means


def write_set(folder: Path, train: int = 3, test: int = 2, **kwargs) -> Path:
    """A set with ``train`` and ``test`` samples under ``folder/scene_*``; returns the list."""
    entries: dict[str, list] = {"train": [], "test": []}
    for i in range(train + test):
        split = "train" if i < train else "test"
        rel = f"scene_{split}/{i:06d}"
        write_sample(folder / rel, seed=i, **kwargs)
        entries[split].append({"filename": rel})
    path = folder / "thdr3k_split.json"
    path.write_text(json.dumps(entries), encoding="utf-8")
    return path
