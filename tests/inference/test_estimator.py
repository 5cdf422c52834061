"""DepthEstimator: zone placement, resizing, hypotheses, backends, checkpoints, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.inference.estimator import DepthEstimator
from deltar.inference.loading import load_estimator
from deltar.inference.preprocess import scale_rects
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.placement import nominal_zone_rects, zone_mean_depth
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet, random_frame, random_image

torch.set_num_threads(1)


def test_scale_rects_maps_image_bounds_and_centres():
    # The whole image (-0.5 .. size - 0.5) maps onto the whole resized image.
    full = np.array([[-0.5, -0.5, 59.5, 89.5]])
    np.testing.assert_allclose(scale_rects(full, (60, 90), (64, 96)),
                               [[-0.5, -0.5, 63.5, 95.5]], atol=1e-5)
    # Doubling the size: pixel centre 10 -> 20.5 (centre of the 2x2 block 20..21).
    np.testing.assert_allclose(scale_rects(np.array([[10.0, 4.0, 12.0, 6.0]]), (50, 50),
                                           (100, 100)), [[20.5, 8.5, 24.5, 12.5]], atol=1e-5)


@pytest.mark.parametrize("height, width", [(150, 220), (300, 430)])
def test_resized_zone_rects_line_up_with_the_image(rng, height, width):
    """A network that paints zone means gives back the zone-mean map after the resizes.

    150x220 is enlarged to a 160x224 network input, 300x430 shrunk to 288x416.
    """
    frame = random_frame(rng, invalid=0)
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    pred = estimator.predict(random_image(rng, height, width), frame)
    assert pred.depth_m.shape == (height, width)
    expected = zone_mean_depth(frame, pred.zone_rects, (height, width))
    np.testing.assert_allclose(pred.zone_rects,
                               nominal_zone_rects(frame, height, width), atol=1e-5)
    # Away from zone borders (where bilinear resizing mixes neighbours) the values match.
    interior = np.ones((height, width), bool)
    grad = np.abs(np.diff(expected, axis=0, prepend=expected[:1])) + \
        np.abs(np.diff(expected, axis=1, prepend=expected[:, :1]))
    near_border = torch.nn.functional.max_pool2d(
        torch.from_numpy((grad > 0).astype(np.float32))[None, None], 7, 1, 3)[0, 0].numpy() > 0
    interior &= ~near_border & (expected > 0)
    assert interior.sum() > 0.1 * height * width
    np.testing.assert_allclose(pred.depth_m[interior], expected[interior], atol=1e-4)


def test_predict_lite_single_and_batch_agree(lite_model, rng):
    estimator = DepthEstimator(lite_model, weights="test")
    images = [random_image(rng, 60, 90) for _ in range(2)]
    frames = [random_frame(rng), random_frame(rng)]
    batch = estimator.predict(images, frames)
    assert isinstance(batch, list) and len(batch) == 2
    for image, frame, pred in zip(images, frames, batch, strict=True):
        single = estimator.predict(image, frame)
        assert single.depth_m.shape == (60, 90) and single.depth_m.dtype == np.float32
        assert np.isfinite(single.depth_m).all() and (single.depth_m > 0).all()
        assert np.isfinite(single.uncertainty_m).all() and (single.uncertainty_m >= 0).all()
        np.testing.assert_allclose(pred.depth_m, single.depth_m, atol=1e-4)


def test_bfloat16_precision_runs(lite_model, rng):
    estimator = DepthEstimator(lite_model, precision="bfloat16", weights="test")
    pred = estimator.predict(random_image(rng, 64, 96), random_frame(rng))
    assert pred.depth_m.dtype == np.float32 and np.isfinite(pred.depth_m).all()
    lite_model.float()  # the session fixture is shared


def test_histogram_frames_are_sampled_from_the_histogram_for_weights_trained_so(rng):
    edges = np.linspace(0.0, 4.0, 101, dtype=np.float32)
    counts = np.zeros((8, 8, 100), np.float32)
    counts[..., 50] = 10.0  # every zone: all mass in [2.00, 2.04)
    frame = ZoneFrame(np.full((8, 8), 1.0), np.full((8, 8), 0.5), np.ones((8, 8), bool),
                      hist_edges_m=edges, hist_counts=counts)
    net = ZonePainterNet()
    net.contract_values["histogram_hypotheses"] = True
    hyp = DepthEstimator(net, weights="x").hypotheses_for(frame)
    assert hyp.shape == (64, 16)
    # The Gaussian (mean 1, sigma 0.5) would spread far; the histogram keeps them in the bin.
    assert float(hyp.min()) >= 2.0 and float(hyp.max()) <= 2.04 + 1e-6


def test_gaussian_hypotheses_are_icdf_quantiles(rng):
    frame = random_frame(rng, invalid=2)
    hyp = DepthEstimator(ZonePainterNet(), weights="x").hypotheses_for(frame)
    mean, sigma, valid = frame.flat()
    from scipy.stats import norm

    probs = np.linspace(1e-3, 1 - 1e-3, 16)
    expected = mean[:, None] + sigma[:, None] * norm.ppf(probs)[None]
    np.testing.assert_allclose(hyp[valid], expected[valid], atol=1e-5)
    assert np.all(hyp[~valid] == 0)


def test_calibration_places_zones_and_must_match_resolution(rng):
    intr = CameraIntrinsics(80.0, 80.0, 47.5, 31.5, 96, 64)
    calib = RigCalibration(intr, SensorExtrinsics(translation_m=np.array([0.03, 0.0, 0.0])))
    frame = random_frame(rng, invalid=0)
    estimator = DepthEstimator(ZonePainterNet(), weights="x")
    pred = estimator.predict(random_image(rng, 64, 96), frame, calib)
    np.testing.assert_allclose(pred.zone_rects, calib.zone_rects_for(frame, (64, 96)))
    assert pred.intrinsics == intr
    with pytest.raises(ValueError, match="calibrated resolution"):
        estimator.predict(random_image(rng, 48, 96), frame, calib)


def test_a_calibration_with_distortion_predicts_on_the_undistorted_image(rng):
    intr = CameraIntrinsics(80.0, 80.0, 47.5, 31.5, 96, 64)
    calib = RigCalibration(intr, SensorExtrinsics(), distortion=(-0.3, 0.1, 0.0, 0.0))
    estimator = DepthEstimator(ZonePainterNet(), weights="x")
    seen = []
    prepare = estimator.prepare
    estimator.prepare = lambda images, *a, **k: seen.extend(images) or prepare(images, *a, **k)
    image = random_image(rng, 64, 96)
    estimator.predict(image, random_frame(rng), calib)
    np.testing.assert_array_equal(seen[0], calib.undistort_image(image))
    assert np.abs(seen[0].astype(int) - image).mean() > 10  # the lens model did move pixels
    # An image undistorted already is predicted with the undistorted camera's calibration
    # (same intrinsics, no distortion): the same depth, without undistorting it again.
    pinhole = calib.undistorted()
    assert pinhole.intrinsics == intr and not pinhole.has_distortion
    frame = random_frame(rng)
    once = estimator.predict(calib.undistort_image(image), frame, pinhole)
    np.testing.assert_allclose(once.depth_m, estimator.predict(image, frame, calib).depth_m,
                               rtol=1e-6)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((64, 96), np.uint8), "image"),
    (np.zeros((64, 96, 3), np.float32), "uint8"),
    (np.zeros((64, 96, 4), np.uint8), "image"),
])
def test_bad_images_raise(bad, match, rng):
    estimator = DepthEstimator(ZonePainterNet(), weights="x")
    with pytest.raises(ValueError, match=match):
        estimator.predict(bad, random_frame(rng))


def test_batch_errors_name_the_problem(rng):
    estimator = DepthEstimator(ZonePainterNet(), weights="x")
    with pytest.raises(ValueError, match="one image size"):
        estimator.predict([random_image(rng, 64, 96), random_image(rng, 32, 96)],
                          [random_frame(rng)] * 2)
    with pytest.raises(ValueError, match="one zone frame per image"):
        estimator.predict([random_image(rng, 64, 96)] * 2, [random_frame(rng)])
    with pytest.raises(ValueError, match="grid"):
        estimator.predict([random_image(rng, 64, 96)] * 2,
                          [random_frame(rng), random_frame(rng, grid=4)])


def test_constructor_options_are_checked(lite_model):
    with pytest.raises(ValueError, match="precision"):
        DepthEstimator(lite_model, precision="int8")
    with pytest.raises(ValueError, match="multiples of 32"):
        DepthEstimator(lite_model, input_size=(60, 96))
    with pytest.raises(ValueError, match="exactly one"):
        DepthEstimator()


def _layout(height: int, width: int, grid: int = 8) -> np.ndarray:
    """An asymmetric (Z, 4) layout in image pixels: zones shifted right of centre."""
    side = 0.8 * min(height, width) / grid
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    y0 = 0.1 * height + rows.ravel() * side
    x0 = 0.3 * width + cols.ravel() * side
    return np.stack([y0, x0, y0 + side, x0 + side], axis=1).astype(np.float32)


def test_flip_average_keeps_a_mirror_symmetric_prediction(lite_model, rng):
    # The untrained zone-prior head returns the zone prior, which depends on the zone
    # geometry only through mirror-symmetric Gaussians: a correct mirror of rectangles
    # and zone order gives back the same depth; a one-pixel error would not.
    image, frame = random_image(rng, 64, 96), random_frame(rng)
    rects = _layout(64, 96)
    plain = DepthEstimator(lite_model, weights="test").predict(image, frame, zone_rects=rects)
    flipped = DepthEstimator(lite_model, weights="test", flip_average=True).predict(
        image, frame, zone_rects=rects)
    np.testing.assert_allclose(flipped.depth_m, plain.depth_m, rtol=1e-5)
    np.testing.assert_allclose(flipped.uncertainty_m, plain.uncertainty_m, rtol=1e-4)


def test_flip_average_is_mirror_equivariant(rng):
    from deltar.models import create_model
    from deltar.sensor.geometry import mirror_zone_rects

    torch.manual_seed(1)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    with torch.no_grad():  # a head that is not zero, so the image matters
        model.head.logits_conv.weight.normal_(0.0, 0.5)
    image, frame, rects = random_image(rng, 64, 96), random_frame(rng), _layout(64, 96)
    mirrored_frame = ZoneFrame(frame.mean_m[:, ::-1], frame.sigma_m[:, ::-1],
                               frame.valid[:, ::-1])
    mirrored_rects = mirror_zone_rects(rects, 96, 8)
    plain = DepthEstimator(model, weights="test")
    averaged = DepthEstimator(model, weights="test", flip_average=True)
    original = averaged.predict(image, frame, zone_rects=rects)
    mirrored = averaged.predict(image[:, ::-1].copy(), mirrored_frame,
                                zone_rects=mirrored_rects)
    np.testing.assert_allclose(mirrored.depth_m[:, ::-1], original.depth_m, rtol=1e-4)
    single = plain.predict(image, frame, zone_rects=rects)
    assert np.abs(single.depth_m - original.depth_m).max() > 1e-3  # the flip did something
    assert (original.uncertainty_m >= 0).all()


def test_flip_average_needs_the_pytorch_backend():
    with pytest.raises(ValueError, match="flip_average"):
        DepthEstimator(onnx_model=object(), flip_average=True)


@pytest.mark.parametrize("threads", [1, 2, 4])
def test_official_estimator_keeps_release_parity(tmp_path, parity_fixture, threads):
    """The estimator's network (every inference optimisation on) reproduces the release."""
    from deltar.contract import normalise_image
    from deltar.models.benchmark import DEPTH_TOLERANCE_M, EDGE_TOLERANCE_M

    weights = tmp_path / "nyu.pt"
    torch.save({k: v.float() for k, v in parity_fixture["state_dict"].items()}, weights)
    estimator = load_estimator(weights, kind="official")
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in estimator.model.modules())
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for case in parity_fixture["cases"]:
            inputs = {"image": normalise_image(case["image_rgb_uint8"].numpy())[None],
                      "hypotheses": case["zone_samples_icdf16"][None].float().numpy(),
                      "zone_rects": case["zone_rects_yxyx"][None].float().numpy(),
                      "zone_valid": case["zone_valid"][None].bool().numpy()}
            depth, _ = estimator.run_network(inputs)
            expected = case["expected_depth_half_res"].numpy()
            error = np.abs(depth[0, 0] - expected).max()
            assert error < DEPTH_TOLERANCE_M, f"{case['name']}: {error} m"
            with torch.inference_mode():
                edges = estimator.model(*map(torch.from_numpy, inputs.values()))["bin_edges"][0]
            edge_error = (edges - case["expected_bin_edges"]).abs().max().item()
            assert edge_error < EDGE_TOLERANCE_M, f"{case['name']}: edges {edge_error} m"
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize("flip_average", [False, True])
def test_no_target_zones_of_a_frame_reach_the_plane_select_head(rng, flip_average):
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96))
    estimator = DepthEstimator(model, weights="test", flip_average=flip_average)
    image = random_image(rng, 64, 96)
    valid = np.ones((8, 8), bool)
    valid[:, 5:] = False  # the right columns see nothing within range
    mean = np.where(valid, 1.5, 0.0)
    plain = ZoneFrame(mean_m=mean, sigma_m=np.full((8, 8), 0.02), valid=valid)
    far = ZoneFrame(mean_m=mean, sigma_m=np.full((8, 8), 0.02), valid=valid,
                    no_target=~valid)
    depth_plain = estimator.predict(image, plain).depth_m
    depth_far = estimator.predict(image, far).depth_m
    assert np.allclose(depth_plain, 1.5, rtol=0.05)
    # The no-target side goes to 5 m; the measured side keeps its reading; mirrored
    # flags in the flipped pass give the same picture as no flip.
    assert depth_far[:, -10:].mean() > 4.5
    np.testing.assert_allclose(depth_far[:, :20], 1.5, rtol=0.1)
    single = DepthEstimator(model, weights="test").predict(image, far).depth_m
    assert np.abs(depth_far - single).mean() < 0.05


