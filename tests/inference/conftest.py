"""Shared inference-test fixtures: a small random lite model and flat-wall frames."""

from __future__ import annotations

import pytest
import torch

from deltar.models import create_model


@pytest.fixture(scope="session")
def lite_model():
    """deltar-lite with seeded random weights, laid out for 64x96 inputs."""
    torch.manual_seed(0)
    return create_model("deltar-lite", design_size=(64, 96)).eval()
