"""Latency / memory / FLOP benchmark of a preset, and the official-parity check of a fixture.

Latency alone does not compare across machines; :func:`benchmark_preset` therefore also
counts the forward pass's floating-point operations (torch's ``FlopCounterMode``:
2 per multiply-add of convolutions and matrix products; element-wise work is not
counted) and measures, in the same process and with the same threads, the rate of a
large float32 matrix product. The achieved fraction of that rate says how well the
network uses the machine.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from deltar.contract import normalise_image
from deltar.io.torch_file import read_torch_file
from deltar.models.official import load_official_weights
from deltar.models.optimize import prepare_for_inference
from deltar.models.presets import create_model

#: Tolerances of the official parity check, metres.
DEPTH_TOLERANCE_M = 1e-3
EDGE_TOLERANCE_M = 1e-4


def _status_mb(field: str) -> float | None:
    """A memory field of /proc/self/status (e.g. ``VmHWM``), MB; None where unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _peak_rss_mb() -> float | None:
    """Peak resident memory of this process (VmHWM), MB; None where unavailable."""
    return _status_mb("VmHWM")


def _current_rss_mb() -> float | None:
    return _status_mb("VmRSS")


def _reset_peak_rss() -> bool:
    """Reset VmHWM to the current RSS (Linux: write 5 to clear_refs); True on success."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def synthetic_inputs(height: int, width: int, batch: int, grid: int = 8, seed: int = 0):
    """Random inputs of the network's layout: an 8x8 grid of valid zones over the centre.

    Returns:
        (image (B, 3, H, W), hypotheses (B, Z, 16) metres, rects (B, Z, 4) px, valid (B, Z)).
    """
    generator = torch.Generator().manual_seed(seed)
    image = torch.randn(batch, 3, height, width, generator=generator)
    zones = grid * grid
    hypotheses = torch.rand(batch, zones, 16, generator=generator).sort(dim=2).values * 3 + 0.3
    side = min(height, width) * 0.9 / grid
    top, left = (height - side * grid) / 2, (width - side * grid) / 2
    rows, cols = torch.meshgrid(torch.arange(grid), torch.arange(grid), indexing="ij")
    y0 = top + rows.flatten() * side
    x0 = left + cols.flatten() * side
    rects = torch.stack([y0, x0, y0 + side, x0 + side], dim=1).float()
    return image, hypotheses, rects.expand(batch, zones, 4).clone(), torch.ones(
        batch, zones, dtype=torch.bool
    )


def count_gflop(model: torch.nn.Module, inputs: tuple) -> float:
    """Floating-point operations of one ``model(*inputs)`` call, in GFLOP (1e9).

    Counted by ``torch.utils.flop_counter.FlopCounterMode``: 2 per multiply-add of
    convolutions, matrix products and attention; element-wise operations, softmax and
    normalisation are not counted.

    Args:
        model: the network as built (the benchmark counts before the inference
            rewrites, whose zero-led kernels would add multiplications by zero).
        inputs: its positional inputs.
    """
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.inference_mode(), counter:
        model(*inputs)
    return counter.get_total_flops() / 1e9


def matmul_gflop_s(size: int = 2048, repeats: int = 3) -> float:
    """Best rate of a (size x size) @ (size x size) float32 product, GFLOP/s (2 size^3 FLOP).

    Runs with the current torch thread count; a reference for how fast this machine
    multiplies dense float32 matrices right now.

    Args:
        size: matrix side (2048: 17.2 GFLOP per product).
        repeats: timed products after one warm-up; the fastest counts.
    """
    if size < 1 or repeats < 1:
        raise ValueError("size and repeats must be >= 1")
    generator = torch.Generator().manual_seed(0)
    left = torch.randn(size, size, generator=generator)
    right = torch.randn(size, size, generator=generator)
    out = torch.empty(size, size)
    with torch.inference_mode():
        torch.mm(left, right, out=out)
        best = math.inf
        for _ in range(repeats):
            start = time.perf_counter()
            torch.mm(left, right, out=out)
            best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best / 1e9


def benchmark_preset(
    preset: str,
    height: int,
    width: int,
    batch: int = 1,
    threads: int = 2,
    repeats: int = 10,
    warmup: int = 2,
    optimize: bool = True,
    fold_encoder: bool = True,
    channels_last: bool = True,
    matmul_size: int = 2048,
    overrides: dict | None = None,
) -> dict:
    """Time the forward pass of a preset (random weights) under ``torch.inference_mode``.

    Args:
        preset: model preset name.
        height: input height, pixels (divisible by 32).
        width: input width, pixels (divisible by 32).
        batch: batch size.
        threads: torch intra-op threads.
        repeats: timed runs (the median and minimum are reported).
        warmup: untimed runs first.
        optimize: apply :func:`~deltar.models.optimize.prepare_for_inference`.
        fold_encoder: also fold the image encoder's batch norms.
        channels_last: channels-last decoder and head (see
            :func:`~deltar.models.optimize.prepare_for_inference`).
        matmul_size: side of the float32 matrix product timed (best of three, before
            and after the forward runs) as this machine's reference rate; 0 skips it
            (and the fraction).
        overrides: constructor arguments replacing the preset's (as
            :func:`~deltar.models.presets.create_model` takes them), e.g. a decoder
            variant or ``design_size``.

    Returns:
        dict with preset, size ("HxW"), batch, threads, latency_ms_median,
        latency_ms_min, cpu_ms_per_run (process CPU time per forward summed over
        threads: less sensitive to other processes than latency), peak_mem_mb
        (peak resident memory during the runs, warm-up included, above the resident
        memory before the first; None if unavailable), params_m (millions), gflop (counted
        FLOP of one forward of the whole batch, 1e9), gflop_s (gflop over the
        fastest forward), matmul_gflop_s (the reference product's best rate; None if
        skipped), matmul_fraction (gflop_s / matmul_gflop_s: best against best),
        overrides, load_avg_1min (system load when the run ended, for context).
    """
    if repeats < 1 or warmup < 0:
        raise ValueError("repeats must be >= 1 and warmup >= 0")
    if matmul_size < 0:
        raise ValueError(f"matmul_size must be >= 0, got {matmul_size}")
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        reference = matmul_gflop_s(matmul_size) if matmul_size else None
        result = _timed_runs(preset, height, width, batch, threads, repeats, warmup, optimize,
                             fold_encoder, channels_last, overrides or {})
        if reference is not None:
            reference = max(reference, matmul_gflop_s(matmul_size))
    finally:
        torch.set_num_threads(previous_threads)
    result["matmul_gflop_s"] = None if reference is None else round(reference, 1)
    result["matmul_fraction"] = (None if reference is None
                                 else round(result["gflop_s"] / reference, 3))
    return result


def _timed_runs(preset, height, width, batch, threads, repeats, warmup, optimize, fold_encoder,
                channels_last, overrides):
    """The body of :func:`benchmark_preset` (thread count already set)."""
    torch.manual_seed(0)
    model = create_model(preset, **overrides).eval()
    inputs = synthetic_inputs(height, width, batch)
    # Counted before the inference rewrites: the network's own arithmetic (the
    # zero-led kernels of SymmetricSameConv2d would add multiplications by zero).
    gflop = count_gflop(model, inputs)
    if optimize:
        prepare_for_inference(model, fold_encoder=fold_encoder, channels_last=channels_last)
    with torch.inference_mode():
        # Memory from before the first forward: after warm-up the allocator keeps the
        # activations' memory, and the timed runs alone would add nothing.
        rss_before = _current_rss_mb()
        peak_resettable = _reset_peak_rss()
        for _ in range(warmup):
            model(*inputs)
        times = []
        cpu_start = time.process_time()
        for _ in range(repeats):
            start = time.perf_counter()
            model(*inputs)
            times.append((time.perf_counter() - start) * 1000.0)
        cpu_ms = (time.process_time() - cpu_start) * 1000.0 / repeats
    peak = _peak_rss_mb()
    peak_mem = None
    if peak is not None and rss_before is not None and peak_resettable:
        peak_mem = round(max(0.0, peak - rss_before), 1)
    try:
        load = round(float(Path("/proc/loadavg").read_text().split()[0]), 2)
    except (OSError, ValueError):
        load = None
    return {
        "preset": preset,
        "size": f"{height}x{width}",
        "batch": batch,
        "threads": threads,
        "latency_ms_median": round(statistics.median(times), 1),
        "latency_ms_min": round(min(times), 1),
        "cpu_ms_per_run": round(cpu_ms, 1),
        "peak_mem_mb": peak_mem,
        "params_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
        "gflop": round(gflop, 3),
        "gflop_s": round(gflop / (min(times) / 1000.0), 2),
        "optimized": optimize,
        "encoder_folded": bool(optimize and fold_encoder),
        "channels_last": bool(optimize and channels_last),
        "overrides": {key: list(value) if isinstance(value, tuple) else value
                      for key, value in overrides.items()},
        "load_avg_1min": load,
    }


@dataclass
class ParityResult:
    """Largest errors of one fixture case against the release's outputs (metres)."""

    name: str
    depth_max_error_m: float
    edges_max_error_m: float

    @property
    def passed(self) -> bool:
        """Both errors within :data:`DEPTH_TOLERANCE_M` / :data:`EDGE_TOLERANCE_M`."""
        return (
            math.isfinite(self.depth_max_error_m)
            and self.depth_max_error_m <= DEPTH_TOLERANCE_M
            and self.edges_max_error_m <= EDGE_TOLERANCE_M
        )