def _far_column_reading(rng):
    """A select model carrying the rule at 2.5 m, an image, and a frame without flags
    whose right columns returned nothing beside a column reading 3 m (mean, sigma,
    valid as (8, 8) arrays)."""
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96))
    model.set_output_contract(no_target_min_neighbour_m=2.5)
    valid = np.ones((8, 8), bool)
    valid[:, 6:] = False
    mean = np.where(valid, 1.5, 0.0)
    mean[:, 5] = 3.0
    return model, random_image(rng, 64, 96), (mean, np.full((8, 8), 0.02), valid)


def test_a_frame_without_flags_gets_them_by_the_weights_rule(rng):
    model, image, (mean, sigma, valid) = _far_column_reading(rng)
    unflagged = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid)
    flagged = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid, no_target=~valid)
    estimator = DepthEstimator(model, weights="test")
    assert estimator.no_target_min_neighbour_m == 2.5
    np.testing.assert_allclose(estimator.predict(image, unflagged).depth_m,
                               estimator.predict(image, flagged).depth_m, atol=1e-5)
    inferred = estimator.predict(image, unflagged)
    assert inferred.depth_m[:, -8:].mean() > 4.0
    # The prediction says which flags it used (the panel draws them).
    np.testing.assert_array_equal(inferred.zone_no_target, (~valid).reshape(-1))
    # None: a frame without flags has no zone read as no target.
    plain = DepthEstimator(model, weights="test", no_target_min_neighbour_m=None)
    assert plain.predict(image, unflagged).depth_m[:, -8:].mean() < 3.5
    with pytest.raises(ValueError, match="no_target_min_neighbour_m"):
        DepthEstimator(model, weights="test", no_target_min_neighbour_m=-1.0)


