"""Confidence blend of the network's depth with the colorization fill of the zones."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.evaluation.baselines import run_baseline
from deltar.inference.blend import (
    DEFAULT_BLEND,
    ConfidenceBlend,
    RegionBlend,
    blend_depth,
    blend_fill,
    blend_weight,
    blend_with_fill,
    zone_grid_mask,
)
from deltar.inference.estimator import DepthEstimator
from deltar.inference.loading import load_estimator
from deltar.inference.preprocess import resize_to_image, scale_rects
from deltar.sensor.placement import nominal_zone_rects
from deltar.sensor.zone_frame import ZoneFrame

torch.set_num_threads(1)

#: Blends that take the network alone and the fill alone everywhere (logits of +-60).
NETWORK_ONLY = ConfidenceBlend(RegionBlend(60.0, 0.0), RegionBlend(60.0, 0.0))
FILL_ONLY = ConfidenceBlend(RegionBlend(-60.0, 0.0), RegionBlend(-60.0, 0.0))


def _scene(rng: np.random.Generator, height: int = 48, width: int = 64):
    """An image with a bright left half, zones reading 1 m there and 3 m on the right."""
    image = np.full((height, width, 3), 40, np.uint8)
    image[:, : width // 2] = 200
    image = np.clip(image + rng.integers(-5, 6, image.shape), 0, 255).astype(np.uint8)
    rows, cols = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    zone_h, zone_w = height / 4, width / 4
    rects = np.stack([rows * zone_h, cols * zone_w, (rows + 1) * zone_h, (cols + 1) * zone_w],
                     axis=-1).reshape(16, 4).astype(np.float32)
    means = np.where(cols < 2, 1.0, 3.0).reshape(16)
    return image, means, np.ones(16, bool), rects


def test_blend_options_are_checked():
    for bad in (float("nan"), float("inf"), "8", True, None):
        with pytest.raises(ValueError, match="confidence blend bias must be a finite number"):
            RegionBlend(bad, 0.0)
    with pytest.raises(ValueError, match="spread_slope"):
        RegionBlend(0.0, float("-inf"))
    with pytest.raises(ValueError, match=r"ConfidenceBlend\.outside must be a RegionBlend"):
        ConfidenceBlend(RegionBlend(0, 0), (1, 2))
    assert RegionBlend(np.float32(2.0), 0).bias == 2.0
    assert ConfidenceBlend.from_dict(DEFAULT_BLEND.to_dict()) == DEFAULT_BLEND
    with pytest.raises(ValueError, match="must have regions"):
        ConfidenceBlend.from_dict({"inside": DEFAULT_BLEND.to_dict()["inside"]})
    broken = DEFAULT_BLEND.to_dict()
    del broken["outside"]["bias"]
    with pytest.raises(ValueError, match="'outside' needs keys"):
        ConfidenceBlend.from_dict(broken)


def test_zone_grid_mask_is_the_clipped_bounding_box():
    rects = np.array([[-5.0, 2.4, 10.0, 8.0], [3.0, 7.0, 12.2, 30.0]])
    mask = zone_grid_mask(rects, (20, 25))
    expected = np.zeros((20, 25), bool)
    expected[0:13, 2:25] = True
    np.testing.assert_array_equal(mask, expected)


def test_blend_weight_is_the_logistic_of_the_relative_spread():
    depth = np.array([[2.0, 2.0], [4.0, 4.0]])
    uncertainty = np.array([[0.0, 0.2], [0.2, 0.4]])
    inside = np.array([[True, True], [False, True]])
    blend = ConfidenceBlend(RegionBlend(1.0, -2.0), RegionBlend(-3.0, -1.0))
    weight = blend_weight(depth, uncertainty, inside, blend)
    log_spread = np.log(np.maximum(uncertainty, 1e-6) / depth)
    logit = np.where(inside, 1.0 - 2.0 * log_spread, -3.0 - 1.0 * log_spread)
    assert weight.dtype == np.float32
    np.testing.assert_allclose(weight, 1 / (1 + np.exp(-logit)), rtol=1e-5)
    # A sure pixel (zero spread) keeps the network wherever the slope is negative.
    assert weight[0, 0] > 0.999


def test_blend_goes_from_the_network_to_the_fill(rng):
    image, means, valid, rects = _scene(rng)
    network = np.full(image.shape[:2], 2.0, np.float32)
    fill = run_baseline("colorization", image, means, valid, rects)
    sure = blend_depth(network, np.zeros_like(network), image, means, valid, rects,
                       NETWORK_ONLY)
    np.testing.assert_array_equal(sure, network)
    unsure = blend_depth(network, np.full_like(network, 10.0), image, means, valid, rects,
                         FILL_ONLY)
    np.testing.assert_allclose(unsure, blend_fill(image, means, valid, rects), rtol=1e-5)
    # The blend's fill is the baseline's solve on a coarser grid: the same away from edges.
    assert np.median(np.abs(unsure / fill - 1.0)) < 1e-3
    # The fill follows the image: the bright half near 1 m, the dark half near 3 m.
    assert abs(np.median(unsure[:, :20]) - 1.0) < 0.1
    assert abs(np.median(unsure[:, -20:]) - 3.0) < 0.1
    # Without a valid zone there is nothing to fill from: the network's depth stays.
    none = blend_depth(network, np.full_like(network, 10.0), image, means, ~valid, rects,
                       FILL_ONLY)
    np.testing.assert_array_equal(none, network)


def test_blend_scales_with_the_readings(rng):
    image, means, valid, rects = _scene(rng)
    network = rng.uniform(1.0, 3.0, image.shape[:2]).astype(np.float32)
    spread = (0.05 * network * rng.uniform(0, 2, image.shape[:2])).astype(np.float32)
    base = blend_depth(network, spread, image, means, valid, rects, DEFAULT_BLEND)
    scaled = blend_depth(2.5 * network, 2.5 * spread, image, 2.5 * means, valid, rects,
                         DEFAULT_BLEND)
    np.testing.assert_allclose(scaled, 2.5 * base, rtol=1e-4)


def test_no_target_zones_join_the_fill_at_their_depth(rng):
    image, means, valid, rects = _scene(rng)
    valid = valid.copy()
    far = np.zeros(16, bool)
    far[[2, 3, 6, 7, 10, 11, 14, 15]] = True  # the right half reports no target
    valid[far] = False
    network = np.full(image.shape[:2], 1.0, np.float32)
    unsure = np.full_like(network, 10.0)
    blended = blend_depth(network, unsure, image, means, valid, rects, FILL_ONLY,
                          zone_far=far, far_depth_m=5.0)
    assert np.median(blended[:, -20:]) > 4.5
    without = blend_depth(network, unsure, image, means, valid, rects, FILL_ONLY)
    assert np.median(without[:, -20:]) < 1.5
    with pytest.raises(ValueError, match="far_depth_m"):
        blend_depth(network, unsure, image, means, valid, rects, FILL_ONLY, zone_far=far)


def _select_estimator(**kwargs) -> DepthEstimator:
    from deltar.models import create_model

    torch.manual_seed(0)
    return DepthEstimator(create_model("deltar-select", design_size=(64, 96)),
                          weights="test", **kwargs)


def _blended_on_grid(estimator: DepthEstimator, image: np.ndarray, frame: ZoneFrame,
                     blend: ConfidenceBlend) -> np.ndarray:
    """What ``predict`` returns with ``blend``: the network's depth blended with the fill
    on the network's output grid, then resized to the image (metres)."""
    inputs = estimator.prepare([image], [frame])
    depth, spread = estimator.run_network(inputs)
    grid = depth.shape[2:]
    rects = inputs["image_rects"][0]
    fill = blend_fill(image, frame.flat()[0], frame.flat()[2], rects,
                      zone_far=frame.flat_no_target(), far_depth_m=5.0, out_size=grid)
    mixed = blend_with_fill(depth[0, 0], spread[0, 0], fill,
                            scale_rects(rects, image.shape[:2], grid), blend)
    return resize_to_image(mixed[None, None], image.shape[:2])[0, 0]


