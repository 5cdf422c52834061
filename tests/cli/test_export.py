"""``deltar export``: bad inputs and outputs are refused before the model is built, and a
failed multi-size export leaves no file under the final names."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.cli.model_options import ModelOptions

runner = CliRunner(env={"COLUMNS": "200"})


@pytest.fixture
def built(monkeypatch):
    """The model loads the command asked for (none, when it refused the input first)."""
    loads = []
    original = ModelOptions.load

    def load(self):
        loads.append(self)
        return original(self)

    monkeypatch.setattr(ModelOptions, "load", load)
    return loads


@pytest.mark.parametrize(("make", "message"), [
    (lambda d: d / "nowhere", "calibration RGB-D folder not found"),
    (lambda d: (d / "empty").mkdir() or d / "empty", "cannot tell the layout of"),
    (lambda d: [(d / "rgbd" / k).mkdir(parents=True) for k in ("color", "depth")] and
     d / "rgbd", "no colour images found"),
])
def test_a_bad_int8_calibration_folder_fails_before_the_model(tmp_path, built, make,
                                                              message):
    out = tmp_path / "int8.onnx"
    result = runner.invoke(app, ["export", "--preset", "deltar-lite", "--out", str(out),
                                 "--size", "64x96", "--int8", "--calibration",
                                 str(make(tmp_path))])
    assert result.exit_code == 1, result.output
    assert "error: --calibration: " in result.output and message in result.output
    assert built == [] and not out.exists()


def test_a_folder_in_place_of_another_sizes_file_is_refused_before_the_export(tmp_path):
    from deltar.export.onnx import sized_export_paths
    from deltar.models import create_model

    out = tmp_path / "a.onnx"
    sizes = [(240, 320), (480, 480)]
    other = list(sized_export_paths(create_model("deltar-lite"), out, sizes).values())[1]
    other.mkdir()
    result = runner.invoke(app, ["export", "--preset", "deltar-lite", "--out", str(out),
                                 "--size", "240x320,480x480", "--overwrite"])
    assert result.exit_code == 1, result.output
    assert f"error: --out {other} is a folder, not a file" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == [other.name]  # nothing written