def check_official_fixture(path: str | Path, threads: int = 2) -> list[ParityResult]:
    """Run ``deltar-official`` with a fixture's weights on each of its cases.

    The fixture layout is that of ``official_parity_fixture_v2.pt``: ``state_dict`` and
    ``cases`` (``image_rgb_uint8`` (H, W, 3), ``zone_samples_icdf16`` (Z, K),
    ``zone_rects_yxyx`` (Z, 4), ``zone_valid`` (Z,), ``expected_bin_edges`` (N + 1,),
    ``expected_depth_half_res`` (H / 2, W / 2)). Its weights are well conditioned, so
    the result does not depend on the CPU or the thread count (errors ~1e-5 m).

    Args:
        path: fixture file.
        threads: torch threads for the check (restored afterwards).

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file does not have the fixture layout.
    """
    path = Path(path)
    # The fixture holds plain tensors, strings and lists; no code objects.
    fixture = read_torch_file(path, "fixture", weights_only=False)
    if not isinstance(fixture, dict) or "state_dict" not in fixture or "cases" not in fixture:
        raise ValueError(f"{path}: expected a dict with 'state_dict' and 'cases'")
    model = create_model("deltar-official")
    load_official_weights(model, fixture["state_dict"])
    model.eval()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _compare_cases(model, fixture["cases"], path)
    finally:
        torch.set_num_threads(previous_threads)


