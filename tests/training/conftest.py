"""Fixtures for training tests: the tiny config, one torch thread per process."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from deltar.training.config_loading import load_config

TINY_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tiny_test.yaml"


@pytest.fixture(autouse=True)
def _one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def tiny_config():
    """A loader for configs/tiny_test.yaml with extra ``key=value`` overrides."""
    return lambda *overrides: load_config(TINY_CONFIG, list(overrides))
