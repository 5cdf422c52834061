"""A frame stream pipelined around the network: the scheduler and predict_stream."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest

from deltar.inference.loading import load_estimator
from deltar.inference.stream import MAX_FINISHING, run_pipelined
from tests.inference.fakes import random_frame, random_image


def test_results_come_in_order_with_each_step_on_its_thread() -> None:
    caller = threading.get_ident()
    seen: dict[str, set[int]] = {"begin": set(), "run": set(), "finish": set()}

    def begin(item: int) -> int:
        seen["begin"].add(threading.get_ident())
        time.sleep(0.002 * (item % 3))  # uneven steps must not reorder the results
        return item * 10

    def run(started: int) -> int:
        seen["run"].add(threading.get_ident())
        return started + 1

    def finish(started: int, outputs: int) -> tuple[int, int]:
        seen["finish"].add(threading.get_ident())
        time.sleep(0.002 * ((started // 10) % 2))
        return started, outputs

    assert list(run_pipelined(range(12), begin, run, finish)) == [(10 * i, 10 * i + 1)
                                                               for i in range(12)]
    assert seen["run"] == {caller}
    assert caller not in seen["begin"] and caller not in seen["finish"]
    assert list(run_pipelined([], begin, run, finish)) == []


@pytest.mark.parametrize("failing", ["begin", "run", "finish"])
def test_a_failing_item_raises_at_its_turn_after_the_results_before_it(failing: str) -> None:
    def step(name: str):
        def call(*args):
            if name == failing and args[0] in (3, 30):
                raise ValueError(f"{name} refused item 3")
            return args[0] * 10 if name == "begin" else args[0]
        return call

    results = []
    stream = run_pipelined(range(6), step("begin"), step("run"),
                       lambda started, outputs: step("finish")(started, outputs))
    with pytest.raises(ValueError, match=f"{failing} refused item 3"):
        for result in stream:
            results.append(result)
    assert results == [0, 10, 20]


def test_a_failing_source_keeps_every_result_before_it() -> None:
    def source():
        yield from range(4)
        raise OSError("the camera went away")

    results = []
    with pytest.raises(OSError, match="camera went away"):
        for result in run_pipelined(source(), lambda item: item, lambda started: started,
                                    lambda started, outputs: outputs):
            results.append(result)
    assert results == [0, 1, 2, 3]


def test_a_result_is_handed_out_before_the_next_frame_exists() -> None:
    # A live source: frame k + 1 exists only once the consumer has result k (a stream
    # that waited for later frames before handing out results would never finish).
    handed_out = [threading.Event() for _ in range(6)]

    def camera():
        for k in range(6):
            if k and not handed_out[k - 1].wait(timeout=20):
                raise TimeoutError(f"frame {k} waited for result {k - 1}")
            yield k

    for result in run_pipelined(camera(), lambda item: item, lambda started: started,
                                lambda started, outputs: outputs):
        handed_out[result].set()
    assert all(event.is_set() for event in handed_out)


def test_closing_early_neither_hangs_nor_begins_everything() -> None:
    begun = []

    def begin(item: int) -> int:
        begun.append(item)
        return item

    stream = run_pipelined(itertools.count(), begin, lambda started: started,
                       lambda started, outputs: outputs)
    first = [next(stream) for _ in range(3)]
    stream.close()
    assert first == [0, 1, 2]
    assert len(begun) <= 6  # at most two ahead of what was handed out


def test_a_slow_finish_holds_the_network_back() -> None:
    # A finish slower than begin and run must not let them run ahead of it without
    # bound (each item run holds its inputs and outputs until it is handed out).
    release = threading.Event()
    ran = []

    def run(started: int) -> int:
        ran.append(started)
        return started

    def finish(started: int, outputs: int) -> int:
        if started == 0:
            release.wait(10)
        return outputs

    timer = threading.Timer(0.3, release.set)
    timer.start()
    try:
        stream = run_pipelined(itertools.count(), lambda item: item, run, finish)
        assert next(stream) == 0
        stream.close()
    finally:
        timer.cancel()
        release.set()
    assert len(ran) <= MAX_FINISHING


@pytest.mark.parametrize("source", ["default", "onnx"])
@pytest.mark.parametrize("pipelined", [None, True, False])
def test_predict_stream_gives_what_predict_gives(source: str, pipelined: bool | None,
                                                 rng) -> None:
    # By default PyTorch on every core predicts the frames in turn and onnxruntime
    # pipelines them; True / False force either.
    estimator = load_estimator("default", kind="onnx" if source == "onnx" else None)
    pairs = [(random_image(rng, 48, 64), random_frame(rng)) for _ in range(4)]
    streamed = list(estimator.predict_stream(iter(pairs), pipelined=pipelined))
    assert len(streamed) == len(pairs)
    for (image, frame), result in zip(pairs, streamed, strict=True):
        alone = estimator.predict(image, frame)
        np.testing.assert_array_equal(result.depth_m, alone.depth_m)
        np.testing.assert_array_equal(result.uncertainty_m, alone.uncertainty_m)
        assert result.zones_used == alone.zones_used


@pytest.mark.parametrize("pipelined", [True, False])
def test_predict_stream_refuses_a_bad_frame_at_its_turn_naming_its_place(rng, pipelined
                                                                        ) -> None:
    estimator = load_estimator("default", kind="onnx")
    pairs = [(random_image(rng, 48, 64), random_frame(rng)) for _ in range(3)]
    pairs[1] = (pairs[1][0].astype(np.float32), pairs[1][1])  # not uint8
    stream = estimator.predict_stream(pairs, pipelined=pipelined)
    assert next(stream).depth_m.shape == (48, 64)
    with pytest.raises(ValueError, match=r"^pair 1 of the stream: images\[0\] "):
        next(stream)


@pytest.mark.parametrize("source", ["default", "onnx"])
def test_predict_stream_refuses_what_is_not_a_pair(source: str, rng) -> None:
    estimator = load_estimator("default", kind="onnx" if source == "onnx" else None)
    image, frame = random_image(rng, 48, 64), random_frame(rng)
    with pytest.raises(ValueError, match=r"takes \(image, zone frame\) pairs, got tuple "
                                         r"of length 3"):
        list(estimator.predict_stream([(image, frame, None)]))


def test_predict_stream_refuses_a_batch_in_a_pair_and_a_bad_schedule(rng) -> None:
    estimator = load_estimator("default", kind="onnx")
    image, frame = random_image(rng, 48, 64), random_frame(rng)
    with pytest.raises(ValueError, match=r"one \(H, W, 3\) image per pair, got list"):
        list(estimator.predict_stream([([image, image], [frame, frame])]))
    with pytest.raises(ValueError, match="pipelined must be None, True or False, got 'no'"):
        list(estimator.predict_stream([(image, frame)], pipelined="no"))


def test_a_numbered_error_keeps_its_type_whatever_its_constructor():
    from deltar.inference.stream import numbered_step

    class NamedError(ValueError):
        def __init__(self, path, message):
            super().__init__(f"{path}: {message}")
            self.path = path

    def step(image, frame):
        raise NamedError("a.png", "unreadable")

    with pytest.raises(NamedError, match=r"^pair 3 of the stream: a\.png: unreadable$") as caught:
        numbered_step(step)((3, (np.zeros((4, 4, 3), np.uint8), None)))
    assert caught.value.path == "a.png"
