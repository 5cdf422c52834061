"""Requests checked against the machine: threads, memory, free disk space."""

from __future__ import annotations

import shutil

import pytest

from deltar.io import resources


@pytest.mark.parametrize("threads", [0, -1, True, 2.5, 10**6])
def test_thread_counts_outside_the_machine_are_refused(threads):
    limit = 4 * resources.cpu_count()
    with pytest.raises(ValueError, match=rf"^threads must be between 1 and {limit} \(4 x the "
                       rf"{resources.cpu_count()} CPUs of this machine\), got "):
        resources.check_threads(threads)
    assert resources.check_threads(limit) == limit


def test_load_estimator_refuses_huge_thread_counts_before_torch():
    from deltar.inference.loading import load_estimator

    with pytest.raises(ValueError, match=r"^threads must be between 1 and"):
        load_estimator("deltar-lite", kind="preset", threads=10**6)


def test_memory_and_disk_checks(tmp_path, monkeypatch):
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 2**20)
    with pytest.raises(ValueError, match=r"^x needs about 2 MiB of memory, more than the 1 "
                       "MiB this machine has available; lower it$"):
        resources.check_memory(2 * 2**20, "x", "lower it")
    resources.check_memory(2**19, "x", "lower it")
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(resources.shutil, "disk_usage", lambda p: usage._replace(free=2**20))
    with pytest.raises(OSError, match=r"^out: needs up to 2\.0 MiB but .* has 1\.0 MiB free$"):
        resources.check_free_space(tmp_path / "new" / "deeper", 2 * 2**20, "out")
    resources.check_free_space(tmp_path, 2**19, "out")
