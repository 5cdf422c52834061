"""Benchmark: decoder shapes for CPU, counted GFLOP, latency and fraction of the matmul rate.

Builds ``deltar-lite`` (random weights, every inference optimisation on) with each
candidate decoder shape and each backbone, and times them in alternating rounds (so
that load from other processes hits all alike); each round is one ``benchmark_preset``
call with its own float32 matmul reference. Prints, per candidate, the counted GFLOP,
the fastest forward over all rounds, and the achieved fraction of the best matmul rate.

    python benchmarks/bench_decoder_shapes.py [--size 256x320] [--threads 2] [--rounds 3] \
        [--backbones tf_mobilenetv3_large_minimal_100 tf_efficientnet_lite0]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from deltar.io.atomic import write_text_atomic
from deltar.models.benchmark import benchmark_preset

#: Decoder overrides compared, by name (``release`` = the preset's own decoder).
CANDIDATES: dict[str, dict] = {
    "release": {},
    "separable": {"decoder_block": "separable"},
    "conv, 1 conv at strides 4 and 2, 1x1 out": {"decoder_convs": (2, 2, 1, 1),
                                                 "decoder_out_kernel": 1},
    "separable, 1 conv at strides 4 and 2, 1x1 out": {"decoder_block": "separable",
                                                      "decoder_convs": (2, 2, 1, 1),
                                                      "decoder_out_kernel": 1},
    "wide coarse (192..16), 1 conv at 4 and 2, 1x1 out": {
        "decoder_channels": (192, 192, 96, 32, 16), "decoder_convs": (2, 2, 1, 1),
        "decoder_out_kernel": 1},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="256x320")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backbones", nargs="+",
                        default=["tf_mobilenetv3_large_minimal_100", "tf_efficientnet_lite0"])
    parser.add_argument("--json", default=None, help="also write all rows to this file")
    args = parser.parse_args()
    height, width = (int(v) for v in args.size.split("x"))
    runs = [(backbone, name) for backbone in args.backbones for name in CANDIDATES]
    best: dict[tuple[str, str], dict] = {}
    matmul = 0.0
    for _ in range(args.rounds):
        for backbone, name in runs:
            overrides = {"backbone": backbone, "design_size": (height, width),
                         **CANDIDATES[name]}
            result = benchmark_preset("deltar-lite", height, width, threads=args.threads,
                                      repeats=args.repeats, warmup=1, overrides=overrides)
            matmul = max(matmul, result["matmul_gflop_s"])
            key = (backbone, name)
            if key not in best or result["latency_ms_min"] < best[key]["latency_ms_min"]:
                best[key] = result
    print(f"deltar-lite decoder shapes at {args.size}, {args.threads} threads, "
          f"{args.rounds} alternating rounds of {args.repeats} forwards; best float32 matmul "
          f"(2048^3) {matmul:.1f} GFLOP/s; load average after {os.getloadavg()[0]:.2f}")
    print("| backbone | decoder | params (M) | GFLOP | ms (fastest) | GFLOP/s | fraction |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for (backbone, name), result in best.items():
        fraction = result["gflop_s"] / matmul
        rows.append({**result, "backbone": backbone, "candidate": name,
                     "fraction_of_best_matmul": round(fraction, 3)})
        print(f"| {backbone} | {name} | {result['params_m']:.2f} | {result['gflop']:.2f} | "
              f"{result['latency_ms_min']:.1f} | {result['gflop_s']:.1f} | {fraction:.0%} |")
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(rows, indent=2) + "\n", overwrite=False)


if __name__ == "__main__":
    main()
