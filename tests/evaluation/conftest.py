"""Fixtures of the evaluation tests."""

from __future__ import annotations

import pytest

from deltar.data.zju_l5 import ZJUL5Sample

from .samples import make_sample


@pytest.fixture
def tiny_samples() -> list[ZJUL5Sample]:
    return [make_sample("scene_a/0001", 0), make_sample("scene_a/0002", 1),
            make_sample("scene_b/0001", 2)]