def _compare_cases(model, cases, path: Path) -> list[ParityResult]:
    """Largest errors of ``model`` against each case's expected outputs."""
    results = []
    required = ("image_rgb_uint8", "zone_samples_icdf16", "zone_rects_yxyx", "zone_valid",
                "expected_bin_edges", "expected_depth_half_res")
    for index, case in enumerate(cases):
        missing = [key for key in required if key not in case]
        if missing:
            raise ValueError(f"{path}: case {index} lacks {missing}")
        with torch.inference_mode():
            out = model(
                torch.from_numpy(normalise_image(np.asarray(case["image_rgb_uint8"])))[None],
                torch.as_tensor(case["zone_samples_icdf16"]).float()[None],
                torch.as_tensor(case["zone_rects_yxyx"]).float()[None],
                torch.as_tensor(case["zone_valid"]).bool()[None],
            )
        expected_depth = torch.as_tensor(case["expected_depth_half_res"]).float()
        expected_edges = torch.as_tensor(case["expected_bin_edges"]).float()
        depth_error = (out["depth"][0, 0] - expected_depth).abs().max().item()
        edge_error = (out["bin_edges"][0] - expected_edges).abs().max().item()
        results.append(ParityResult(str(case.get("name", f"case {index}")), depth_error,
                                    edge_error))
    return results
