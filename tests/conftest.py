"""Shared test fixtures: paths into ../shared and fixed seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED = PROJECT_ROOT.parent / "shared"
SHARED_DATA = SHARED / "data" / "rgbd"
PARITY_FIXTURE = SHARED / "fixtures" / "official_parity_fixture.pt"


@pytest.fixture
def shared_data() -> Path:
    """``../shared/data/rgbd`` (read-only real RGB-D frames)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def parity_fixture_path() -> Path:
    if not PARITY_FIXTURE.is_file():
        pytest.fail(f"official parity fixture not found at {PARITY_FIXTURE}")
    return PARITY_FIXTURE


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
