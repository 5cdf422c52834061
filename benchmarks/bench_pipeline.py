"""Benchmark: end-to-end ``DepthEstimator.predict`` vs the bare network, PyTorch and ONNX.

End to end = ``DepthEstimator.predict`` on a decoded RGB image and its zone frame, as a
camera or a driver hands them over: zone placement + hypothesis sampling + network +
for plane-select networks (the bundled ``default``) the confidence blend with the
colorization fill that the estimator applies by default + resize to the input size;
"e2e from PNG" = the same with the PNG decode before it (a recording replayed from
files); "no blend" = from the image with ``blend=None`` (``--network-only``); bare = the
network call alone on prepared inputs. Presets run with random weights (speed does not
depend on them). Each ONNX model is exported first (not timed). Prints frames per second
(medians over the repeats; the runs alternate so that load from other processes hits
them alike), and per backend and size the network's counted GFLOP
(:func:`deltar.models.benchmark.count_gflop`: convolutions and matrix products) and its
rate as a fraction of a float32 matrix product's measured in the same process with the
same threads before and after the runs (:func:`deltar.models.benchmark.matmul_gflop_s`,
the better of the two): ``NN% of matmul`` = GFLOP / median bare network time / that rate.
``around ms`` is the time end to end spends beyond the bare network (median e2e minus
median bare), with and without the blend: a fixed cost a frame, so the e2e / bare ratio
falls when the network runs faster. ``stream fps`` is ``DepthEstimator.predict_stream``
over the same frame repeated (:data:`STREAM_FRAMES` a call), whose work around the
network overlaps the neighbouring frames' networks.
Two parts of end to end are also timed alone, in the same alternation: the PNG decode and
(for networks with the blend) the blend's colorization fill (``blend_fill``, milliseconds;
in ``predict`` it runs on a worker thread beside the network, or before a PyTorch network
whose threads take every core).

    python benchmarks/bench_pipeline.py [--threads 2] [--repeats 5] \
        [--presets deltar-lite deltar-official] [--sizes 240x320 480x640] \
        [--backends torch onnx] [--allow-spinning]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch

from deltar.export.onnx import export_onnx
from deltar.inference.estimator import DepthEstimator
from deltar.inference.onnx_runtime import OnnxDepthModel
from deltar.models import create_model
from deltar.models.benchmark import count_gflop, matmul_gflop_s
from deltar.models.checkpoint import load_checkpoint
from deltar.sensor.zone_frame import ZoneFrame
from deltar.weights import bundled_model_names, resolve_checkpoint

#: Frames per timed call of ``predict_stream``.
STREAM_FRAMES = 10


def _interleaved_medians(functions, repeats: int, warmup: int = 1) -> list[float]:
    """Median seconds of functions timed alternately, so machine load hits them alike."""
    for _ in range(warmup):
        for function in functions:
            function()
    times: list[list[float]] = [[] for _ in functions]
    for _ in range(repeats):
        for function, store in zip(functions, times, strict=True):
            start = time.perf_counter()
            function()
            store.append(time.perf_counter() - start)
    return [statistics.median(t) for t in times]


def _test_frame(height: int, width: int, seed: int = 0) -> tuple[bytes, ZoneFrame]:
    """A textured test image encoded as PNG, and an 8x8 zone frame with 3 invalid zones."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 255, (height // 8, width // 8, 3)).astype(np.float32)
    image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    ok, png = cv2.imencode(".png", np.clip(image, 0, 255).astype(np.uint8))
    assert ok
    valid = np.ones((8, 8), bool)
    valid.flat[[3, 17, 60]] = False
    frame = ZoneFrame(np.where(valid, rng.uniform(0.5, 3.5, (8, 8)), 0.0),
                      np.where(valid, rng.uniform(0.01, 0.1, (8, 8)), 0.0), valid)
    return png.tobytes(), frame


