"""When the confidence blend's fill runs: beside the network or before it.

The fill (:func:`deltar.inference.blend.blend_fill`) needs only the image and the zones,
so the estimator starts it once the zones are placed, on one worker thread shared by all
estimators (:func:`start_blend_fill`), while the calling thread resizes the image for the
network. Then it either lets the fill run on beside the network or waits for it before
the network starts (:func:`wait_unless_beside_network`); :func:`fill_beside_network`
says which suits the network's backend and the cores there are.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait

import numpy as np

from deltar.inference.blend import blend_fill
from deltar.io.resources import cpu_count

_FILL_WORKER: ThreadPoolExecutor | None = None
_FILL_WORKER_LOCK = threading.Lock()


def start_blend_fill(image_rgb: np.ndarray, zone_mean_m: np.ndarray, zone_valid: np.ndarray,
                     zone_rects: np.ndarray, zone_far: np.ndarray | None = None,
                     far_depth_m: float | None = None,
                     out_size: tuple[int, int] | None = None) -> Future:
    """:func:`blend_fill` on a worker thread; its ``Future`` gives the fill (or raises).

    The fill spends most of its time in LAPACK and OpenCV, which release the GIL, so it
    runs beside the calling thread's work (onnxruntime and PyTorch release the GIL too).
    One worker thread, shared by all estimators, started on first use. Arguments and
    result as :func:`blend_fill`'s.
    """
    global _FILL_WORKER
    with _FILL_WORKER_LOCK:
        if _FILL_WORKER is None:
            _FILL_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-fill")
    return _FILL_WORKER.submit(blend_fill, image_rgb, zone_mean_m, zone_valid, zone_rects,
                               zone_far, far_depth_m, out_size)


def wait_unless_beside_network(fills: Sequence[Future], torch_backend: bool) -> None:
    """Wait for started fills unless they should run beside the network
    (:func:`fill_beside_network`); called just before the network runs.

    Waiting there still lets each fill overlap the image's resize for the network. A
    fill's error is not raised here but by its ``result()``.

    Args:
        fills: the fills' futures (:func:`start_blend_fill`).
        torch_backend: the network runs in PyTorch.
    """
    if fills and not fill_beside_network(torch_backend):
        wait(fills)


def fill_beside_network(torch_backend: bool) -> bool:
    """Whether the blend's fill should run on beside the network or be finished before it.

    Beside it for onnxruntime, whose idle threads yield their cores (the estimator's
    sessions do not busy-wait). Beside PyTorch only when a core is left over for the fill:
    where PyTorch's threads use every core, the fill competed with them for one and the
    frame took longer than with the fill finished first (benchmarks/RESULTS.md).

    Args:
        torch_backend: the network runs in PyTorch (with ``torch.get_num_threads()``
            threads).
    """
    if not torch_backend:
        return True
    import torch

    return torch.get_num_threads() < cpu_count()