def test_a_batch_mixing_frames_with_and_without_flags_keeps_each_frames_own(rng):
    model, image, (mean, sigma, valid) = _far_column_reading(rng)
    unflagged = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid)
    # Flags carried, none set: these invalid zones are failed readings, not far.
    none_far = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid,
                         no_target=np.zeros((8, 8), bool))
    estimator = DepthEstimator(model, weights="test")
    batch = estimator.predict([image, image], [unflagged, none_far])
    for result, frame in zip(batch, (unflagged, none_far), strict=True):
        np.testing.assert_allclose(result.depth_m, estimator.predict(image, frame).depth_m,
                                   atol=1e-4)
    assert batch[0].depth_m[:, -8:].mean() > 4.0 > batch[1].depth_m[:, -8:].mean()


def test_zones_disagreeing_with_all_neighbours_are_set_aside_by_the_weights_rule(rng):
    from deltar.models import create_model
    from deltar.sensor.zone_outliers import OutlierRule

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96))
    model.set_output_contract(zone_outlier_rule=OutlierRule(0.05, min_zones=3).to_dict())
    image = random_image(rng, 64, 96)
    mean = np.full((8, 8), 2.0)
    spikes = ((2, 2), (2, 5), (5, 3))
    for row, col in spikes:
        mean[row, col] = 2.6  # a noisy sensor's outliers on a flat wall
    frame = ZoneFrame(mean_m=mean, sigma_m=np.full((8, 8), 0.02), valid=np.ones((8, 8), bool),
                      no_target=np.zeros((8, 8), bool))
    screened = DepthEstimator(model, weights="test")
    assert screened.zone_outliers == OutlierRule(0.05, min_zones=3)
    result = screened.predict(image, frame)
    expected = np.zeros((8, 8), bool)
    expected[tuple(zip(*spikes, strict=True))] = True
    np.testing.assert_array_equal(result.zone_rejected, expected.reshape(-1))
    assert result.zones_used == 61 and not result.zone_frame.valid[2, 2]
    kept = DepthEstimator(model, weights="test", zone_outliers=None).predict(image, frame)
    assert kept.zone_rejected is None and kept.zones_used == 64
    # Over a rejected zone the depth follows its neighbours, not its reading.
    y0, x0, y1, x1 = np.round(result.zone_rects[2 * 8 + 2]).astype(int)
    screened_depth = float(np.median(result.depth_m[y0:y1, x0:x1]))
    kept_depth = float(np.median(kept.depth_m[y0:y1, x0:x1]))
    assert abs(screened_depth - 2.0) < 0.05 and kept_depth > screened_depth + 0.1
    # A frame with fewer outliers than the rule asks for is kept whole.
    mean[5, 3] = 2.0
    few = ZoneFrame(mean_m=mean, sigma_m=frame.sigma_m, valid=frame.valid,
                    no_target=frame.no_target)
    assert not screened.predict(image, few).zone_rejected.any()


