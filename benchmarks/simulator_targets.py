"""Several targets per zone in the zone simulator: its cost, and how often a zone has
a second target.

``speed``: process CPU time per frame of ``simulate_zones`` (a batch and a single
frame) and of ``simulate_zone_frame`` at ``max_targets`` 1 and 4, on the 480x640 frame
of benchmarks/bench_simulator.py with the calibrated ZJU-L5 8x8 layout (one torch
thread; the variants alternate within every repeat).

``share``: on ZJU-L5-layout sets (``<sets>/<scene>/data.json``), every frame simulated
with ``max_targets=4`` from its ground-truth depth and its zone rectangles; per scene,
the valid zones (primary reading) and the share of them with a second (third) target.

    python benchmarks/simulator_targets.py speed [--repeats 20] [--batch 16]
    python benchmarks/simulator_targets.py share --sets ../cs/s10/sets [--scenes a b ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_simulator import interleaved_times, load_depth

from deltar.camera import ZJU_L5_INTRINSICS
from deltar.sensor import simulate_zone_frame, simulate_zones, zone_rects

SCENES = ("kitchen", "shelf", "office", "totes", "icl", "lab_table", "floor", "table",
          "cabinet", "makerspace")


def speed(repeats: int, batch_size: int) -> None:
    torch.set_num_threads(1)
    depth, source = load_depth()
    rects = zone_rects(ZJU_L5_INTRINSICS)
    single = torch.from_numpy(depth)
    batch = torch.from_numpy(np.repeat(depth[None], batch_size, axis=0))
    boxes = torch.from_numpy(rects)
    fns = {}
    for targets in (1, 4):
        fns[f"batch {batch_size}, T={targets}"] = (
            batch_size, lambda t=targets: simulate_zones(batch, boxes, max_targets=t))
        fns[f"1 frame, T={targets}"] = (
            1, lambda t=targets: simulate_zones(single, boxes, max_targets=t))
        fns[f"numpy frame, T={targets}"] = (
            1, lambda t=targets: simulate_zone_frame(depth, rects, max_targets=t))
    times = interleaved_times({name: fn for name, (_, fn) in fns.items()}, repeats)
    out = simulate_zones(single, boxes, max_targets=4)
    print(f"depth: {source} ({depth.shape[0]}x{depth.shape[1]}), calibrated ZJU-L5 8x8 "
          f"layout, torch threads 1, repeats {repeats}, process CPU time; "
          f"{int(out.valid.sum())} valid zones, {int(out.target_valid[:, 1].sum())} with a "
          "second target")
    print("  ms per frame (best / median)")
    for name, (frames, _) in fns.items():
        best, median = (t / frames for t in times[name])
        print(f"  simulate_zones {name:<22}" if not name.startswith("numpy") else
              f"  simulate_zone_frame {name[6:]:<17}", end="")
        print(f" {best * 1e3:7.2f} / {median * 1e3:7.2f}")


def share(sets: Path, scenes: list[str]) -> None:
    from deltar.data.zju_l5 import ZJUL5Dataset

    print(f"{'scene':<11} {'frames':>6} {'valid zones':>11} {'2nd target':>11} {'share':>7} "
          f"{'3rd target':>11}")
    totals = np.zeros(4, dtype=np.int64)
    for scene in scenes:
        dataset = ZJUL5Dataset(sets / scene / "data.json")
        counts = np.zeros(4, dtype=np.int64)  # frames, valid zones, >= 2 targets, >= 3
        for index in range(len(dataset)):
            sample = dataset[index]
            zones = simulate_zones(sample.depth_m, sample.zone_rects.astype(np.float32),
                                   max_targets=4)
            valid = zones.target_valid.numpy()
            counts += [1, valid[:, 0].sum(), (valid[:, 0] & valid[:, 1]).sum(),
                       (valid[:, 0] & valid[:, 2]).sum()]
        totals += counts
        print(f"{scene:<11} {counts[0]:6d} {counts[1]:11d} {counts[2]:11d} "
              f"{100 * counts[2] / max(counts[1], 1):6.1f}% {counts[3]:11d}", flush=True)
    print(f"{'all':<11} {totals[0]:6d} {totals[1]:11d} {totals[2]:11d} "
          f"{100 * totals[2] / max(totals[1], 1):6.1f}% {totals[3]:11d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    speed_args = sub.add_parser("speed")
    speed_args.add_argument("--repeats", type=int, default=20)
    speed_args.add_argument("--batch", type=int, default=16)
    share_args = sub.add_parser("share")
    share_args.add_argument("--sets", type=Path, required=True)
    share_args.add_argument("--scenes", nargs="+", default=list(SCENES))
    args = parser.parse_args()
    if args.command == "speed":
        speed(args.repeats, args.batch)
    else:
        share(args.sets, args.scenes)


if __name__ == "__main__":
    main()
