"""Learned models in ``deltar evaluate``: ``--checkpoint`` and ``--official``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.data.zju_l5 import write_zju_l5
from deltar.models import create_model
from deltar.models.checkpoint import save_checkpoint

runner = CliRunner(env={"COLUMNS": "200"})


def _untrained_prior_model(path: Path) -> Path:
    torch.manual_seed(0)
    # An untrained zone-prior head returns the prior interpolated from the zones, so the
    # model's depth is only right if the sample's own zone rectangles reach the network.
    model = create_model("deltar-lite", head="zone_prior", design_size=(32, 64))
    return save_checkpoint(path, model, "deltar-lite")


def _evaluate_checkpoint(tmp_path: Path, data: Path, checkpoint: Path, *options: str) -> dict:
    """``deltar evaluate --checkpoint CHECKPOINT OPTIONS``; the metrics it wrote."""
    out = tmp_path / "metrics.json"
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(checkpoint), *options,
                                 "--data", str(data), "--json", str(out)])
    assert result.exit_code == 0, result.output
    return json.loads(out.read_text())


def test_checkpoint_is_evaluated_beside_the_baselines(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    checkpoint = _untrained_prior_model(tmp_path / "prior.pt")
    out = tmp_path / "metrics.json"
    result = runner.invoke(app, ["evaluate", "-m", "median,nearest", "--checkpoint",
                                 str(checkpoint), "--data", str(data), "--json", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    key = f"model:{checkpoint}"
    assert list(metrics) == ["median", "nearest", key]
    # Zone-following depth: far better than one constant, not as exact as painting zones.
    assert metrics[key]["rmse"] < 0.6 * metrics["median"]["rmse"]
    assert metrics[key]["d1"] > metrics["median"]["d1"]


def test_missing_checkpoint_and_official_files_are_named(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    missing = tmp_path / "nope.pt"
    for option in ("--checkpoint", "--official"):
        result = runner.invoke(app, ["evaluate", option, str(missing), "--data", str(data)])
        # Checked as an option value before any work (docs/errors.md): a usage error.
        assert result.exit_code == 2, result.output
        assert "error: Invalid value for --checkpoint/--official" in result.output
        assert "nope.pt" in result.output


def test_no_method_at_all_is_an_error(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    result = runner.invoke(app, ["evaluate", "--data", str(data)])
    assert result.exit_code == 2, result.output
    assert "error:" in result.output and "--checkpoint" in result.output


def test_flip_adds_a_flip_averaged_entry(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    checkpoint = _untrained_prior_model(tmp_path / "prior.pt")
    metrics = _evaluate_checkpoint(tmp_path, data, checkpoint, "--flip")
    key = f"model:{checkpoint}"
    assert list(metrics) == [key, f"{key}+flip"]
    # The untrained prior is mirror-symmetric in the zones: flipping must not change it.
    for name in ("rmse", "rel", "d1"):
        assert abs(metrics[f"{key}+flip"][name] - metrics[key][name]) < 1e-4


def test_estimator_predictor_samples_histogram_sets_from_their_histograms(tmp_path):
    """A THDR3K sample carries CNH histograms: the model's hypotheses come from them."""
    from deltar.data.thdr3k import read_thdr3k_sample
    from deltar.evaluation.model_methods import EstimatorPredictor
    from deltar.inference.estimator import DepthEstimator
    from deltar.sensor.sampling import sample_hypotheses_from_histogram
    from tests.data.thdr3k_set import write_sample
    from tests.inference.fakes import ZonePainterNet

    write_sample(tmp_path / "s", seed=3, height=64, width=96)
    sample = read_thdr3k_sample(tmp_path / "s")
    estimator = DepthEstimator(ZonePainterNet(), weights="painter", input_size=(64, 96))
    depth = EstimatorPredictor(estimator)(sample).depth_m
    expected = sample_hypotheses_from_histogram(
        torch.from_numpy(sample.hist_edges_m), torch.from_numpy(sample.hist_counts),
        torch.from_numpy(sample.zone_valid), 16).mean(-1).numpy()
    # The painter writes each zone's mean hypothesis over the zone (8 px zones here).
    y0, x0, y1, x1 = sample.zone_rects[10].astype(int)
    np.testing.assert_allclose(depth[y0 + 2:y1 - 2, x0 + 2:x1 - 2], expected[10], atol=1e-4)
    # ... which is the histogram's, not the Gaussian around the reported distance.
    assert abs(expected[10] - sample.zone_mean_sigma[10, 0]) > 1e-3


def test_evaluation_runs_the_size_rule(tmp_path: Path) -> None:
    """``model:`` runs the network at the size the estimator and export use, not at the
    design size whatever the image (a square image stays square)."""
    from deltar.evaluation.model_methods import checkpoint_predictor
    from deltar.inference.preprocess import network_input_size
    from tests.evaluation.samples import make_sample

    checkpoint = _untrained_prior_model(tmp_path / "prior.pt")  # design 32x64
    predictor = checkpoint_predictor(str(checkpoint))
    for size in ((480, 480), (720, 1280), (16, 4000)):
        expected = network_input_size(*size, design_size=(32, 64))
        assert predictor.estimator.network_size_for(size) == expected
    assert predictor.estimator.network_size_for((480, 480)) == (32, 32)  # not 32x64
    sample = make_sample("a", 0)
    depth = predictor(sample).depth_m
    assert depth.shape == sample.depth_m.shape and np.isfinite(depth).all()


def test_network_adds_the_network_alone_for_a_plane_select_model(tmp_path: Path,
                                                                 tiny_samples) -> None:
    """A plane-select checkpoint is scored with the estimator's blend; ``--network`` adds
    its depth without it, which differs (the untrained network is unsure)."""
    from deltar.evaluation.model_methods import checkpoint_predictor

    data = write_zju_l5(tmp_path / "set", tiny_samples)
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    checkpoint = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    metrics = _evaluate_checkpoint(tmp_path, data, checkpoint, "--network")
    key = f"model:{checkpoint}"
    assert list(metrics) == [key, f"{key}+network"]
    assert metrics[key]["rmse"] != metrics[f"{key}+network"]["rmse"]
    assert checkpoint_predictor(str(checkpoint)).estimator.blend is not None
    assert checkpoint_predictor(f"{checkpoint}+network").estimator.blend is None
