"""Benchmark the model presets (latency, memory, GFLOP, matmul fraction); one JSON per run.

Usage::

    python benchmarks/bench_models.py --out-dir bench_results \\
        --runs deltar-official:480x640 deltar-lite:256x320 deltar-lite:224x320

Each run is the same measurement as ``deltar bench`` (random weights, inference mode,
median and fastest of repeated runs after warm-up, counted GFLOP, and the achieved
fraction of a 2048^3 float32 matmul timed in the same process). Other processes on the
machine change the numbers; the system load is recorded in each result.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from deltar.io.atomic import write_text_atomic
from deltar.models.benchmark import benchmark_preset


def main(argv: list[str] | None = None) -> None:
    """Run the benchmarks given on the command line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", default=["deltar-official:480x640",
                                                      "deltar-lite:256x320"],
                        help="PRESET:HxW entries")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--out-dir", type=Path, default=None,
                        help="folder for one JSON per run (not overwritten)")
    args = parser.parse_args(argv)
    for run in args.runs:
        preset, _, size = run.partition(":")
        height, width = (int(v) for v in size.lower().split("x"))
        result = benchmark_preset(preset, height, width, args.batch, args.threads,
                                  args.repeats, args.warmup)
        print(json.dumps(result))
        if args.out_dir is not None:
            name = f"{preset}_{height}x{width}_b{args.batch}_t{args.threads}.json"
            write_text_atomic(args.out_dir / name, json.dumps(result, indent=2) + "\n",
                              overwrite=False)


if __name__ == "__main__":
    main()
