"""Fitting a checkpoint's uncertainty calibration: library and ``deltar fit-uncertainty``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
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
    passes, visits = [], []
    fit = fit_checkpoint_uncertainty(source, [ZJUL5Dataset(data)], tmp_path / "cal.pt",
                                     min_pixels=100, on_frame=lambda: visits.append(1),
                                     on_passes=passes.append)
    assert fit.frames == 3 and fit.pixels["inside"] + fit.pixels["outside"] == 3 * 32 * 48
    # A network that reads no flags: three passes (outlier rule; zone consistency; blend
    # and sigma), so the progress total is the visits.
    assert passes == [3] and len(visits) == 9
    assert set(fit.zone_consistency_errors) == {0.0, 0.5, 1.0}
    assert fit.zone_consistency == min(fit.zone_consistency_errors,
                                       key=fit.zone_consistency_errors.get)
    for name in ("inside", "outside"):
        within_1, within_2 = fit.coverage[name]
        assert 0.55 <= within_1 <= 0.85 and within_2 >= within_1
    model, _, config = load_checkpoint(fit.path)
    assert config["output"]["uncertainty_calibration"] == fit.calibration.to_dict()
    assert config["output"]["zone_consistency"] == fit.zone_consistency
    estimator = DepthEstimator(model)
    assert estimator.zone_consistency == fit.zone_consistency
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


def test_too_few_pixels_for_the_two_regions_are_refused_before_any_pass(tmp_path,
                                                                       tiny_samples) -> None:
    # 1 frame x 100 pixels can never give 1000 per region: said before the checkpoint is
    # read and the frames visited (three passes), naming the options.
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    passes, visits = [], []
    with pytest.raises(ValueError, match=r"1 frame\(s\) x 100 pixels per frame give at most "
                       r"100 calibration pixels.*--frames-per-set, --pixels-per-frame"):
        fit_checkpoint_uncertainty(_checkpoint(tmp_path / "model.pt"), [ZJUL5Dataset(data)],
                                   tmp_path / "cal.pt", frames_per_set=1, pixels_per_frame=100,
                                   on_frame=lambda: visits.append(1), on_passes=passes.append)
    assert passes == [] and visits == [] and not (tmp_path / "cal.pt").exists()


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
    # The set has no 'train' split; the message says which it has.
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--split", "train", "--out", str(out)])
    assert result.exit_code == 2 and "no split 'train'" in result.output
    trained_on = write_zju_l5(tmp_path / "train-set", tiny_samples, split="train")
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(trained_on),
                                 "--split", "train", "--frames-per-set", "1", "--out",
                                 str(out)])
    assert result.exit_code == 1 and "need at least 1000" in result.output  # it read them
    # A Lightning checkpoint is named as such.
    lightning = tmp_path / "last.ckpt"
    lightning.write_bytes(source.read_bytes())
    result = runner.invoke(app, ["fit-uncertainty", str(lightning), "--data", str(data),
                                 "--out", str(out)])
    assert result.exit_code == 2 and "Lightning training checkpoint" in result.output
    out.write_bytes(b"keep")
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--out", str(out)])
    assert result.exit_code != 0 and "exists; pass --overwrite" in result.output
    assert out.read_bytes() == b"keep"


def _unflagged_sample(far_truth: bool, seed: int):
    """A 4 x 4 frame without flags whose right half returned nothing, beside a column
    reading 3.2 m: its truth is 6 m (beyond the range) or 3.2 m (failed zones on the
    same wall)."""
    from deltar.data.zju_l5 import ZJUL5Sample
    from tests.evaluation.samples import make_sample

    base = make_sample(f"scene/{seed:04d}", seed)
    means = np.tile([1.0, 3.2, 0.0, 0.0], (4, 1))
    truth = means.copy()
    truth[:, 2:] = 6.0 if far_truth else 3.2
    depth = np.pad(np.kron(truth, np.ones((8, 8))), ((0, 0), (8, 8)), mode="edge")
    valid = (means > 0).reshape(-1)
    mean_sigma = np.stack([means.reshape(-1), np.full(16, 0.05)], 1)
    return ZJUL5Sample(rgb=base.rgb, depth_m=depth.astype(np.float32),
                       zone_mean_sigma=mean_sigma, zone_rects=base.zone_rects,
                       zone_valid=valid, name=base.name)


@pytest.mark.parametrize("far_truth, expected", [(True, 3.0), (False, None)])
def test_no_target_rule_is_chosen_by_what_invalid_zones_hide(far_truth, expected) -> None:
    from deltar.evaluation.uncertainty import fit_no_target_inference

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    estimator = DepthEstimator(model, blend=None, uncertainty=None)
    samples = [_unflagged_sample(far_truth, seed) for seed in range(2)]
    chosen, errors = fit_no_target_inference(estimator, [samples])
    # 3.5 m marks only the column with no valid neighbour; 3.0 m and below mark both
    # invalid columns alike.
    assert errors[3.0] == errors[1.5] and len(set(errors.values())) == 3
    assert chosen == expected
    assert (errors[3.0] < errors[3.5] < errors[None]) == far_truth


def _fit_with_cli(tmp_path, samples) -> tuple[str, Path]:
    """``deltar fit-uncertainty`` of an untrained plane-select model on ``samples``:
    (its output, the written checkpoint)."""
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    source = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    data = write_zju_l5(tmp_path / "set", samples)
    out = tmp_path / "fitted.pt"
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    return result.output, out


def test_cli_reports_and_stores_the_no_target_rule(tmp_path) -> None:
    output, out = _fit_with_cli(tmp_path, [_unflagged_sample(True, seed) for seed in range(2)])
    assert "beside a valid zone reading >= 3 m" in output
    assert load_checkpoint(out)[2]["output"]["no_target_min_neighbour_m"] == 3.0



def test_the_fit_does_not_depend_on_the_rule_the_checkpoint_carried(tmp_path) -> None:
    # The blend and sigma are fitted on the network alone: frames without flags reach it
    # without the rule being refitted, so a checkpoint that carried one fits the same.
    sets = [[_unflagged_sample(True, seed) for seed in range(2)]]
    fits = []
    for rule in (None, 0.0):
        torch.manual_seed(0)
        model = create_model("deltar-select", design_size=(32, 64))
        model.set_output_contract(no_target_min_neighbour_m=rule)
        source = save_checkpoint(tmp_path / f"select-{rule}.pt", model, "deltar-select")
        fits.append(fit_checkpoint_uncertainty(source, sets, tmp_path / f"fitted-{rule}.pt",
                                               min_pixels=100))
    first, second = fits
    assert second.no_target_min_neighbour_m == first.no_target_min_neighbour_m == 3.0
    for name in ("network", "fill", "blend"):
        assert second.relative_error[name] == pytest.approx(first.relative_error[name],
                                                            rel=1e-6)
    blend_a, blend_b = first.blend.to_dict(), second.blend.to_dict()
    calib_a, calib_b = first.calibration.to_dict(), second.calibration.to_dict()
    for a, b in ((blend_a, blend_b), (calib_a, calib_b)):
        for region in ("inside", "outside"):
            for key, value in a[region].items():
                assert b[region][key] == pytest.approx(value, rel=1e-5, abs=1e-8), key


def _wall_sample(seed: int, outliers_real: bool):
    """A 4 x 4 frame of a wall at 2 m whose three zones read 2.6 m: a noisy sensor's
    outliers (the truth is the wall) or three recesses in it (``outliers_real``: the
    truth follows the readings)."""
    from deltar.data.zju_l5 import ZJUL5Sample
    from tests.evaluation.samples import make_sample

    base = make_sample(f"wall/{seed:04d}", seed)
    means = np.full((4, 4), 2.0)
    for row, col in ((1, 1), (1, 3), (3, 1)):  # apart, each with >= 5 neighbours
        means[row, col] = 2.6
    truth = means if outliers_real else np.full((4, 4), 2.0)
    depth = np.pad(np.kron(truth, np.ones((8, 8))), ((0, 0), (8, 8)), mode="edge")
    depth *= np.random.default_rng(seed).normal(1.0, 0.01, depth.shape)  # a rough wall
    mean_sigma = np.stack([means.reshape(-1), np.full(16, 0.05)], 1)
    return ZJUL5Sample(rgb=base.rgb, depth_m=depth.astype(np.float32),
                       zone_mean_sigma=mean_sigma, zone_rects=base.zone_rects,
                       zone_valid=np.ones(16, bool), name=base.name)


@pytest.mark.parametrize("outliers_real", [False, True])
def test_outlier_rule_is_chosen_by_what_rejecting_does_to_the_error(outliers_real) -> None:
    from deltar.evaluation.uncertainty import OUTLIER_CANDIDATES, fit_outlier_rule
    from deltar.sensor.zone_outliers import OutlierRule

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    estimator = DepthEstimator(model, blend=None, uncertainty=None, zone_outliers=None)
    samples = [_wall_sample(seed, outliers_real) for seed in range(2)]
    chosen, errors = fit_outlier_rule(estimator, [samples])
    # Only the candidate that asks for three outliers per frame rejects any here.
    assert set(errors) == set(OUTLIER_CANDIDATES)
    assert errors[OUTLIER_CANDIDATES[1]] == errors[None] == errors[OUTLIER_CANDIDATES[3]]
    rejecting = OutlierRule(0.05, min_zones=3)
    assert (errors[rejecting] < errors[None]) != outliers_real
    # Chosen on 4 x 4 frames, the rule applies to them (the candidates are for 8 x 8).
    assert chosen == (None if outliers_real else OutlierRule(0.05, min_zones=3, grid=4))
    assert estimator.zone_outliers is None  # restored


def test_cli_reports_and_stores_the_outlier_rule(tmp_path) -> None:
    output, out = _fit_with_cli(tmp_path, [_wall_sample(seed, False) for seed in range(2)])
    assert "zone outliers: set aside beyond 0.05 log distance" in output
    assert "kept " in output and "0.05 / 3 " in output
    stored = load_checkpoint(out)[2]["output"]["zone_outlier_rule"]
    assert stored == {"tolerance": 0.05, "min_zones": 3, "min_neighbours": 4, "grid": 4}
    assert DepthEstimator(load_checkpoint(out)[0]).zone_outliers.min_zones == 3


def _far_sample(seed: int, far_truth_m: float):
    """A 4 x 4 frame whose right half reported no target (flags carried) in front of a
    wall ``far_truth_m`` away; the left half reads 2 m."""
    from deltar.data.zju_l5 import ZJUL5Sample
    from tests.evaluation.samples import make_sample

    base = make_sample(f"far/{seed:04d}", seed)
    means = np.tile([2.0, 2.0, 0.0, 0.0], (4, 1))
    truth = np.where(means > 0, means, far_truth_m)
    depth = np.pad(np.kron(truth, np.ones((8, 8))), ((0, 0), (8, 8)), mode="edge")
    valid = (means > 0).reshape(-1)
    mean_sigma = np.stack([means.reshape(-1), np.full(16, 0.05)], 1)
    return ZJUL5Sample(rgb=base.rgb, depth_m=depth.astype(np.float32),
                       zone_mean_sigma=mean_sigma, zone_rects=base.zone_rects,
                       zone_valid=valid, zone_no_target=~valid, name=base.name)


@pytest.mark.parametrize("far_truth_m", [5.0, 6.5])
def test_no_target_depth_is_chosen_by_how_far_the_unseen_surfaces_are(far_truth_m) -> None:
    from deltar.evaluation.uncertainty import fit_no_target_depth

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    estimator = DepthEstimator(model, blend=None, uncertainty=None)
    chosen, errors = fit_no_target_depth(estimator, [[_far_sample(s, far_truth_m)
                                                      for s in range(2)]])
    assert sorted(errors) == [5.0, 5.5, 6.0, 6.5, 7.0] and chosen == far_truth_m
    # The estimator is left at the chosen depth: network and fill.
    assert estimator.no_target_depth_m == chosen == estimator.model.head.no_target_depth
    assert estimator.model.contract()["no_target_depth"] == chosen


def test_cli_reports_and_stores_the_no_target_depth(tmp_path) -> None:
    output, out = _fit_with_cli(tmp_path, [_far_sample(seed, 6.0) for seed in range(2)])
    assert "zones that reported no target read at 6 m" in output
    fitted = load_checkpoint(out)[0]
    assert fitted.contract()["no_target_depth"] == 6.0 == fitted.head.no_target_depth
    assert DepthEstimator(fitted).no_target_depth_m == 6.0


def _tilted_wall(seed: int):
    """A 4 x 4 reading of a wall 1.5-3 m away, tilted at random, read right."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:4, 0:4]
    means = rng.uniform(1.5, 3.0) * np.exp(rng.normal(0, 0.03) * rows +
                                           rng.normal(0, 0.03) * cols)
    sample = _wall_sample(seed, True)
    return replace(sample, zone_mean_sigma=np.stack([means.reshape(-1),
                                                     0.02 * means.reshape(-1)], 1))


