"""Fitting a checkpoint's uncertainty calibration: library and ``deltar fit-uncertainty``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.data.zju_l5 import ZJUL5Dataset, write_zju_l5
from deltar.evaluation.uncertainty import fit_checkpoint_uncertainty
from deltar.inference.estimator import DepthEstimator
from deltar.models import create_model
from deltar.models.checkpoint import load_checkpoint, save_checkpoint

runner = CliRunner(env={"COLUMNS": "200"})


def _checkpoint(path: Path) -> Path:
    torch.manual_seed(0)
    model = create_model("deltar-lite", head="zone_prior", design_size=(32, 64))
    return save_checkpoint(path, model, "deltar-lite")


def test_fit_writes_a_checkpoint_the_estimator_calibrates_with(tmp_path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    source = _checkpoint(tmp_path / "model.pt")
    fit = fit_checkpoint_uncertainty(source, [ZJUL5Dataset(data)], tmp_path / "cal.pt",
                                     min_pixels=100)
    assert fit.frames == 3 and fit.pixels["inside"] + fit.pixels["outside"] == 3 * 32 * 48
    for name in ("inside", "outside"):
        within_1, within_2 = fit.coverage[name]
        assert 0.55 <= within_1 <= 0.85 and within_2 >= within_1
    model, _, config = load_checkpoint(fit.path)
    assert config["output"]["uncertainty_calibration"] == fit.calibration.to_dict()
    estimator = DepthEstimator(model)
    assert estimator.uncertainty == fit.calibration
    sample = tiny_samples[0]
    assert estimator.predict(sample.rgb, sample.zone_frame(),
                             zone_rects=sample.zone_rects).uncertainty_calibrated
    # The input checkpoint is left as it was.
    assert load_checkpoint(source)[2]["output"]["uncertainty_calibration"] is None
    with pytest.raises(ValueError, match="is the checkpoint being calibrated"):
        fit_checkpoint_uncertainty(source, [ZJUL5Dataset(data)], source, overwrite=True)


def test_fit_of_a_plane_select_model_fits_its_blend_first(tmp_path, tiny_samples) -> None:
    from deltar.inference.blend import DEFAULT_BLEND, ConfidenceBlend

    data = write_zju_l5(tmp_path / "set", tiny_samples)
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    source = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    fit = fit_checkpoint_uncertainty(source, [ZJUL5Dataset(data)], tmp_path / "cal.pt",
                                     min_pixels=100)
    assert fit.blend is not None and fit.blend != DEFAULT_BLEND
    # The fit minimises a smoothed relative error: no worse than either side on its pixels.
    rel = fit.relative_error
    assert rel["blend"] <= min(rel["network"], rel["fill"]) * 1.02
    _, _, config = load_checkpoint(fit.path)
    assert ConfidenceBlend.from_dict(config["output"]["confidence_blend"]) == fit.blend
    estimator = DepthEstimator(load_checkpoint(fit.path)[0])
    assert estimator.blend == fit.blend and estimator.uncertainty == fit.calibration


def test_cli_fits_and_refuses_bad_arguments(tmp_path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    source = _checkpoint(tmp_path / "model.pt")
    out = tmp_path / "cal.pt"
    # One tiny frame has 512 pixels beyond the zone grid, fewer than the 1000 needed.
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--frames-per-set", "1", "--out", str(out)])
    assert result.exit_code == 1 and "need at least 1000" in result.output
    assert not out.exists()
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--blend-objective", "rmse", "--out", str(out)])
    assert result.exit_code == 2 and "--blend-objective" in result.output
    assert "relative, squared" in result.output and not out.exists()
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data",
                                 str(tmp_path / "missing.json"), "--out", str(out)])
    assert result.exit_code == 2 and "--data" in result.output
    out.write_bytes(b"keep")
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--out", str(out)])
    assert result.exit_code != 0 and "exists; pass --overwrite" in result.output
    assert out.read_bytes() == b"keep"