def test_estimator_blends_plane_select_networks_by_default(rng, lite_model):
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    mean = rng.uniform(0.8, 3.0, (8, 8))
    frame = ZoneFrame(mean, np.full((8, 8), 0.02), np.ones((8, 8), bool))
    blended = _select_estimator()
    assert blended.blend == DEFAULT_BLEND
    plain = _select_estimator(blend=None)
    result, raw = blended.predict(image, frame), plain.predict(image, frame)
    assert raw.network_depth_m is None
    np.testing.assert_allclose(result.network_depth_m, raw.depth_m, rtol=1e-6)
    np.testing.assert_allclose(result.depth_m,
                               _blended_on_grid(plain, image, frame, DEFAULT_BLEND), rtol=1e-5)
    # Blending on the grid then resizing is close to blending at the image's size.
    at_image_size = blend_depth(raw.depth_m, raw.uncertainty_m, image, frame.flat()[0],
                                frame.flat()[2], result.zone_rects, DEFAULT_BLEND,
                                zone_far=frame.flat_no_target(), far_depth_m=5.0)
    assert np.median(np.abs(result.depth_m / at_image_size - 1.0)) < 0.01
    assert not np.allclose(result.depth_m, raw.depth_m)  # the random net is unsure
    np.testing.assert_array_equal(result.uncertainty_m, raw.uncertainty_m)
    # Other heads were not validated with the blend: off unless asked for.
    assert DepthEstimator(lite_model, weights="test").blend is None
    assert DepthEstimator(lite_model, weights="test", blend=FILL_ONLY).blend == FILL_ONLY
    # Coefficients the weights carry (fitted by deltar fit-uncertainty) are used.
    carried = _select_estimator().model
    carried.set_output_contract(confidence_blend=FILL_ONLY.to_dict())
    assert DepthEstimator(carried, weights="test").blend == FILL_ONLY
    with pytest.raises(ValueError, match="blend must be 'auto', a ConfidenceBlend or None"):
        DepthEstimator(lite_model, weights="test", blend="on")