def test_the_depth_moves_to_reproduce_the_zones_readings_as_the_weights_say(rng):
    from deltar.models import create_model

    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96))
    model.set_output_contract(zone_consistency=1.0)
    image = random_image(rng, 64, 96)
    mean = 2.0 + 0.1 * (np.indices((8, 8)).sum(axis=0) % 2)  # a checkerboard of readings
    frame = ZoneFrame(mean_m=mean, sigma_m=np.full((8, 8), 0.02), valid=np.ones((8, 8), bool))
    consistent = DepthEstimator(model, weights="test", blend=None)
    plain = DepthEstimator(model, weights="test", blend=None, zone_consistency=0.0)
    assert consistent.zone_consistency == 1.0 and plain.zone_consistency == 0.0

    def misfit(result) -> float:
        """Mean |log(reading / mean depth over the zone's footprint)| over the zones."""
        gaps = []
        for zone, (y0, x0, y1, x1) in enumerate(np.ceil(result.zone_rects).astype(int)):
            cells = result.depth_m[max(y0, 0):y1, max(x0, 0):x1]
            if cells.size:
                gaps.append(abs(np.log(mean.flat[zone] / cells.mean())))
        return float(np.mean(gaps))

    before, after = misfit(plain.predict(image, frame)), misfit(consistent.predict(image, frame))
    # Smoothed between zone centres, the correction closes part of each gap.
    assert after < 0.85 * before
    with pytest.raises(ValueError, match="zone_consistency"):
        DepthEstimator(model, weights="test", zone_consistency=-0.1)


