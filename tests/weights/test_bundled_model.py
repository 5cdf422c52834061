"""The model shipped inside the package: small, the current select recipe, and well behaved.

How accurate it is on rooms it never saw is measured by the leave-one-scene-out protocol
(benchmarks/cross_scene.py, docs/training.md), not here: it was trained on every shared
scene, so no shared frame is unseen by it.
"""

from __future__ import annotations

import numpy as np
import torch

from deltar.camera import CameraIntrinsics
from deltar.data.sources import open_source
from deltar.inference.loading import load_estimator
from deltar.models.checkpoint import load_checkpoint
from deltar.sensor.geometry import zone_rects
from deltar.sensor.simulate import simulate_zone_frame
from deltar.sensor.zone_frame import ZoneFrame
from deltar.weights import resolve_checkpoint


def test_default_is_a_small_float16_select_model_with_its_input_contract():
    path = resolve_checkpoint("default")
    assert path.stat().st_size <= 20 * 1024 * 1024
    payload = torch.load(path, map_location="cpu", weights_only=False)
    floats = [t for t in payload["state_dict"].values() if t.is_floating_point()]
    assert floats and all(t.dtype == torch.float16 for t in floats)
    model, preset, config = load_checkpoint(path)
    assert preset == "deltar-select" and not model.training
    assert payload["format_version"] == 3  # per-part sections
    inputs, head = config["input"], config["head"]
    assert config["encoder"]["backbone"] == "tf_efficientnet_lite0"
    assert head["name"] == "plane_select" and head["planar"]
    assert config["decoder"]["name"] == "descriptors"
    assert inputs["image_mean"] == (0.5, 0.5, 0.5) and inputs["image_std"] == (0.5, 0.5, 0.5)
    assert inputs["zone_scale_norm"] and inputs["design_size"] == (256, 320)
    # Trained on (mean, sigma) hypotheses: frames with histograms are read the same way.
    assert not model.network_config.inputs.histogram_hypotheses


def test_default_carries_its_fitted_blend_and_sigma_calibration():
    from deltar.inference.blend import DEFAULT_BLEND, ConfidenceBlend
    from deltar.inference.uncertainty import UncertaintyCalibration

    estimator = load_estimator("default")
    _, _, config = load_checkpoint(resolve_checkpoint("default"))
    assert estimator.blend == ConfidenceBlend.from_dict(config["output"]["confidence_blend"])
    assert estimator.uncertainty == UncertaintyCalibration.from_dict(
        config["output"]["uncertainty_calibration"])
    # DEFAULT_BLEND (for plane-select files without a blend) is the bundled model's fit.
    for region in ("inside", "outside"):
        ours, default = getattr(estimator.blend, region), getattr(DEFAULT_BLEND, region)
        assert abs(ours.bias - default.bias) < 1e-3
        assert abs(ours.spread_slope - default.spread_slope) < 1e-3
        # Less sure, more fill: the weight falls as the relative spread grows.
        assert ours.spread_slope < 0


def test_default_carries_its_fitted_outlier_rule_and_no_target_depth():
    from deltar.evaluation.uncertainty import NO_TARGET_DEPTH_CANDIDATES_M
    from deltar.sensor.zone_outliers import outlier_rule_from_dict

    estimator = load_estimator("default")
    _, _, config = load_checkpoint(resolve_checkpoint("default"))
    rule = config["output"]["zone_outlier_rule"]
    assert rule is not None and estimator.zone_outliers == outlier_rule_from_dict(rule)
    depth = config["output"]["no_target_depth"]
    assert depth in NO_TARGET_DEPTH_CANDIDATES_M and estimator.no_target_depth_m == depth
    # The head's hypothesis for a no-target zone is the one the fill uses.
    assert estimator.model.head.no_target_depth == depth


def test_default_carries_its_fitted_zone_consistency_in_both_backends():
    from deltar.inference.zone_consistency import STRENGTH_CANDIDATES

    _, _, config = load_checkpoint(resolve_checkpoint("default"))
    strength = config["output"]["zone_consistency"]
    assert strength in STRENGTH_CANDIDATES
    assert load_estimator("default").zone_consistency == strength
    assert load_estimator("default", kind="onnx").zone_consistency == strength