def test_predict_starts_the_fill_before_it_normalises_the_images(rng, monkeypatch):
    """The fill needs the zones as screened and placed: predict starts it from prepare's
    ``on_zones`` hook, so it runs while the images are resized, with the zone inputs
    prepare returns."""
    import deltar.inference.estimator as estimator_module

    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(0.8, 3.0, (8, 8)), np.full((8, 8), 0.02),
                      np.ones((8, 8), bool))
    estimator = _select_estimator()
    order: list[str] = []

    def spy(name, function):
        monkeypatch.setattr(estimator_module, name,
                            lambda *a, **k: order.append(name) or function(*a, **k))

    for name in ("start_frame_fills", "normalise_images"):
        spy(name, getattr(estimator_module, name))
    screen = estimator.screen_zones
    monkeypatch.setattr(estimator, "screen_zones",
                        lambda *a: order.append("screen_zones") or screen(*a))
    result = estimator.predict(image, frame)
    assert order == ["screen_zones", "start_frame_fills", "normalise_images"]
    np.testing.assert_array_equal(result.depth_m, estimator.predict(image, frame).depth_m)
    seen = {}
    inputs = estimator.prepare([image], [frame], on_zones=lambda zones: seen.update(zones))
    assert "image" not in seen and set(inputs) == set(seen) | {"image"}
    np.testing.assert_array_equal(seen["image_rects"], inputs["image_rects"])
    np.testing.assert_array_equal(result.zone_rects, inputs["image_rects"][0])


def test_image_only_frames_are_not_blended(rng):
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(np.zeros((8, 8)), np.zeros((8, 8)), np.zeros((8, 8), bool))
    result = _select_estimator().predict(image, frame)
    assert result.image_only and not result.blended and result.network_depth_m is None


def test_network_suffix_turns_the_blend_off():
    from deltar.evaluation.model_methods import _split_suffixes

    assert _split_suffixes("default") == ("default", {})
    assert _split_suffixes("a.pt+network") == ("a.pt", {"blend": None})
    assert _split_suffixes("a.pt+flip+network") == ("a.pt", {"flip_average": True,
                                                              "blend": None})
    assert _split_suffixes("a.pt+network+flip") == ("a.pt", {"flip_average": True,
                                                              "blend": None})


