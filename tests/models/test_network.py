"""DeltarNet: presets and ablations build and train, general inputs, clear input errors."""

from __future__ import annotations

import pytest
import torch

from deltar.models import ABLATIONS, create_model, list_presets


@pytest.fixture(scope="module")
def lite_model():
    torch.manual_seed(0)
    return create_model("deltar-lite").eval()


@pytest.fixture(scope="module")
def lite_bins_model():
    """deltar-lite with the release's bins head and metric input (as the release)."""
    torch.manual_seed(0)
    return create_model("deltar-lite", head="bins", zone_scale_norm=False).eval()


def _forward_backward(model, inputs):
    out = model(*inputs)
    (out["depth"].mean() + out["uncertainty"].mean()).backward()
    return out


@pytest.mark.parametrize("preset", ["deltar-official", "deltar-paper", "deltar-lite"])
def test_presets_forward_backward_finite(preset, network_inputs):
    torch.manual_seed(0)
    model = create_model(preset)
    out = _forward_backward(model, network_inputs())
    n_bins = model.network_config.head.n_bins
    assert out["depth"].shape == (2, 1, 32, 48)
    assert out["uncertainty"].shape == (2, 1, 32, 48)
    assert out["bin_edges"].shape == (2, n_bins + 1)
    for value in out.values():
        assert torch.isfinite(value).all()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None, f"{name} received no gradient"
        assert torch.isfinite(parameter.grad).all(), f"{name} has a non-finite gradient"


@pytest.mark.parametrize("ablation", sorted(ABLATIONS))
def test_ablations_forward_backward_finite(ablation, network_inputs):
    torch.manual_seed(0)
    model = create_model("deltar-lite", **ABLATIONS[ablation])
    out = _forward_backward(model, network_inputs())
    assert out["depth"].shape == (2, 1, 32, 48)
    assert torch.isfinite(out["depth"]).all()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name


def test_uniform_sampling_is_recorded():
    model = create_model("deltar-lite", **ABLATIONS["uniform_sampling"])
    assert model.network_config.inputs.hypothesis_sampling == "uniform"


def test_unknown_preset_lists_known_names():
    with pytest.raises(ValueError, match="deltar-official"):
        create_model("deltar-huge")
    assert set(list_presets()) >= {"deltar-official", "deltar-paper", "deltar-lite"}


