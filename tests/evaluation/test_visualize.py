"""Per-frame PNG panels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from deltar.evaluation.visualize import safe_filename, save_frame_panel

from .samples import make_sample


def test_safe_filename() -> None:
    assert safe_filename("scene/00012") == "scene__00012"
    assert safe_filename("model:deltar-official") == "model__deltar-official"
    assert safe_filename("a b?c") == "a_b_c"
    assert safe_filename("..") == "frame"


def test_panel_with_invalid_zones_and_missing_ground_truth(tmp_path: Path) -> None:
    sample = make_sample("scene/0001", 0)
    sample.zone_valid[[0, 5]] = False
    sample.zone_no_target = np.zeros_like(sample.zone_valid)
    sample.zone_no_target[5] = True  # drawn apart from the other invalid zone
    sample.depth_m[:4] = 0.0
    target = tmp_path / "panels" / "p.png"
    written = save_frame_panel(target, sample, np.full((32, 48), 1.5, np.float32), "m")
    assert written == target
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in target.parent.iterdir()] == ["p.png"]


def test_panel_rejects_wrong_shape(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not match"):
        save_frame_panel(tmp_path / "p.png", make_sample("s", 0), np.ones((8, 8)), "m")
    assert not (tmp_path / "p.png").exists()