def test_colorization_solve_grid_does_not_depend_on_the_image_size(rng):
    """The fill is solved on ~4800 cells: a 480x640 frame and its 240x320 version agree."""
    from deltar.camera import ZJU_L5_INTRINSICS

    big = np.zeros((480, 640, 3), np.uint8)
    big[:, :300] = 180
    big[200:, 350:] = 90
    small = big[::2, ::2].copy()
    frame_mean = np.where(np.arange(64).reshape(8, 8) % 8 < 4, 1.2, 2.6)
    frame = ZoneFrame(frame_mean, np.full((8, 8), 0.02), np.ones((8, 8), bool))
    rects_big = nominal_zone_rects(frame, 480, 640, ZJU_L5_INTRINSICS.scaled(480, 640))
    rects_small = nominal_zone_rects(frame, 240, 320, ZJU_L5_INTRINSICS.scaled(240, 320))
    valid = np.ones(64, bool)
    depth_big = run_baseline("colorization", big, frame_mean.ravel(), valid, rects_big)
    depth_small = run_baseline("colorization", small, frame_mean.ravel(), valid, rects_small)
    assert np.abs(depth_big[::2, ::2] - depth_small).mean() < 0.02


def test_bad_blend_inputs_name_the_argument(rng):
    from deltar.inference.colorization import colorize_zones

    image, means, valid, rects = _scene(rng)
    depth = np.full(image.shape[:2], 2.0, np.float32)
    unsure = np.full_like(depth, 0.5)
    cases = [
        (dict(uncertainty_m=unsure[:-1]), "uncertainty_m"),
        (dict(depth_m=depth[None]), "depth_m"),
        (dict(image_rgb=image[:, :-2]), "image_rgb"),
        (dict(zone_valid=valid[:-1]), "zone_valid"),
        (dict(blend=(8, 128)), "blend must be a ConfidenceBlend"),
        (dict(zone_far=np.zeros(16, bool), far_depth_m=float("nan")), "far_depth_m"),
        (dict(zone_far=np.zeros(5, bool), far_depth_m=5.0), "zone_far"),
        (dict(zone_rects=rects[:, :3]), "zone_rects"),
    ]
    base = dict(depth_m=depth, uncertainty_m=unsure, image_rgb=image, zone_mean_m=means,
                zone_valid=valid, zone_rects=rects, blend=DEFAULT_BLEND)
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            blend_depth(**{**base, **change})
    for kwargs, message in [(dict(seed_side=3.0), "seed_side"), (dict(seed_side=4), "seed_side"),
                            (dict(solve_cells=True), "solve_cells")]:
        with pytest.raises(ValueError, match=message):
            colorize_zones(image, means, valid, rects, **kwargs)
    with pytest.raises(ValueError, match="uint8"):
        colorize_zones(image.astype(np.float32), means, valid, rects)
    with pytest.raises(ValueError, match="zone_mean_m must be finite"):
        colorize_zones(image, np.where(valid, np.nan, 1.0), valid, rects)


def test_blend_off_the_image_returns_the_network_depth(rng):
    image, means, valid, rects = _scene(rng)
    depth = np.full(image.shape[:2], 2.0, np.float32)
    away = rects + np.float32(1000.0)  # no zone overlaps the image
    out = blend_depth(depth, np.full_like(depth, 1.0), image, means, valid, away,
                      FILL_ONLY)
    assert out is depth


def test_blend_follows_the_flip_averaged_network_and_batches(rng):
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(0.8, 3.0, (8, 8)), np.full((8, 8), 0.02),
                      np.ones((8, 8), bool))
    flipped = _select_estimator(flip_average=True).predict(image, frame)
    expected = _blended_on_grid(_select_estimator(flip_average=True), image, frame,
                                DEFAULT_BLEND)
    np.testing.assert_allclose(flipped.depth_m, expected, rtol=1e-5)
    # A batch with an image-only frame: that one keeps the network's depth, the other is
    # blended exactly as alone.
    empty = ZoneFrame(np.zeros((8, 8)), np.zeros((8, 8)), np.zeros((8, 8), bool))
    estimator = _select_estimator()
    both = estimator.predict([image, image], [frame, empty])
    assert [b.image_only for b in both] == [False, True]
    alone = estimator.predict(image, frame)
    np.testing.assert_allclose(both[0].depth_m, alone.depth_m, rtol=1e-5, atol=1e-6)
    assert both[1].network_depth_m is None


