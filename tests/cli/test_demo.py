"""``deltar demo`` end to end on one small generated scene."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from deltar.cli.main import app

METRIC_KEYS = {"d1", "d2", "d3", "rel", "sq_rel", "rmse", "rmse_log", "log10", "silog"}


def test_demo_writes_scenes_panels_and_metrics(tmp_path):
    out = tmp_path / "demo"
    result = CliRunner().invoke(app, ["demo", str(out), "--frames", "1", "--size", "96x128"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert {"nearest", "bilinear", "guided_filter", "colorization"} <= set(metrics)
    # The bundled model runs beside the baselines, once (no test-time flip here).
    assert "model:default" in metrics and not any("+flip" in name for name in metrics)
    for name, values in metrics.items():
        # The model also gives a per-pixel sigma, scored for its coverage.
        extra = {"within_1sigma", "within_2sigma"} if name.startswith("model:") else set()
        assert set(values) == METRIC_KEYS | extra
        assert 0.0 <= values["d1"] <= 1.0 and values["rmse"] > 0
    panels = sorted((out / "panels").rglob("*.png"))
    assert len(panels) == len(metrics)
    # The sample for `deltar predict` reads back as a valid frame with its camera.
    from deltar.calibration.rig import RigCalibration
    from deltar.io.zone_file import load_zone_frame

    frame = load_zone_frame(out / "sample" / "zones.json")
    assert frame.grid == 8 and frame.valid.any()
    calib = RigCalibration.load(out / "sample" / "calib.json")
    assert (calib.intrinsics.height, calib.intrinsics.width) == (96, 128)
    assert (out / "sample" / "image.png").read_bytes()[:4] == b"\x89PNG"
    # A second run into the same folder must not overwrite the first.
    again = CliRunner().invoke(app, ["demo", str(out), "--frames", "1", "--size", "96x128"],
                               env={"COLUMNS": "300"})
    assert again.exit_code == 2
    assert "already holds a demo" in again.output
    (out / "metrics.json").unlink()  # as a demo stopped before its evaluation leaves it
    again = CliRunner().invoke(app, ["demo", str(out), "--frames", "1", "--size", "96x128"],
                               env={"COLUMNS": "300"})
    assert again.exit_code == 2 and "holds an unfinished demo (no metrics.json: it was " \
        "interrupted); remove it or choose another folder" in " ".join(again.output.split())
