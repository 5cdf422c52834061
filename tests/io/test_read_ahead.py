"""Reading the next item on a worker thread while the current one is processed."""

from __future__ import annotations

import threading

import pytest

from deltar.io.read_ahead import read_ahead


def test_items_come_in_order_with_their_loads():
    got = [(item, future.result()) for item, future in read_ahead(range(5), lambda i: i * i)]
    assert got == [(0, 0), (1, 1), (2, 4), (3, 9), (4, 16)]
    assert list(read_ahead([], lambda i: i)) == []


def test_the_next_load_runs_while_the_caller_works():
    started = {i: threading.Event() for i in range(3)}

    def load(i):
        started[i].set()
        return threading.current_thread().name

    for item, future in read_ahead(range(3), load):
        if item + 1 < 3:
            # Handed item `item`, the next one's load starts without the caller asking.
            assert started[item + 1].wait(10)
        assert future.result().startswith("deltar-read-ahead")


def test_a_load_error_is_raised_at_its_item():
    def load(i):
        if i == 1:
            raise OSError("corrupt frame 1")
        return i

    seen = []
    for _item, future in read_ahead(range(3), load):
        try:
            seen.append(future.result())
        except OSError as err:
            seen.append(str(err))
    assert seen == [0, "corrupt frame 1", 2]


def test_stopping_early_loads_at_most_one_more():
    loaded = []
    for item, future in read_ahead(range(100), lambda i: loaded.append(i) or i):
        future.result()
        if item == 2:
            break
    assert loaded[:3] == [0, 1, 2] and len(loaded) <= 4


def test_items_are_drawn_on_the_calling_thread():
    threads = []

    def items():
        for i in range(3):
            threads.append(threading.current_thread())
            yield i

    assert [item for item, _ in read_ahead(items(), lambda i: i)] == [0, 1, 2]
    assert set(threads) == {threading.current_thread()}
    with pytest.raises(TypeError):
        next(read_ahead(5, lambda i: i))
