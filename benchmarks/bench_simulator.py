"""Benchmark: vectorised zone simulator vs a plain per-zone Python loop.

Simulates 64 zones on 480x640 depth maps (a real 7-Scenes frame from ../shared when
present, else a synthetic ramp), checks that both implementations agree, and prints the
time per frame and the speed-up.

    python benchmarks/bench_simulator.py [--repeats 20] [--batch 16] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the loop reference lives with the tests

from tests.sensor.loop_reference import simulate_zones_loop  # noqa: E402

from deltar.camera import ZJU_L5_INTRINSICS  # noqa: E402
from deltar.sensor import simulate_zones, training_zone_rects, zone_rects  # noqa: E402

FRAME = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes_redkitchen" / "frame-000000.depth.png"


def load_depth() -> tuple[np.ndarray, str]:
    """A 480x640 depth map in metres (0 = invalid) and where it came from."""
    if FRAME.is_file():
        import cv2

        raw = cv2.imread(str(FRAME), cv2.IMREAD_UNCHANGED)
        depth = raw.astype(np.float32) / 1000.0
        depth[(raw == 0) | (raw == 65535)] = 0.0
        return depth, str(FRAME)
    rows, cols = np.mgrid[0:480, 0:640]
    return (0.8 + 2.5 * cols / 640 + 0.3 * np.sin(rows / 30)).astype(np.float32), "synthetic"


def interleaved_times(fns: dict, repeats: int) -> dict:
    """Best and median CPU time of this process in seconds for each function.

    CPU time (not wall time) so that other processes on a shared machine do not count;
    with one torch thread it is the compute time. The functions run in turn within
    every repeat so that cache and frequency effects hit them alike; one warm-up each.
    """
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.process_time()
            fn()
            times[name].append(time.process_time() - start)
    return {name: (min(t), statistics.median(t)) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    depth, source = load_depth()
    layouts = {
        "aligned 8x8 x 56 px": training_zone_rects(480, 640, grid=8, zone_px=56),
        "calibrated 8x8 (ZJU intrinsics, ~63 px, past the image)": zone_rects(ZJU_L5_INTRINSICS),
    }
    print(f"depth: {source} ({depth.shape[0]}x{depth.shape[1]}), torch threads: "
          f"{args.threads}, repeats: {args.repeats}, process CPU time")
    for name, rects in layouts.items():
        out = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects))
        mean, sigma, valid, hist = simulate_zones_loop(depth, rects)
        agree = (np.array_equal(out.valid.numpy(), valid)
                 and np.array_equal(out.histogram.numpy(), hist)
                 and np.allclose(out.mean_m.numpy(), mean, atol=1e-6)
                 and np.allclose(out.sigma_m.numpy(), sigma, atol=1e-6))
        if not agree:
            raise SystemExit(f"{name}: vectorised and loop results differ")

        batch = torch.from_numpy(np.repeat(depth[None], args.batch, axis=0))
        single = torch.from_numpy(depth)
        boxes = torch.from_numpy(rects)
        times = interleaved_times({
            "loop": lambda rects=rects: simulate_zones_loop(depth, rects),
            "single": lambda boxes=boxes, single=single: simulate_zones(single, boxes),
            "batch": lambda boxes=boxes, batch=batch: simulate_zones(batch, boxes),
        }, args.repeats)
        loop_best, loop_median = times["loop"]
        print(f"\n{name}: {int(valid.sum())}/64 valid zones, results agree")
        print("  ms per frame (best / median)       speed-up vs loop (best / median)")
        print(f"  per-zone loop          {loop_best * 1e3:7.2f} / {loop_median * 1e3:7.2f}")
        for label, key, frames in (("vectorised, 1 frame", "single", 1),
                                   (f"vectorised, batch {args.batch}", "batch", args.batch)):
            best, median = (t / frames for t in times[key])
            print(f"  {label:<22} {best * 1e3:7.2f} / {median * 1e3:7.2f}       "
                  f"x{loop_best / best:.1f} / x{loop_median / median:.1f}")

if __name__ == "__main__":
    main()
