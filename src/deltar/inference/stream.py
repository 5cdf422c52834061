"""A frame stream pipelined around the network: :func:`run_pipelined`.

:meth:`~deltar.inference.estimator.DepthEstimator.predict_stream` splits each frame's
prediction in three: the work before the network (checks, zone screening, the
network's input, the blend's fill), the network, and the work after it (the output
stage and the results). The network runs on the calling thread, one frame at a time;
the frame after it is prepared on one worker thread meanwhile, and the frame before it
finished on another. Where the network's threads leave cores idle (PyTorch on a CPU, or
any network on a GPU), the work around it then costs little of the frame rate; with
onnxruntime on two cores it measured level with a plain loop (benchmarks/RESULTS.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

Item = TypeVar("Item")
Started = TypeVar("Started")
Outputs = TypeVar("Outputs")
Result = TypeVar("Result")


def run_pipelined(items: Iterable[Item], begin: Callable[[Item], Started],
              run: Callable[[Started], Outputs],
              finish: Callable[[Started, Outputs], Result]) -> Iterator[Result]:
    """``finish(started, run(started))`` with ``started = begin(item)`` for each item, in
    order, overlapping the three steps of neighbouring items.

    ``begin`` of the next item runs on a worker thread while ``run`` of this one runs
    on the calling thread; ``finish`` of this one on a second worker while ``run`` of
    the next one does. At most two items are begun ahead of the one handed out.

    Args:
        items: anything iterable, drawn on the calling thread one ahead.
        begin: the work before ``run`` (must not need the calling thread).
        run: the work that stays on the calling thread (e.g. a network call).
        finish: the work after it.

    Yields:
        Each item's result, in the items' order.

    Raises:
        Whatever a step raises, at that item's turn (the results before it have been
        yielded). Closing the iterator early (``break``) cancels what has not started and
        does not wait for what has.
    """
    iterator = iter(items)
    preparing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-stream-begin")
    finishing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-stream-finish")
    finished: deque[Future] = deque()
    try:
        upcoming = _begin_next(iterator, preparing, begin)
        while upcoming is not None:
            try:
                started = upcoming.result()
                upcoming = _begin_next(iterator, preparing, begin)
                outputs = run(started)
            except Exception:
                while finished:  # the results before the failing item come first
                    yield finished.popleft().result()
                raise
            finished.append(finishing.submit(finish, started, outputs))
            while len(finished) > 1:
                yield finished.popleft().result()
        while finished:
            yield finished.popleft().result()
    finally:
        preparing.shutdown(wait=False, cancel_futures=True)
        finishing.shutdown(wait=False, cancel_futures=True)


def _begin_next(iterator: Iterator[Item], pool: ThreadPoolExecutor,
                begin: Callable[[Item], Started]) -> Future | None:
    """``begin`` of the iterator's next item on ``pool``, or None at its end."""
    for item in iterator:
        return pool.submit(begin, item)
    return None


def stream_pair(pair: Any) -> tuple[Any, Any]:
    """One item of ``predict_stream``'s stream as (image, zone frame); ``ValueError``
    for anything that is not such a pair (the image and frame are checked later)."""
    if not isinstance(pair, tuple | list) or len(pair) != 2:
        raise ValueError(f"predict_stream takes (image, zone frame) pairs, got "
                         f"{type(pair).__name__}"
                         f"{f' of length {len(pair)}' if isinstance(pair, tuple | list) else ''}")
    return pair[0], pair[1]
