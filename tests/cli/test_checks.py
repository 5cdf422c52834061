"""The CLI's shared option checks: devices and displays (the others are tested through
the commands that use them)."""

from __future__ import annotations

import pytest
import typer

from deltar.cli import checks


def test_cpu_device_is_accepted() -> None:
    assert checks.torch_device("cpu") == "cpu"


@pytest.mark.parametrize(("name", "message"), [
    ("gpu", "unknown device 'gpu'; use cpu, cuda, cuda:N or mps"),
    ("cuda:x", "unknown device 'cuda:x'"),
])
def test_device_typos_are_refused(name: str, message: str) -> None:
    with pytest.raises(typer.BadParameter, match=message):
        checks.torch_device(name)


def test_cuda_without_a_gpu_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(typer.BadParameter, match="no CUDA GPU is available on this machine "
                                                 r"\(use --device cpu\)"):
        checks.torch_device("cuda")


def test_a_gpu_index_beyond_the_machine_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert checks.torch_device("cuda:1", "--gpu") == "cuda:1"
    with pytest.raises(typer.BadParameter, match="this machine has 2 CUDA GPU"):
        checks.torch_device("cuda:2", "--gpu")


def test_mps_where_there_is_none_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(typer.BadParameter, match="Apple MPS is not available here"):
        checks.torch_device("mps")


def test_windows_need_a_display(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(checks.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert not checks.has_display()
    with pytest.raises(ValueError, match=r"--show needs a display .* --out DIR instead"):
        checks.display()
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert checks.has_display()
