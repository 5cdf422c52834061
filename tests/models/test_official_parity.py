"""The deltar-official preset with the fixture's weights reproduces the release's outputs.

The v2 fixture holds the released architecture with well-conditioned weights and the
outputs the release's own code computed from them; thread count, batch-norm folding and
channels-last move those outputs by ~1e-5 m, while real mistakes (wrong zone samples,
shifted rectangles, timm's stem activation) move them by decimetres. So the 1e-3 m /
1e-4 m tolerances hold on any CPU and still catch every mistake that matters.
"""

from __future__ import annotations

import copy

import pytest
import torch

from deltar.models import create_model, load_official_weights
from deltar.models.benchmark import DEPTH_TOLERANCE_M, EDGE_TOLERANCE_M, normalise_image

THREADS = (1, 2, 4)


@pytest.fixture(scope="module")
def official_model(parity_fixture):
    model = create_model("deltar-official")
    report = load_official_weights(model, parity_fixture["state_dict"])
    assert report.ok, report.summary()
    return model.eval()


def _errors(model, case) -> tuple[float, float]:
    with torch.inference_mode():
        out = model(
            normalise_image(case["image_rgb_uint8"]),
            case["zone_samples_icdf16"][None].float(),
            case["zone_rects_yxyx"][None].float(),
            case["zone_valid"][None].bool(),
        )
    assert torch.isfinite(out["uncertainty"]).all()
    depth_error = (out["depth"][0, 0] - case["expected_depth_half_res"]).abs().max().item()
    edge_error = (out["bin_edges"][0] - case["expected_bin_edges"]).abs().max().item()
    return depth_error, edge_error


def test_normalisation_is_the_release_formula(parity_fixture):
    image = parity_fixture["cases"][0]["image_rgb_uint8"]
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    expected = (image.permute(2, 0, 1)[None].float() / 255.0 - mean) / std
    assert torch.equal(normalise_image(image), expected)


@pytest.mark.parametrize("threads", THREADS)
@pytest.mark.parametrize("case_index", [0, 1, 2])
def test_matches_release_outputs(official_model, parity_fixture, case_index, threads):
    torch.set_num_threads(threads)  # restored by the autouse single_thread fixture
    case = parity_fixture["cases"][case_index]
    depth_error, edge_error = _errors(official_model, case)
    assert depth_error < DEPTH_TOLERANCE_M, f"{case['name']}: depth error {depth_error} m"
    assert edge_error < EDGE_TOLERANCE_M, f"{case['name']}: bin edge error {edge_error} m"


@pytest.mark.parametrize("threads", THREADS)
def test_every_inference_optimisation_keeps_release_parity(official_model, parity_fixture,
                                                           threads):
    from deltar.models.optimize import prepare_for_inference

    torch.set_num_threads(threads)
    model = prepare_for_inference(copy.deepcopy(official_model), fold_encoder=True,
                                  channels_last=True)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    for case in parity_fixture["cases"]:
        depth_error, edge_error = _errors(model, case)
        assert depth_error < DEPTH_TOLERANCE_M, f"{case['name']}: depth error {depth_error} m"
        assert edge_error < EDGE_TOLERANCE_M, f"{case['name']}: edge error {edge_error} m"


def test_parity_catches_a_real_mistake(official_model, parity_fixture):
    # Zone samples 0.1 m too far: the kind of mistake the tolerance must not hide.
    case = dict(parity_fixture["cases"][0])
    samples = case["zone_samples_icdf16"].float()
    case["zone_samples_icdf16"] = torch.where(samples > 0, samples + 0.1, samples)
    depth_error, _ = _errors(official_model, case)
    assert depth_error > 10 * DEPTH_TOLERANCE_M