def test_onnx_backend_blends_like_pytorch(rng, tmp_path):
    pytest.importorskip("onnxruntime")
    from deltar.export.onnx import export_onnx

    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(0.8, 3.0, (8, 8)), np.full((8, 8), 0.02),
                      np.ones((8, 8), bool))
    torch_estimator = _select_estimator(blend=None)
    rects = nominal_zone_rects(frame, 64, 96, torch_estimator.intrinsics.scaled(64, 96))
    export_onnx(torch_estimator.model, tmp_path / "select.onnx", 64, 96, zone_rects=rects)
    onnx_estimator = load_estimator(tmp_path / "select.onnx", kind="onnx", threads=1)
    assert onnx_estimator.blend == DEFAULT_BLEND
    got = onnx_estimator.predict(image, frame)
    reference = _select_estimator().predict(image, frame)
    np.testing.assert_allclose(got.network_depth_m, reference.network_depth_m, atol=1e-4)
    np.testing.assert_allclose(got.depth_m, reference.depth_m, atol=1e-4)


def test_onnx_refuses_flip_in_evaluation_names():
    from deltar.evaluation.model_methods import onnx_predictor

    with pytest.raises(ValueError, match=r"\+flip needs a PyTorch model"):
        onnx_predictor("model.onnx+flip")


def test_blend_with_fill_is_blend_weight_then_mix_log_depth(rng):
    # blend_with_fill takes the zone grid's box as slices and works in place: the same
    # values as the two public steps with the mask, over the whole range of weights.
    from deltar.inference.blend import DEFAULT_BLEND, blend_with_fill, mix_log_depth

    depth = rng.uniform(0.3, 6.0, (96, 128)).astype(np.float32)
    spread = (depth * rng.choice([0.0, 1e-9, 1e-4, 0.05, 0.3, 2.0], depth.shape)).astype(
        np.float32)
    fill = rng.uniform(0.3, 6.0, depth.shape).astype(np.float32)
    rects = np.array([[20.3, 30.0, 40.0, 50.7], [60.0, 70.2, 80.0, 100.0]], np.float32)
    weight = blend_weight(depth, spread, zone_grid_mask(rects, depth.shape), DEFAULT_BLEND)
    assert weight.min() < 0.01 and weight.max() == 1.0
    expected = mix_log_depth(depth, fill, weight)
    got = blend_with_fill(depth, spread, fill, rects, DEFAULT_BLEND)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(got[weight >= 1.0], depth[weight >= 1.0])


@pytest.mark.parametrize("shape", [(), (1,), (1, 1), (3,), (2, 5), (40, 7)])
def test_the_blend_takes_arrays_of_any_shape_and_size(rng, shape):
    """OpenCV reads arrays of up to four values as scalars: small ones take NumPy's log and
    exp; all give the NumPy formula, and views are exponentiated in place."""
    from deltar.inference.blend import _exp_in_place, mix_log_depth

    depth = np.asarray(rng.uniform(0.3, 6.0, shape), dtype=np.float32)
    fill = np.asarray(rng.uniform(0.3, 6.0, shape), dtype=np.float32)
    spread = np.asarray(depth * rng.uniform(0.01, 0.5, shape), dtype=np.float32)
    weight = blend_weight(depth, spread, np.ones(shape, bool), DEFAULT_BLEND)
    expected = np.exp(weight * np.log(depth) + (1 - weight) * np.log(fill))
    np.testing.assert_allclose(weight, 1 / (1 + np.exp(-(DEFAULT_BLEND.inside.bias
                               + DEFAULT_BLEND.inside.spread_slope * np.log(spread / depth)))),
                               rtol=1e-5)
    np.testing.assert_allclose(mix_log_depth(depth, fill, weight), expected, rtol=1e-5)
    values = rng.uniform(-2, 2, (6, 10)).astype(np.float32)
    view = values[:, :7]
    expected_view = np.exp(view)
    _exp_in_place(view)
    np.testing.assert_allclose(values[:, :7], expected_view, rtol=1e-6)
