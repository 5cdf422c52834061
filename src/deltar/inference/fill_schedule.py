"""When and where the confidence blend's fill runs: beside the network or before it.

The fill (:func:`deltar.inference.blend.blend_fill`) needs only the image and the zones,
so the estimator starts it (:func:`start_blend_fill`, :func:`start_frame_fills`) once the
zones are placed, before the images are resized and the network runs. It runs on one
worker thread shared by all estimators, beside the network, or at once on the calling
thread; :func:`fill_beside_network` says which suits the network's backend and the cores
there are. Its tasks run in the order they were started, so estimators predicting on
several threads at once queue their frames' fills there.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from deltar.inference.blend import blend_fill
from deltar.io.resources import cpu_count

if TYPE_CHECKING:
    from deltar.sensor.zone_frame import ZoneFrame

_FILL_WORKER: ThreadPoolExecutor | None = None
_FILL_WORKER_LOCK = threading.Lock()


def _forget_worker_after_fork() -> None:
    """In a forked child the parent's worker thread does not exist (and the lock may be
    held by a thread that does not either): start afresh, or every fill would wait on
    a queue no thread reads."""
    global _FILL_WORKER, _FILL_WORKER_LOCK
    _FILL_WORKER, _FILL_WORKER_LOCK = None, threading.Lock()


if hasattr(os, "register_at_fork"):  # POSIX
    os.register_at_fork(after_in_child=_forget_worker_after_fork)


def start_blend_fill(image_rgb: np.ndarray, zone_mean_m: np.ndarray, zone_valid: np.ndarray,
                     zone_rects: np.ndarray, zone_far: np.ndarray | None = None,
                     far_depth_m: float | None = None,
                     out_size: tuple[int, int] | None = None, beside: bool = True) -> Future:
    """:func:`blend_fill` on a worker thread; its ``Future`` gives the fill (or raises).

    The fill spends most of its time in LAPACK (or numba's compiled solver) and OpenCV,
    which release the GIL, so it runs beside the network (onnxruntime and PyTorch release
    the GIL too). One worker thread, shared by all estimators, started on first use.
    ``beside=False`` computes the fill now, on the calling thread, and returns it as a
    finished ``Future`` (:func:`fill_beside_network` says which).
    """
    def fill() -> np.ndarray | None:
        return blend_fill(image_rgb, zone_mean_m, zone_valid, zone_rects, zone_far,
                          far_depth_m, out_size)

    return _run(fill, beside)


def start_frame_fills(images: Sequence[np.ndarray], frames: Sequence[ZoneFrame],
                      rects: Sequence[np.ndarray], no_target: Sequence[np.ndarray],
                      far_depth_m: float | None, beside: bool,
                      out_size: tuple[int, int] | None = None) -> list[Future]:
    """:func:`start_blend_fill` for each frame of a batch (metres, at ``out_size`` or the
    image's size).

    Args:
        images: B (H, W, 3) uint8 RGB images; ``frames`` their B zone frames.
        rects: B (Z, 4) zone rectangles in image pixels.
        no_target: B (Z,) bool no-target flags (those the network reads), read at
            ``far_depth_m`` metres; ignored when that is None.
        beside: as :func:`start_blend_fill`'s.
    """
    return [start_blend_fill(image, mean, valid, frame_rects,
                             zone_far=None if far_depth_m is None else flags,
                             far_depth_m=far_depth_m, out_size=out_size, beside=beside)
            for image, (mean, _, valid), frame_rects, flags in zip(
                images, (frame.flat() for frame in frames), rects, no_target, strict=True)]


def _run(task: Callable[[], Any], beside: bool) -> Future:
    """``task`` on the shared worker thread, or now on this one (a finished ``Future``)."""
    if not beside:
        done: Future = Future()
        try:
            done.set_result(task())
        except Exception as error:  # raised by result(), as from the worker
            done.set_exception(error)
        return done
    global _FILL_WORKER
    with _FILL_WORKER_LOCK:
        if _FILL_WORKER is None:
            _FILL_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-fill")
    return _FILL_WORKER.submit(task)


def fill_beside_network(torch_backend: bool) -> bool:
    """Whether the blend's fill should run beside the network (``start_blend_fill``'s
    ``beside``) or before it, on the calling thread.

    Beside it for onnxruntime, whose idle threads yield their cores (the estimator's
    sessions do not busy-wait). Beside PyTorch only when a core is left over for the fill:
    where PyTorch's threads use every core, the fill competed with them for one and the
    frame took longer than with the fill run first (benchmarks/RESULTS.md).

    Args:
        torch_backend: the network runs in PyTorch (with ``torch.get_num_threads()``
            threads).
    """
    if not torch_backend:
        return True
    import torch

    return torch.get_num_threads() < cpu_count()