@pytest.mark.parametrize(("height", "width", "grid"), [(96, 128, 4), (64, 160, 8), (128, 96, 8)])
def test_sizes_and_grids(lite_model, network_inputs, height, width, grid):
    with torch.inference_mode():
        out = lite_model(*network_inputs(batch=2, height=height, width=width, n=grid))
    assert out["depth"].shape == (2, 1, height // 2, width // 2)
    assert torch.isfinite(out["depth"]).all()
    assert (out["depth"] >= 1e-3).all() and (out["depth"] <= 10.0).all()


def test_depth_is_expectation_of_bin_centres(lite_bins_model, network_inputs):
    # Uncertainty is the spread of a distribution over centres inside the edges, so it
    # can never exceed half the depth range.
    with torch.inference_mode():
        out = lite_bins_model(*network_inputs())
    edges = out["bin_edges"]
    assert torch.all(edges[:, 1:] > edges[:, :-1])
    torch.testing.assert_close(edges[:, 0], torch.full((2,), 1e-3))
    torch.testing.assert_close(edges[:, -1], torch.full((2,), 10.0), atol=1e-4, rtol=0)
    assert (out["uncertainty"] >= 0).all() and (out["uncertainty"] <= 5.0).all()


def test_no_valid_zone_gives_image_only_estimate(lite_model, network_inputs):
    image, hypotheses, rects, valid = network_inputs()
    none_valid = torch.zeros_like(valid)
    with torch.inference_mode():
        out_a = lite_model(image, torch.zeros_like(hypotheses), rects, none_valid)
        # With every zone invalid, neither the hypotheses nor the layout may matter.
        out_b = lite_model(image, torch.zeros_like(hypotheses), rects + 17.0, none_valid)
    assert torch.isfinite(out_a["depth"]).all()
    torch.testing.assert_close(out_a["depth"], out_b["depth"])


def test_invalid_zones_are_ignored(lite_model, network_inputs):
    image, hypotheses, rects, valid = network_inputs()
    changed = hypotheses.clone()
    changed[~valid] = 2.5  # values of invalid zones must not influence the output
    with torch.inference_mode():
        reference = lite_model(image, hypotheses, rects, valid)["depth"]
        altered = lite_model(image, changed, rects, valid)["depth"]
        moved = lite_model(image, hypotheses * 0.5, rects, valid)["depth"]
    torch.testing.assert_close(reference, altered)
    assert not torch.allclose(reference, moved)


def test_zones_wholly_outside_the_image(lite_model, lite_bins_model, network_inputs):
    image, hypotheses, rects, valid = network_inputs()
    with torch.inference_mode():
        # The bins head sees zones only through their image patches: none inside, no effect.
        outside = lite_bins_model(image, hypotheses, rects + 1000.0, valid)["depth"]
        no_zone = lite_bins_model(image, hypotheses, rects, torch.zeros_like(valid))["depth"]
        # The zone-prior head extrapolates the nearest zones' means into the image.
        prior_outside = lite_model(image, hypotheses, rects + 1000.0, valid)["depth"]
    assert torch.isfinite(outside).all()
    torch.testing.assert_close(outside, no_zone)
    assert torch.isfinite(prior_outside).all() and (prior_outside > 0).all()


def test_batch_samples_are_independent(lite_model, network_inputs):
    image, hypotheses, rects, valid = network_inputs()
    with torch.inference_mode():
        both = lite_model(image, hypotheses, rects, valid)["depth"]
        second = lite_model(image[1:], hypotheses[1:], rects[1:], valid[1:])["depth"]
    torch.testing.assert_close(both[1:], second, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda x: (x[0][:, :2], *x[1:]), "image must be"),
        (lambda x: (x[0][:, :, :60], *x[1:]), "divisible by 32"),
        (lambda x: (x[0], x[1].index_fill(2, torch.tensor([0]), float("nan")), *x[2:]),
         "hypotheses must be finite"),
        (lambda x: (x[0], -x[1] - 0.1, *x[2:]), "non-negative"),
        (lambda x: (x[0], x[1][:, :60], *x[2:]), "square grid"),
        (lambda x: (x[0], x[1], x[2][:, :16], x[3]), "zone_rects must be"),
        (lambda x: (*x[:3], x[3][:, :16]), "zone_valid must be"),
        (lambda x: (*x[:3], x[3].float()), "bool"),
        (lambda x: (x[0], x[1], x[2].flip(-1), x[3]), "y1 > y0"),
    ],
)
def test_bad_inputs_raise_clear_errors(lite_model, network_inputs, change, match):
    with pytest.raises(ValueError, match=match):
        lite_model(*change(network_inputs()))


def test_negative_sigma_raises(lite_model, network_inputs):
    image, hypotheses, rects, valid = network_inputs()
    mean_sigma = torch.ones(2, 64, 2)
    mean_sigma[0, 3, 1] = -0.1
    with pytest.raises(ValueError, match="zone_mean_sigma"):
        lite_model(image, hypotheses, rects, valid, mean_sigma)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="head"):
        create_model("deltar-lite", head="magic")
    with pytest.raises(ValueError, match="bad override"):
        create_model("deltar-lite", no_such_argument=1)


