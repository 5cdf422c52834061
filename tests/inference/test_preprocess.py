"""The one size rule (deltar.inference.preprocess) and what the estimator feeds the network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.inference.estimator import DepthEstimator
from deltar.inference.loading import load_estimator
from deltar.inference.preprocess import (
    check_input_size,
    network_input_size,
    resize_to_image,
    scale_rects,
)
from deltar.sensor.placement import zone_mean_depth
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet

torch.set_num_threads(1)

BUNDLED_DESIGN = (256, 320)
ODD_SIZES = [(480, 480), (720, 1280), (16, 4000)]


def _frame(rng: np.random.Generator) -> ZoneFrame:
    return ZoneFrame(rng.uniform(0.8, 3.5, (8, 8)), rng.uniform(0.01, 0.1, (8, 8)),
                     np.ones((8, 8), bool))


@pytest.mark.parametrize("size, expected", [
    ((480, 640), (256, 320)),   # the design aspect: exactly the design size
    ((480, 480), (288, 288)),   # square stays square (not 256x320, distorted)
    ((720, 1280), (224, 384)),  # 16:9, s = 0.298 -> 214.7 x 381.6
    ((16, 4000), (32, 4512)),   # a strip: enlarged, the short side clamped at 32
    ((120, 160), (256, 320)),   # smaller images are enlarged to the design budget
])
def test_rule_keeps_aspect_at_the_design_pixel_budget(size, expected):
    assert network_input_size(*size, design_size=BUNDLED_DESIGN) == expected


@pytest.mark.parametrize("size", [(480, 480), (720, 1280), (300, 430), (1080, 1920),
                                  (61, 97)])
@pytest.mark.parametrize("design", [(256, 320), (480, 640), (64, 96)])
def test_rule_distorts_only_by_rounding(size, design):
    height, width = network_input_size(*size, design_size=design)
    assert height % 32 == 0 and width % 32 == 0
    scale = np.sqrt(design[0] * design[1] / (size[0] * size[1]))
    # Each side is the exactly scaled side rounded to the nearest multiple of 32.
    assert abs(height - size[0] * scale) <= 16 and abs(width - size[1] * scale) <= 16


def test_rule_without_design_size_only_rounds():
    assert network_input_size(480, 640) == (480, 640)
    assert network_input_size(60, 90) == (64, 96)
    assert network_input_size(47, 49) == (32, 64)
    assert network_input_size(10, 10) == (32, 32)


@pytest.mark.parametrize("call, name", [
    (lambda: network_input_size(0, 10), "image size"),
    (lambda: network_input_size(10, 10, design_size=(0, 64)), "design_size"),
    (lambda: network_input_size(10, 10, design_size=(64,)), "design_size"),
    (lambda: network_input_size(10, 10, divisor=0), "divisor"),
    (lambda: check_input_size((60, 96)), "input_size"),
    (lambda: check_input_size("big", "--size"), "--size"),
])
def test_bad_sizes_name_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_output_mapping_back_agrees_with_the_rect_mapping():
    # A step between network pixels 15 and 16 (edge at 15.5) must land, resized back to
    # the image, where scale_rects puts that coordinate: the same pixel-centre mapping.
    net = torch.zeros(1, 1, 32, 64)
    net[..., 16:] = 1.0
    net[..., 8:, :] += 1.0
    back = resize_to_image(net.numpy(), (90, 300))[0, 0]
    assert back.shape == (90, 300)
    _, edge_x, edge_y, _ = scale_rects(np.array([0.0, 15.5, 7.5, 0.0]), (32, 64), (90, 300))

    def crossing(profile: np.ndarray, level: float) -> float:
        i = int(np.argmax(profile >= level)) - 1
        return i + (level - profile[i]) / (profile[i + 1] - profile[i])

    assert crossing(back[0], 0.5) == pytest.approx(edge_x, abs=0.01)
    assert crossing(back[:, 0], 0.5) == pytest.approx(edge_y, abs=0.01)


@pytest.mark.parametrize("size", ODD_SIZES)
def test_estimator_runs_the_rule_on_odd_sizes(lite_model, rng, size):
    estimator = DepthEstimator(lite_model, weights="test")
    image = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
    pred = estimator.predict(image, _frame(rng))
    expected = network_input_size(*size, design_size=lite_model.network_config.inputs.design_size)
    assert pred.network_size == estimator.network_size_for(size) == expected
    assert pred.depth_m.shape == size and pred.uncertainty_m.shape == size
    assert np.isfinite(pred.depth_m).all() and np.isfinite(pred.uncertainty_m).all()
    assert (pred.depth_m > 0).all()


@pytest.mark.parametrize("size", [(480, 480), (200, 356)])
def test_zones_line_up_through_the_rule_on_odd_sizes(rng, size):
    """A network painting zone means gives back the zone-mean map on non-4:3 images."""
    painter = ZonePainterNet()
    painter.contract_values["design_size"] = (64, 96)
    estimator = DepthEstimator(painter, weights="painter")
    frame = _frame(rng)
    pred = estimator.predict(rng.integers(0, 256, (*size, 3), dtype=np.uint8), frame)
    assert pred.network_size == network_input_size(*size, design_size=(64, 96))
    expected = zone_mean_depth(frame, pred.zone_rects, size)
    # Away from zone borders (bilinear resizing mixes neighbours) the values match.
    border = np.zeros(size, bool)
    border[1:] |= expected[1:] != expected[:-1]
    border[:, 1:] |= expected[:, 1:] != expected[:, :-1]
    margin = 2 * int(np.ceil(max(s / n for s, n in zip(size, pred.network_size,
                                                       strict=True))))
    near = torch.nn.functional.max_pool2d(
        torch.from_numpy(border.astype(np.float32))[None, None], 2 * margin + 1, 1,
        margin)[0, 0].numpy() > 0
    interior = ~near & (expected > 0)
    assert interior.sum() > 0.1 * size[0] * size[1]
    np.testing.assert_allclose(pred.depth_m[interior], expected[interior], atol=1e-4)


def test_fixed_input_size_replaces_the_rule(lite_model, rng):
    estimator = DepthEstimator(lite_model, weights="test", input_size=(64, 64))
    pred = estimator.predict(rng.integers(0, 256, (48, 160, 3), dtype=np.uint8), _frame(rng))
    assert pred.network_size == (64, 64) and pred.depth_m.shape == (48, 160)


def test_bundled_model_runs_a_square_image_square():
    # The case: 480x480 was fed to the bundled model as 256x320 (distorted).
    from deltar.weights import bundled_model_names

    if "default" not in bundled_model_names():
        pytest.skip("no bundled model in this installation")
    estimator = load_estimator("default")
    assert estimator.design_size == BUNDLED_DESIGN
    assert estimator.network_size_for((480, 480)) == (288, 288)
    assert estimator.network_size_for((480, 640)) == BUNDLED_DESIGN


@pytest.mark.parametrize("size", [(480, 640), (100, 90), (32, 64)])
def test_resize_to_image_is_torch_bilinear(size):
    """OpenCV's resize matches torch's bilinear (align_corners=False)."""
    import torch.nn.functional as F

    maps = np.random.default_rng(2).uniform(0.3, 5.0, (2, 2, 32, 64)).astype(np.float32)
    expected = F.interpolate(torch.from_numpy(maps), size=size, mode="bilinear",
                             align_corners=False).numpy()
    got = resize_to_image(maps, size)
    assert got.shape == expected.shape and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=5e-5, atol=1e-6)
    # Other dtypes are resized as float32.
    np.testing.assert_array_equal(resize_to_image(maps.astype(np.float64), size), got)


@pytest.mark.parametrize(("mean", "std"), [(None, None), ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5))])
def test_normalise_images_is_the_contracts_normaliser_at_the_network_size(rng, mean, std):
    """The batched, resizing form agrees with the one normaliser (deltar.contract)."""
    from deltar.contract import IMAGENET_MEAN, IMAGENET_STD, normalise_image
    from deltar.inference.preprocess import normalise_images

    images = [rng.integers(0, 256, (32, 64, 3), dtype=np.uint8) for _ in range(2)]
    out = normalise_images(images, (32, 64), mean, std)
    assert out.shape == (2, 3, 32, 64) and out.dtype == np.float32
    for got, image in zip(out, images, strict=True):
        expected = normalise_image(image, mean or IMAGENET_MEAN, std or IMAGENET_STD)
        np.testing.assert_allclose(got, expected, atol=1e-5)


def test_normalise_images_halves_large_images_first(rng):
    """A large image is halved (OpenCV's fast 2 x 2 area path) while both sides keep 90 %
    of the network's size, then resized the rest of the way: 480 x 640 to 256 x 320 via
    240 x 320; close to a direct area resize, for a fraction of its cost."""
    import cv2

    from deltar.contract import normalise_image
    from deltar.inference.preprocess import halved_while, normalise_images

    coarse = rng.uniform(0, 255, (30, 40, 3)).astype(np.float32)
    image = np.clip(cv2.resize(coarse, (640, 480), interpolation=cv2.INTER_CUBIC)
                    + rng.normal(0, 4, (480, 640, 3)), 0, 255).astype(np.uint8)
    halved = cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(halved_while(image, (230.4, 288.0)), halved)
    expected = normalise_image(cv2.resize(halved, (320, 256), interpolation=cv2.INTER_LINEAR))
    got = normalise_images([image], (256, 320))[0]
    np.testing.assert_allclose(got, expected, atol=1e-5)
    direct = normalise_image(cv2.resize(image, (320, 256), interpolation=cv2.INTER_AREA))
    assert np.abs(got - direct).mean() < 0.02  # about one grey level in 255
    # Odd sides, or a halved side below 90 % of the size: no halving.
    assert halved_while(image[:479], (10, 10)).shape == (479, 640, 3)
    assert halved_while(image, (241, 10)).shape == (480, 640, 3)
    assert halved_while(image, (60, 80)).shape == (60, 80, 3)


@pytest.mark.parametrize("sizes", [((240, 320), (480, 640)), ((7, 9), (30, 41)),
                                   ((1, 5), (3, 9)), ((4, 4), (1, 1))])
def test_resize_with_aligned_corners_samples_as_torch_does(sizes, rng):
    import torch

    (h, w), (height, width) = sizes
    maps = rng.uniform(0.5, 5.0, (1, 2, h, w)).astype(np.float32)
    ours = resize_to_image(maps, (height, width), align_corners=True)
    theirs = torch.nn.functional.interpolate(torch.from_numpy(maps), size=(height, width),
                                             mode="bilinear", align_corners=True).numpy()
    assert np.abs(ours - theirs).max() < 1e-5
    # Corner pixels land on corner pixels.
    assert ours[0, 0, 0, 0] == maps[0, 0, 0, 0] and ours[0, 0, -1, -1] == pytest.approx(
        maps[0, 0, -1, -1] if height > 1 and width > 1 else maps[0, 0, 0, 0], abs=1e-6)