def test_a_detector_trained_on_clean_sets_joins_the_outlier_candidates(tmp_path) -> None:
    from deltar.evaluation.uncertainty import DETECTOR_THRESHOLDS, OUTLIER_CANDIDATES
    from deltar.sensor.zone_outlier_detector import OutlierDetector

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    source = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    noisy = [[_wall_sample(seed, False) for seed in range(2)]]
    clean = [[_tilted_wall(seed) for seed in range(2, 8)]]
    fit = fit_checkpoint_uncertainty(source, noisy, tmp_path / "fitted.pt", min_pixels=100,
                                     detector_sets=clean,
                                     detector_noise={"bias_prob": 0.5, "bias_mean_m": 0.5})
    detectors = [c for c in fit.outlier_errors if isinstance(c, OutlierDetector)]
    assert sorted(d.threshold for d in detectors) == sorted(DETECTOR_THRESHOLDS)
    assert set(fit.outlier_errors) - set(detectors) == set(OUTLIER_CANDIDATES)
    stored = load_checkpoint(tmp_path / "fitted.pt")[2]["output"]["zone_outlier_rule"]
    chosen = fit.outlier_rule
    assert stored == (None if chosen is None else chosen.to_dict())
    # A detector the weights carry is read back by the estimator, unchanged.
    detector = detectors[0]
    model.set_output_contract(zone_outlier_rule=detector.to_dict())
    path = save_checkpoint(tmp_path / "with-detector.pt", model, "deltar-select")
    assert DepthEstimator(load_checkpoint(path)[0]).zone_outliers == detector


def test_cli_refuses_a_bad_detector_noise_or_set(tmp_path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    source = _checkpoint(tmp_path / "model.pt")
    out = tmp_path / "cal.pt"
    for noise in ("0.2,0.3", "0.2,0,0.1,0.15", "1,0.3,0.1,0.15", "a,b,c,d"):
        result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                     "--detector-data", str(data), "--detector-noise", noise,
                                     "--out", str(out)])
        assert result.exit_code == 2 and "--detector-noise" in result.output, noise
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--detector-noise", "0.1,0.3,0.1,0.15", "--out", str(out)])
    assert result.exit_code == 2 and "give --detector-data too" in result.output
    result = runner.invoke(app, ["fit-uncertainty", str(source), "--data", str(data),
                                 "--detector-data", str(tmp_path / "missing.json"),
                                 "--out", str(out)])
    assert result.exit_code == 2 and "--detector-data" in result.output
    assert not out.exists()