def test_default_keeps_the_sensor_scale_on_a_real_frame(shared_data):
    torch.set_num_threads(2)
    frame = open_source(str(shared_data / "realsense_floor"))[3]
    rects = zone_rects(frame.intrinsics, 8)
    zones = simulate_zone_frame(frame.depth_m, rects)
    estimator = load_estimator("default")
    depth = estimator.predict(frame.image, zones).depth_m
    readings = zones.mean_m[zones.valid]
    # Every pixel is a mean of zone planes, each within 2x of its reading...
    assert depth.min() >= readings.min() / 2 - 1e-3 and depth.max() <= 2 * readings.max() + 1e-3
    # ...and it tracks the readings: the depth averaged over each valid zone is close to
    # the zone's reading (the sensor's scale, not the image's).
    ratios = [depth[max(0, int(y0)):int(y1), max(0, int(x0)):int(x1)].mean() / mean
              for (y0, x0, y1, x1), mean, ok in zip(rects, zones.mean_m.ravel(),
                                                    zones.valid.ravel(), strict=True)
              if ok and y1 > 0 and x1 > 0]
    assert abs(np.median(ratios) - 1.0) < 0.05
    # ...and scaling every reading scales the depth (the scale comes from the sensor).
    # Both frames are rebuilt from mean and sigma alone (the simulated one also carries
    # a histogram, which the hypotheses would be drawn from instead); hypotheses of wide
    # zones near the sensor are clamped at 0 m, hence a tolerance.
    base = ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid)
    scaled = ZoneFrame(zones.mean_m * 0.7, zones.sigma_m * 0.7, zones.valid)
    ratio = estimator.predict(frame.image, scaled).depth_m / (
        estimator.predict(frame.image, base).depth_m * 0.7)
    assert abs(np.median(ratio) - 1.0) < 1e-3
    assert np.percentile(np.abs(ratio - 1.0), 99) < 1e-2


def test_default_runs_large_images_at_its_training_scale(rng):
    estimator = load_estimator("default")
    frame = ZoneFrame(np.full((8, 8), 2.0), np.full((8, 8), 0.05), np.ones((8, 8), bool))
    image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    inputs = estimator.prepare([image], [frame])
    assert tuple(inputs["image"].shape[-2:]) == (256, 320)
    assert estimator.predict(image, frame).depth_m.shape == (480, 640)


def test_default_places_zones_with_no_target_beyond_the_range(shared_data):
    # A real office frame whose window side lies beyond the L5's 4 m: with the zones'
    # no-target flags the default puts those pixels past the range, closer to the truth
    # than without them; the measured zones keep their depth. Without flags the default
    # infers them by the rule it carries (docs/inference.md).
    torch.set_num_threads(2)
    camera = CameraIntrinsics(615.0, 615.0, 320.0, 240.0, width=640, height=480)
    frame = open_source(str(shared_data / "realsense_office"), intrinsics=camera)[0]
    rects = zone_rects(frame.intrinsics, 8)
    zones = simulate_zone_frame(frame.depth_m, rects)
    assert zones.no_target.sum() >= 4
    estimator = load_estimator("default")
    flagged = estimator.predict(frame.image, ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid,
                                                       no_target=zones.no_target)).depth_m
    unflagged = ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid)
    plain = load_estimator("default", no_target_min_neighbour_m=None).predict(
        frame.image, unflagged).depth_m
    # A frame without flags gets them from the rule the default carries.
    inferred = estimator.predict(frame.image, unflagged).depth_m
    truth = frame.depth_m
    far = np.zeros(truth.shape, bool)
    for (y0, x0, y1, x1), flag in zip(rects, zones.no_target.ravel(), strict=True):
        if flag:
            top, left, bottom, right = np.ceil([y0, x0, y1, x1]).astype(int).clip(0)
            far[top:bottom, left:right] = True
    seen = far & (truth > 0)
    assert np.median(flagged[seen]) > 4.0 > np.median(plain[seen])
    rel = {name: np.mean(np.abs(d[seen] - truth[seen]) / truth[seen])
           for name, d in (("flagged", flagged), ("plain", plain), ("inferred", inferred))}
    assert rel["flagged"] < 0.7 * rel["plain"]
    # Inferred flags recover most of what the sensor's own flags give.
    assert np.median(inferred[seen]) > 4.0 and rel["inferred"] < 0.8 * rel["plain"]
    # Over each valid zone, the depth stays what it was (median ratio within 2%).
    ratios = []
    for (y0, x0, y1, x1), ok in zip(rects, zones.valid.ravel(), strict=True):
        top, left, bottom, right = np.ceil([y0, x0, y1, x1]).astype(int).clip(0)
        if ok and bottom > top and right > left:
            ratios.append(flagged[top:bottom, left:right].mean() /
                          plain[top:bottom, left:right].mean())
    assert abs(np.median(ratios) - 1.0) < 0.02
