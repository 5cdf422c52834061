"""The released weights: the state-dict converter (names, wrappers, reports, file errors)
and parity of the deltar-official preset with the release's own outputs.

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

from deltar.contract import normalise_image
from deltar.models import create_model, load_official_weights
from deltar.models.benchmark import DEPTH_TOLERANCE_M, EDGE_TOLERANCE_M
from deltar.models.official import official_to_ours, unwrap_state_dict


@pytest.fixture(scope="module")
def official_state(parity_fixture):
    return parity_fixture["state_dict"]


@pytest.fixture(scope="module")
def model():
    return create_model("deltar-official")


@pytest.mark.parametrize(
    ("official", "ours"),
    [
        ("img_encoder.conv0.0.weight", "image_encoder.backbone.conv_stem.weight"),
        ("img_encoder.conv3.1.0.conv_pw.weight",
         "image_encoder.backbone.blocks.4.0.conv_pw.weight"),
        ("hist_encoder.hist_extractor2.pointnet_encoder.bn3.running_var",
         "distribution_encoder.blocks.1.mlp.7.running_var"),
        ("decoder.cross_atten1.layers.1.gsa.sr.weight",
         "decoder.fusions.2.layers.1.global_.reduce.weight"),
        ("decoder.cross_atten3.layers.0.merge.weight",
         "decoder.fusions.0.layers.0.out_proj.weight"),
        ("decoder.up4._net.3.bias", "decoder.up_blocks.3.block.3.bias"),
        ("conv_out.0.bias", "head.logits_conv.bias"),
        ("something.else", None),
    ],
)
def test_name_rules(official, ours):
    assert official_to_ours(official) == ours


def test_every_fixture_key_loads_and_values_arrive(model, official_state):
    report = load_official_weights(model, official_state)
    assert report.ok and report.loaded == len(official_state)
    ours = model.state_dict()
    torch.testing.assert_close(
        ours["head.logits_conv.weight"], official_state["conv_out.0.weight"].float()
    )
    # The flat (H * W, C) positional encoding arrives as an (H, W, C) grid, row-major.
    flat = official_state["decoder.cross_atten2.positional_encodings"].float()
    grid = ours["decoder.fusions.1.image_position"]
    torch.testing.assert_close(grid[1, 2], flat[1 * grid.shape[1] + 2])


def test_wrapped_and_prefixed_checkpoints(model, official_state):
    wrapped = {"model": {f"module.{key}": value for key, value in official_state.items()}}
    assert unwrap_state_dict(wrapped).keys() == official_state.keys()
    assert load_official_weights(model, wrapped).ok


def test_unmapped_and_missing_keys_are_reported(model, official_state):
    partial = dict(list(official_state.items())[:-2])
    partial["extra.head.weight"] = torch.zeros(3)
    with pytest.raises(ValueError, match="unmapped"):
        load_official_weights(model, partial)
    report = load_official_weights(model, partial, strict=False)
    assert report.unmapped == ["extra.head.weight"]
    assert len(report.missing) == 2 and not report.ok


def test_file_errors(model, tmp_path):
    with pytest.raises(FileNotFoundError):
        load_official_weights(model, tmp_path / "nyu.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"corrupt\.pt"):
        load_official_weights(model, corrupt)


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
            torch.from_numpy(normalise_image(case["image_rgb_uint8"].numpy()))[None],
            case["zone_samples_icdf16"][None].float(),
            case["zone_rects_yxyx"][None].float(),
            case["zone_valid"][None].bool(),
        )
    assert torch.isfinite(out["uncertainty"]).all()
    depth_error = (out["depth"][0, 0] - case["expected_depth_half_res"]).abs().max().item()
    edge_error = (out["bin_edges"][0] - case["expected_bin_edges"]).abs().max().item()
    return depth_error, edge_error


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