def _decode(png: bytes) -> np.ndarray:
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def bench(preset: str, size: tuple[int, int], backend: str, threads: int, repeats: int,
          workdir: Path, allow_spinning: bool = False) -> dict:
    """Frames per second of the bare network and of predict() for one configuration."""
    height, width = size
    torch.manual_seed(0)
    if preset in bundled_model_names() or preset.endswith(".pt"):
        # A bundled model or a checkpoint file: the real network, trained weights.
        model = load_checkpoint(resolve_checkpoint(preset))[0]
    else:
        model = create_model(preset).eval()
    png, frame = _test_frame(height, width)
    # Counted on the network as built, before any inference rewrite of the estimator.
    counting = DepthEstimator(model, fold_batch_norms=False).prepare([_decode(png)], [frame])
    gflop = count_gflop(model, tuple(torch.from_numpy(counting[name]) for name in
                                     ("image", "hypotheses", "zone_rects", "zone_valid")))
    if backend == "onnx":
        path = workdir / f"{preset}-{height}x{width}.onnx"
        start = time.perf_counter()
        export_onnx(model, path, height, width, overwrite=True)
        print(f"  exported {path.name} in {time.perf_counter() - start:.1f} s", flush=True)
        onnx_model = OnnxDepthModel(path, num_threads=threads, allow_spinning=allow_spinning)
        estimator = DepthEstimator(onnx_model=onnx_model, weights=f"onnx {path}")
    else:
        estimator = DepthEstimator(model, weights=f"{preset} (random)")
    inputs = estimator.prepare([_decode(png)], [frame])
    blend = estimator.blend

    image = _decode(png)

    def network_only():
        estimator.blend = None
        try:
            estimator.predict(image, frame)
        finally:
            estimator.blend = blend

    rects = inputs["image_rects"][0]
    grid = tuple(side // 2 for side in inputs["network_size"])  # as predict asks for it

    def fill_only():
        if blend is not None:
            estimator.blend_fill_for(image, frame, rects, out_size=grid)

    stream_pairs = [(image, frame)] * STREAM_FRAMES

    def stream():
        for _ in estimator.predict_stream(stream_pairs):
            pass

    matmul = matmul_gflop_s()
    bare, full, from_png, plain, decode, fill, streamed = _interleaved_medians(
        [lambda: estimator.run_network(inputs), lambda: estimator.predict(image, frame),
         lambda: estimator.predict(_decode(png), frame), network_only, lambda: _decode(png),
         fill_only, stream], repeats)
    streamed /= STREAM_FRAMES
    matmul = max(matmul, matmul_gflop_s())
    return {"preset": preset, "size": f"{height}x{width}", "backend": backend,
            "blend": blend is not None, "bare_fps": 1.0 / bare, "e2e_fps": 1.0 / full,
            "png_fps": 1.0 / from_png, "no_blend_fps": 1.0 / plain,
            "overhead": full / bare - 1.0, "e2e_ratio": bare / full,
            "around_ms": 1e3 * (full - bare), "around_no_blend_ms": 1e3 * (plain - bare),
            "stream_fps": 1.0 / streamed, "stream_ratio": bare / streamed,
            "png_ratio": bare / from_png, "gflop": gflop, "matmul_gflop_s": matmul,
            "matmul_fraction": gflop / bare / matmul, "decode_ms": 1e3 * decode,
            "fill_ms": 1e3 * fill if blend is not None else float("nan")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--presets", nargs="+", default=["deltar-lite", "deltar-official"],
                        help="presets (random weights), bundled model names ('default') or "
                             "checkpoint files")
    parser.add_argument("--sizes", nargs="+", default=["240x320", "480x640"])
    parser.add_argument("--backends", nargs="+", default=["torch", "onnx"])
    parser.add_argument("--allow-spinning", action="store_true",
                        help="let onnxruntime's idle threads busy-wait (its own default)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore")
    print(f"threads={args.threads} repeats={args.repeats} torch={torch.__version__} "
          f"load average={os.getloadavg()}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for size_text in args.sizes:
                size = tuple(int(v) for v in size_text.split("x"))
                for backend in args.backends:
                    print(f"{preset} {size_text} {backend} ...", flush=True)
                    rows.append(bench(preset, size, backend, args.threads, args.repeats,
                                      Path(tmp), args.allow_spinning))
    print(f"\nload average after: {os.getloadavg()}")
    header = f"{'preset':<16} {'size':>8} {'backend':>8} {'bare fps':>9} {'e2e fps':>8} " \
             f"{'blend':>6} {'e2e no blend':>13} {'overhead':>9} {'e2e/bare':>9} " \
             f"{'around ms':>9} {'(no blend)':>10} {'stream fps':>10} {'/bare':>6} " \
             f"{'from PNG fps':>13} {'/bare':>6} " \
             f"{'GFLOP':>6} {'network rate':>30} {'decode ms':>9} {'fill ms':>7}"
    print(header)
    print("-" * len(header))
    for r in rows:
        print(f"{r['preset']:<16} {r['size']:>8} {r['backend']:>8} {r['bare_fps']:>9.2f} "
              f"{r['e2e_fps']:>8.2f} {'yes' if r['blend'] else 'no':>6} "
              f"{r['no_blend_fps']:>13.2f} {100 * r['overhead']:>8.1f}% "
              f"{r['e2e_ratio']:>8.2f}x {r['around_ms']:>9.2f} {r['around_no_blend_ms']:>10.2f} "
              f"{r['stream_fps']:>10.2f} {r['stream_ratio']:>5.2f}x "
              f"{r['png_fps']:>13.2f} {r['png_ratio']:>5.2f}x "
              f"{r['gflop']:>6.2f} "
              f"{r['gflop'] / (1.0 / r['bare_fps']):>6.1f} GFLOP/s, "
              f"{100 * r['matmul_fraction']:>3.0f}% of matmul "
              f"({r['matmul_gflop_s']:.0f}) {r['decode_ms']:>9.2f} {r['fill_ms']:>7.2f}")


if __name__ == "__main__":
    main()
