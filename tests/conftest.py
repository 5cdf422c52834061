"""Shared test fixtures: paths into ../shared and fixed seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED = PROJECT_ROOT.parent / "shared"
SHARED_DATA = SHARED / "data" / "rgbd"
#: Released architecture with well-conditioned weights and the release's own outputs.
#: (The older official_parity_fixture.pt is chaotic and machine-dependent: never used.)
PARITY_FIXTURE = SHARED / "fixtures" / "official_parity_fixture_v2.pt"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data/rgbd`` (read-only real RGB-D frames)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def parity_fixture_path() -> Path:
    """Path of the official parity fixture (v2) in ``../shared/fixtures``."""
    if not PARITY_FIXTURE.is_file():
        pytest.fail(f"official parity fixture not found at {PARITY_FIXTURE}")
    return PARITY_FIXTURE


@pytest.fixture(scope="session")
def parity_fixture() -> dict:
    """The parity fixture's contents, loaded once; treat as read-only."""
    import torch

    if not PARITY_FIXTURE.is_file():
        pytest.fail(f"official parity fixture not found at {PARITY_FIXTURE}")
    # The fixture holds plain tensors, strings and lists (no code objects).
    return torch.load(PARITY_FIXTURE, weights_only=False)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def tiny_samples():
    """Three small synthetic ZJU-L5 samples (two scenes) for evaluation tests."""
    from tests.evaluation.samples import make_sample

    return [make_sample("scene_a/0001", 0), make_sample("scene_a/0002", 1),
            make_sample("scene_b/0001", 2)]
