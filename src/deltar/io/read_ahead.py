"""Read the next frame while the current one is processed.

Decoding a frame's PNG files is a large part of a frame's time beside the network;
OpenCV releases Python's GIL while it decodes, so a stream that reads its next frame on
a worker thread while the estimator works on the current one runs faster (``deltar
replay``, ``deltar predict`` on folders, ``deltar map``; measured in
benchmarks/RESULTS.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

Item = TypeVar("Item")
Loaded = TypeVar("Loaded")


def read_ahead(items: Iterable[Item], load: Callable[[Item], Loaded]
               ) -> Iterator[tuple[Item, Future]]:
    """Yield ``(item, future)`` in order, ``future.result()`` being ``load(item)``.

    Each item's ``load`` runs on a worker thread, started when the previous item is
    handed over, so one load overlaps the caller's work on the previous item. The items
    themselves are drawn on the calling thread (one ahead of the one handed over). An
    error of ``load`` is raised by that item's ``future.result()``, where the caller can
    handle it per item. Closing the iterator early (``break``) cancels the load not yet
    started and does not wait for a running one.

    Args:
        items: anything iterable (e.g. recording pairs, file jobs).
        load: reads one item (e.g. decodes its image); called once per item.
    """
    iterator = iter(items)
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-read-ahead")
    try:
        pending = _submit_next(iterator, pool, load)
        while pending is not None:
            item, future = pending
            pending = _submit_next(iterator, pool, load)
            yield item, future
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _submit_next(iterator: Iterator[Item], pool: ThreadPoolExecutor,
                 load: Callable[[Item], Loaded]) -> tuple[Item, Future] | None:
    for item in iterator:
        return item, pool.submit(load, item)
    return None
