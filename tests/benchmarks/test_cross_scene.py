"""The protocol script's comparisons (benchmarks/cross_scene.py), on made-up metrics."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

_SPEC = importlib.util.spec_from_file_location(
    "cross_scene", Path(__file__).resolve().parents[2] / "benchmarks" / "cross_scene.py")
cross_scene = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(cross_scene)


def _rows(model: float, a: float, b: float) -> dict[str, dict[str, float]]:
    return {"trained": {"rel": model, "rmse": model}, "a": {"rel": a, "rmse": a},
            "b": {"rel": b, "rmse": b}}


def test_margins_against_the_means_each_folds_and_each_scenes_best() -> None:
    # Two folds of two scenes. Method a is best on the means; b wins the second fold
    # and the last scene.
    scenes = [_rows(0.8, 1.0, 2.0), _rows(0.8, 1.0, 2.0), _rows(0.9, 1.2, 1.3),
              _rows(0.9, 1.6, 1.0)]
    means = {name: {k: sum(r[name][k] for r in scenes) / 4 for k in ("rel", "rmse")}
             for name in ("trained", "a", "b")}
    line = cross_scene._comparison("the best classical baseline", ("a", "b"), scenes, means,
                                   "trained", [2, 2])
    model = 0.8 + 0.8 + 0.9 + 0.9
    expected = {"the means": 1 - model / (1.0 + 1.0 + 1.2 + 1.6),
                "each fold's best": 1 - model / (1.0 + 1.0 + 1.3 + 1.0),  # a, then b
                "each scene's best": 1 - model / (1.0 + 1.0 + 1.2 + 1.0)}
    for label, gain in expected.items():
        found = re.search(re.escape(label) + r": REL ([+-][\d.]+)%", line)
        assert found and float(found.group(1)) == pytest.approx(100 * gain, abs=0.05), label
    assert "better in both on 4 of 4" in line
    # Without folds, the line stops at the means; folds that miss scenes are refused.
    assert "each fold" not in cross_scene._comparison("x", ("a", "b"), scenes, means)
    with pytest.raises(ValueError, match="do not add up"):
        cross_scene._comparison("x", ("a", "b"), scenes, means, "trained", [2, 1])


def test_a_relative_out_folder_is_the_callers_not_the_project_roots(tmp_path, monkeypatch):
    # The deltar commands run with the project root as working folder: the paths they are
    # given must not be relative to the caller's.
    commands: list[tuple[str, ...]] = []

    class Stop(Exception):
        pass

    def record(*args: str) -> None:
        commands.append(args)
        raise Stop

    monkeypatch.setattr(cross_scene, "deltar", record)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(Stop):
        cross_scene.main(["--out", "cs", "--folds", "kitchen-shelf", "--steps", "1"])
    config = Path(commands[0][commands[0].index("-c") + 1])
    assert config.is_absolute() and config.is_file()
    assert config.parent.parent == tmp_path / "cs"


def test_an_extra_model_file_is_the_callers_a_bundled_name_stays(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.pt").write_bytes(b"")
    assert cross_scene.model_argument("mine.pt") == str(tmp_path / "mine.pt")
    assert cross_scene.model_argument("default") == "default"
