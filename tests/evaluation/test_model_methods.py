"""Learned models as evaluation methods: hypotheses from a sample's histograms, the size
rule."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from deltar.models import create_model
from deltar.models.checkpoint import save_checkpoint


def untrained_prior_checkpoint(path: Path) -> Path:
    """A deltar-lite checkpoint with an untrained zone-prior head, design 32x64."""
    torch.manual_seed(0)
    # An untrained zone-prior head returns the prior interpolated from the zones, so the
    # model's depth is only right if the sample's own zone rectangles reach the network.
    model = create_model("deltar-lite", head="zone_prior", design_size=(32, 64))
    return save_checkpoint(path, model, "deltar-lite")


@pytest.mark.parametrize("trained_on_histograms", [True, False])
def test_estimator_predictor_samples_histogram_sets_as_the_weights_were_trained(
        tmp_path, trained_on_histograms):
    """A THDR3K sample carries CNH histograms: a model trained on histograms draws its
    hypotheses from them, any other model from the zones' reported mean and sigma."""
    from deltar.data.thdr3k import read_thdr3k_sample
    from deltar.evaluation.model_methods import EstimatorPredictor
    from deltar.inference.estimator import DepthEstimator
    from deltar.sensor.hypotheses import zone_hypotheses
    from deltar.sensor.sampling import sample_hypotheses_from_histogram
    from tests.data.thdr3k_set import write_sample
    from tests.inference.fakes import ZonePainterNet

    write_sample(tmp_path / "s", seed=3, height=64, width=96)
    sample = read_thdr3k_sample(tmp_path / "s")
    net = ZonePainterNet()
    if trained_on_histograms:
        net.contract_values["histogram_hypotheses"] = True
    estimator = DepthEstimator(net, weights="painter", input_size=(64, 96))
    depth = EstimatorPredictor(estimator)(sample).depth_m
    from_histogram = sample_hypotheses_from_histogram(
        torch.from_numpy(sample.hist_edges_m), torch.from_numpy(sample.hist_counts),
        torch.from_numpy(sample.zone_valid), 16).mean(-1).numpy()
    gaussian = zone_hypotheses(sample.zone_mean_sigma[:, 0], sample.zone_mean_sigma[:, 1],
                               sample.zone_valid, 16).mean(-1)
    # The two differ here: the histogram's mean is not the reported distance.
    assert abs(from_histogram[10] - gaussian[10]) > 1e-3
    expected = from_histogram if trained_on_histograms else gaussian
    # The painter writes each zone's mean hypothesis over the zone (8 px zones here).
    y0, x0, y1, x1 = sample.zone_rects[10].astype(int)
    np.testing.assert_allclose(depth[y0 + 2:y1 - 2, x0 + 2:x1 - 2], expected[10], atol=1e-4)


def test_evaluation_runs_the_size_rule(tmp_path: Path) -> None:
    """``model:`` runs the network at the size the estimator and export use, not at the
    design size whatever the image (a square image stays square)."""
    from deltar.evaluation.model_methods import checkpoint_predictor
    from deltar.inference.preprocess import network_input_size
    from tests.evaluation.samples import make_sample

    checkpoint = untrained_prior_checkpoint(tmp_path / "prior.pt")  # design 32x64
    predictor = checkpoint_predictor(str(checkpoint))
    for size in ((480, 480), (720, 1280), (16, 4000)):
        expected = network_input_size(*size, design_size=(32, 64))
        assert predictor.estimator.network_size_for(size) == expected
    assert predictor.estimator.network_size_for((480, 480)) == (32, 32)  # not 32x64
    sample = make_sample("a", 0)
    depth = predictor(sample).depth_m
    assert depth.shape == sample.depth_m.shape and np.isfinite(depth).all()


def test_uninferred_suffix_turns_the_no_target_rule_off() -> None:
    from deltar.evaluation.model_methods import checkpoint_predictor

    assert checkpoint_predictor("default").estimator.no_target_min_neighbour_m is not None
    plain = checkpoint_predictor("default+network+uninferred").estimator
    assert plain.no_target_min_neighbour_m is None and plain.blend is None


def test_kept_suffix_turns_the_outlier_rule_off(tmp_path) -> None:
    from deltar.evaluation.model_methods import checkpoint_predictor
    from deltar.models import create_model
    from deltar.models.checkpoint import save_checkpoint
    from deltar.sensor.zone_outliers import OutlierRule

    model = create_model("deltar-select", design_size=(32, 64))
    model.set_output_contract(zone_outlier_rule=OutlierRule(0.05, min_zones=3).to_dict())
    path = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    assert checkpoint_predictor(str(path)).estimator.zone_outliers is not None
    kept = checkpoint_predictor(f"{path}+network+kept").estimator
    assert kept.zone_outliers is None and kept.blend is None


def test_official_weights_are_scored_with_the_releases_final_resize(tmp_path, parity_fixture):
    from deltar.data.zju_l5 import ZJUL5Sample
    from deltar.evaluation.model_methods import EstimatorPredictor, official_predictor
    from deltar.inference.loading import load_estimator

    weights = tmp_path / "nyu.pt"
    torch.save({k: v.float() for k, v in parity_fixture["state_dict"].items()}, weights)
    predictor = official_predictor(str(weights))
    opencv = EstimatorPredictor(load_estimator(weights, kind="official",
                                               output_align_corners=False))
    for case in parity_fixture["cases"]:
        image = case["image_rgb_uint8"].numpy()
        # The release's evaluation: its half-resolution depth, torch's align_corners=True.
        expected = torch.nn.functional.interpolate(
            case["expected_depth_half_res"][None, None].float(), size=image.shape[:2],
            mode="bilinear", align_corners=True)[0, 0].numpy()
        sample = ZJUL5Sample(rgb=image, depth_m=expected, name=case["name"],
                             zone_mean_sigma=case["zone_mean_sigma_m"].numpy(),
                             zone_rects=case["zone_rects_yxyx"].numpy(),
                             zone_valid=case["zone_valid"].numpy())
        result = predictor(sample)
        assert result.depth_m.shape == expected.shape and not result.image_only
        error = np.abs(result.depth_m - expected).max()
        assert error < 1e-4, f"{case['name']}: {error} m"
        # OpenCV's resize (align_corners=False) is centimetres away at depth edges.
        assert np.abs(opencv(sample).depth_m - expected).max() > 100 * error