def test_a_zone_frame_changed_after_it_was_made_is_checked_again(rng):
    """Its fields may be reassigned (the dataclass is not frozen): predict names it."""
    estimator = load_estimator("default", kind="onnx")
    frame = ZoneFrame(np.full((8, 8), 2.0), np.full((8, 8), 0.02), np.ones((8, 8), bool))
    frame.mean_m = frame.mean_m.ravel()
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"^zone_frame: ZoneFrame\.mean_m must have shape"):
        estimator.predict(image, frame)
    with pytest.raises(ValueError, match=r"^zone_frame\[1\]: ZoneFrame\.mean_m"):
        estimator.predict([image, image], [ZoneFrame(np.full((8, 8), 2.0), np.full((8, 8), 0.02),
                                                     np.ones((8, 8), bool)), frame])


@pytest.mark.parametrize("fov", [60.0, (60.0,), (45.0, 45.0, 45.0), ("45", "45"),
                                 (float("nan"), 45.0), (0.0, 45.0), (True, 45.0)])
def test_a_field_of_view_that_is_not_two_angles_is_refused_when_built(lite_model, fov):
    """A single number was a TypeError ('float' object is not iterable), one angle an
    IndexError, NaN an error only at the first predict."""
    with pytest.raises(ValueError, match=r"fov_deg must be two angles in \(0, 180\) degrees"):
        DepthEstimator(lite_model, weights="test", fov_deg=fov)


def test_a_field_of_view_of_numpy_numbers_is_kept(lite_model):
    estimator = DepthEstimator(lite_model, weights="test", fov_deg=np.float32([45.0, 40.0]))
    assert estimator.fov_deg == (45.0, 40.0)