@pytest.mark.parametrize("head", ["zone_prior", "zone_select", "bins"])
def test_zone_scale_norm_takes_the_metric_scale_from_the_zones(network_inputs, head):
    # Scaling every zone reading by k scales depth, uncertainty and bin edges by k: the
    # image says where depth changes, the zones say how far.
    torch.manual_seed(3)
    model = create_model("deltar-lite", head=head).eval()
    assert model.network_config.inputs.zone_scale_norm
    with torch.no_grad():
        if head == "zone_prior":  # a head that is not zero, so the image matters
            model.head.logits_conv.weight.normal_(0.0, 0.5)
        if head == "zone_select":
            model.head.query.weight.normal_(0.0, 0.5)
    image, hypotheses, rects, valid = network_inputs(seed=4)
    # Small readings (scale ~0.4 m) keep 2.5 * depth inside the clamp: the untrained
    # bins head answers about half its range (0.001-10) times the scale.
    hypotheses = hypotheses.clamp(max=1.0) * 0.5
    with torch.inference_mode():
        base = model(image, hypotheses, rects, valid)
        for k in (0.4, 2.5):
            scaled = model(image, hypotheses * k, rects, valid)
            # Equivariant up to the output clamp to (min_depth, max_depth).
            inside = (base["depth"] * k < 9.99) & (scaled["depth"] < 9.99)
            assert inside.float().mean() > 0.5
            torch.testing.assert_close(scaled["depth"][inside], base["depth"][inside] * k,
                                       rtol=1e-4, atol=1e-5)
            for key in ("uncertainty", "bin_edges"):
                torch.testing.assert_close(scaled[key], base[key] * k, rtol=1e-4, atol=1e-5)
    if head == "bins":  # the release's metric bins are not equivariant without it
        metric = create_model("deltar-lite", head=head, zone_scale_norm=False).eval()
        metric.load_state_dict(model.state_dict())
        with torch.inference_mode():
            a = metric(image, hypotheses, rects, valid)["depth"]
            b = metric(image, hypotheses * 2.5, rects, valid)["depth"]
        assert not torch.allclose(b, a * 2.5, rtol=1e-2)


def test_zone_scale_is_the_lower_median_of_valid_zone_means():
    from deltar.models.network import zone_scale

    means = torch.tensor([[1.0, 3.0, 2.0, 9.0], [5.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0],
                          [4.0, 1.0, 0.0, 0.0]])
    valid = torch.tensor([[True, True, True, False], [True, False, False, False],
                          [False] * 4, [True, True, False, False]])
    hypotheses = means[..., None].expand(4, 4, 3)
    torch.testing.assert_close(zone_scale(hypotheses, valid), torch.tensor([2.0, 5.0, 1.0, 1.0]))


@pytest.mark.parametrize("head", ["zone_select", "mvit"])
def test_traceable_path_gives_the_same_outputs(network_inputs, head):
    torch.manual_seed(0)
    model = create_model("deltar-lite", head=head, design_size=(64, 96)).eval()
    inputs = network_inputs(batch=2)
    with torch.no_grad():
        eager = model(*inputs)
        assert model.set_traceable() is model and model.head.traceable
        traced = model(*inputs)
        model.set_traceable(False)
    assert not model.traceable and not model.head.traceable
    for key in ("depth", "bin_edges", "uncertainty"):
        torch.testing.assert_close(traced[key], eager[key], atol=1e-6, rtol=1e-6)


def test_output_stage_options_set_on_a_built_network():
    from deltar.models.config import OUTPUT_STAGE_OPTIONS

    select = create_model("deltar-select", design_size=(32, 64))
    assert select.set_output_contract(no_target_depth=6.5, zone_outlier_rule=None) is select
    assert select.head.no_target_depth == 6.5 == select.contract()["no_target_depth"]
    assert "no_target_depth" in OUTPUT_STAGE_OPTIONS
    with pytest.raises(ValueError, match="no_target_depth must lie in"):
        select.set_output_contract(no_target_depth=20.0)
    lite = create_model("deltar-lite", head="zone_select", design_size=(32, 64))
    with pytest.raises(ValueError, match="no_target_depth on a head that reads no-target"):
        lite.set_output_contract(no_target_depth=6.0)
    with pytest.raises(ValueError, match="can be set on a built network"):
        select.set_output_contract(head="bins")
