"""A frame stream pipelined around the network: :func:`run_pipelined`.

:meth:`~deltar.inference.estimator.DepthEstimator.predict_stream` splits each frame's
prediction in three: the work before the network (checks, zone screening, the
network's input, the blend's fill), the network, and the work after it (the output
stage and the results). The network runs on the calling thread, one frame at a time;
the frame after it is prepared on one worker thread meanwhile, and the frame before it
finished on another. Where the network's threads leave cores idle, the work around it
then costs little of the frame rate; where they take every core it competes with them
(what each schedule measured: benchmarks/RESULTS.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import Any, TypeVar

Item = TypeVar("Item")
Started = TypeVar("Started")
Outputs = TypeVar("Outputs")
Result = TypeVar("Result")

#: Items run and not yet handed out, at most: the one being finished beside the next
#: one's ``run`` and that one.
MAX_FINISHING = 2


def run_pipelined(items: Iterable[Item], begin: Callable[[Item], Started],
                  run: Callable[[Started], Outputs],
                  finish: Callable[[Started, Outputs], Result]) -> Iterator[Result]:
    """``finish(started, run(started))`` with ``started = begin(item)`` for each item, in
    order, overlapping the three steps of neighbouring items.

    The items are drawn and begun on a worker thread, one at a time, the next one while
    ``run`` of this one runs on the calling thread; ``finish`` runs on a second worker.
    A result is handed out as soon as it is finished, while the next item is still being
    drawn: with a live source (a camera that blocks until its next frame) each result
    comes out without waiting for later frames. At most :data:`MAX_FINISHING` items are
    being finished at once: when ``finish`` is the slowest step, ``run`` waits for it,
    so the items in flight (and their memory) stay bounded.

    Args:
        items: anything iterable; drawn on the worker thread, at most one ahead of the
            item being run.
        begin: the work before ``run`` (must not need the calling thread).
        run: the work that stays on the calling thread (e.g. a network call).
        finish: the work after it.

    Yields:
        Each item's result, in the items' order.

    Raises:
        Whatever a step or the items raise, at that item's turn: the results of the
        items before it are yielded first. Closing the iterator (``close()``, or dropping
        it) cancels what has not started and does not wait for what has.
    """
    iterator = iter(items)
    preparing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-stream-begin")
    finishing = ThreadPoolExecutor(max_workers=1, thread_name_prefix="deltar-stream-finish")

    def draw_and_begin() -> Any:
        for item in iterator:
            return begin(item)
        return _END

    finished: deque[Future] = deque()
    try:
        upcoming = preparing.submit(draw_and_begin)
        while True:
            # Hand out what is finished while the next item is drawn and begun; with
            # MAX_FINISHING results in flight, wait for the oldest: a finish slower than
            # begin and run would otherwise let them run ahead without bound.
            while finished:
                if len(finished) >= MAX_FINISHING:
                    wait([finished[0]])
                else:
                    wait([upcoming, finished[0]], return_when=FIRST_COMPLETED)
                if not finished[0].done():
                    break
                yield finished.popleft().result()
            try:
                started = upcoming.result()
                if started is _END:
                    break
                upcoming = preparing.submit(draw_and_begin)
                outputs = run(started)
            except Exception:
                while finished:  # the results before the failing item come first
                    yield finished.popleft().result()
                raise
            finished.append(finishing.submit(finish, started, outputs))
        while finished:
            yield finished.popleft().result()
    finally:
        preparing.shutdown(wait=False, cancel_futures=True)
        finishing.shutdown(wait=False, cancel_futures=True)


#: What the draw returns after the last item.
_END = object()


def pipeline_chosen(pipelined: bool | None, torch_on_every_core: bool) -> bool:
    """Whether ``predict_stream`` pipelines: ``pipelined`` when it is True or False; by
    default (None) except for a PyTorch network on the CPU whose threads take every
    core (there the steps around it compete with its threads: benchmarks/RESULTS.md).

    Raises:
        ValueError: ``pipelined`` is not None, True or False.
    """
    if pipelined is not None and not isinstance(pipelined, bool):
        raise ValueError(f"pipelined must be None, True or False, got {pipelined!r}")
    return not torch_on_every_core if pipelined is None else pipelined


def stream_pair(pair: Any) -> tuple[Any, Any]:
    """One item of ``predict_stream``'s stream as (image, zone frame); ``ValueError``
    for anything that is not such a pair (the image and frame are checked later)."""
    if not isinstance(pair, tuple | list) or len(pair) != 2:
        raise ValueError(f"predict_stream takes (image, zone frame) pairs, got "
                         f"{type(pair).__name__}"
                         f"{f' of length {len(pair)}' if isinstance(pair, tuple | list) else ''}")
    if isinstance(pair[0], tuple | list) or getattr(pair[0], "ndim", 3) != 3:
        raise ValueError("predict_stream takes one (H, W, 3) image per pair, got "
                         f"{type(pair[0]).__name__} of shape {getattr(pair[0], 'shape', None)}")
    return pair[0], pair[1]


def numbered_step(step: Callable[[Any, Any], Result]) -> Callable[[tuple[int, Any]], Result]:
    """``step(image, frame)`` for an ``(index, pair)`` item of ``enumerate(pairs)``: a
    ``ValueError`` (of the same type) then names the pair's place in the stream, which
    the message of a one-frame check (``images[0] ...``) cannot."""
    def run(item: tuple[int, Any]) -> Result:
        index, pair = item
        try:
            return step(*stream_pair(pair))
        except ValueError as err:
            # Of the same type, made without its __init__ (whose arguments may differ).
            numbered = type(err).__new__(type(err))
            numbered.__dict__.update(err.__dict__)
            numbered.args = (f"pair {index} of the stream: {err}",)
            raise numbered from err
    return run
