"""The learned detector of biased zones (deltar.sensor.zone_outlier_detector)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_outlier_detector import (
    ZONE_FEATURE_NAMES,
    OutlierDetector,
    fit_outlier_detector,
    zone_outlier_features,
)
from deltar.sensor.zone_outliers import (
    find_outlier_zones,
    outlier_rule_from_dict,
    reject_outlier_zones,
    resolve_outlier_rule,
)

FEATURE = {name: index for index, name in enumerate(ZONE_FEATURE_NAMES)}


def _frame(mean: np.ndarray, valid: np.ndarray | None = None,
           sigma_fraction: float = 0.02) -> ZoneFrame:
    valid = np.ones(mean.shape, bool) if valid is None else valid
    return ZoneFrame(mean_m=np.where(valid, mean, 0.0), sigma_m=np.where(
        valid, sigma_fraction * mean, 0.0), valid=valid)


def test_features_of_a_zone_beyond_a_wall() -> None:
    mean = np.full((8, 8), 2.0)
    mean[3, 4] = 2.2
    features = zone_outlier_features(mean, 0.02 * mean, np.ones((8, 8), bool))
    assert features.shape == (8, 8, len(ZONE_FEATURE_NAMES))
    zone = features[3, 4]
    step = math.log(1.1)
    assert zone[FEATURE["valid_neighbours"]] == 8
    for name in ("nearest_log_difference", "farthest_log_difference",
                 "median_log_difference", "log_difference_to_median_5x5"):
        assert zone[FEATURE[name]] == pytest.approx(step)
    assert zone[FEATURE["fraction_nearer"]] == 1.0
    # 0.2 m apart in units of hypot(0.044, 0.04, 0.01) m.
    expected = 0.2 / math.sqrt(0.044 ** 2 + 0.04 ** 2 + 1e-4)
    assert zone[FEATURE["median_sigma_difference"]] == pytest.approx(expected)
    assert zone[FEATURE["relative_sigma"]] == pytest.approx(0.02)
    assert zone[FEATURE["log_distance"]] == pytest.approx(math.log(2.2))
    assert zone[FEATURE["targets"]] == 1
    # Its neighbour sees it as the one farther zone of eight.
    beside = features[3, 3]
    assert beside[FEATURE["nearest_log_difference"]] == pytest.approx(-step)
    assert beside[FEATURE["median_log_difference"]] == pytest.approx(0.0)
    assert features[0, 0, FEATURE["valid_neighbours"]] == 3  # a corner


def test_features_skip_invalid_zones_and_lone_zones_read_zero() -> None:
    mean = np.full((8, 8), 2.0)
    valid = np.zeros((8, 8), bool)
    valid[4, 4] = True
    features = zone_outlier_features(mean, 0.02 * mean, valid)
    assert np.all(np.isfinite(features))
    assert features[4, 4, FEATURE["valid_neighbours"]] == 0
    assert features[4, 4, FEATURE["nearest_log_difference"]] == 0.0
    valid[4, 5] = True
    mean[4, 6] = 0.5  # invalid: neither counts nor moves anything
    features = zone_outlier_features(mean, 0.02 * mean, valid, np.full((8, 8), 2))
    assert features[4, 4, FEATURE["valid_neighbours"]] == 1
    assert features[4, 5, FEATURE["valid_neighbours"]] == 1
    assert features[4, 5, FEATURE["nearest_log_difference"]] == 0.0
    assert features[4, 4, FEATURE["targets"]] == 2
    # A "valid" reading that is not a finite distance is left out like an invalid one.
    for bad in (np.inf, np.nan, -1.0):
        mean[4, 6] = bad
        valid[4, 6] = True
        odd = zone_outlier_features(mean, 0.02 * np.abs(mean), valid)
        assert np.all(np.isfinite(odd))
        assert odd[4, 5, FEATURE["valid_neighbours"]] == 1, bad
    with pytest.raises(ValueError, match="must all be"):
        zone_outlier_features(mean, mean[:4], valid)


def _threshold_detector(tolerance: float, threshold: float = 0.5) -> OutlierDetector:
    """A hand-made detector whose logit is 100 (nearest log difference - tolerance)."""
    size = len(ZONE_FEATURE_NAMES)
    first = np.zeros((size, 1))
    first[FEATURE["nearest_log_difference"], 0] = 100.0
    return OutlierDetector(np.zeros(size), np.ones(size),
                           ((first, np.array([-100.0 * tolerance])),), threshold)


def test_detector_gives_probabilities_and_sets_aside_the_zones_above_its_threshold() -> None:
    mean = np.full((8, 8), 2.0)
    mean[3, 4] = 2.4
    valid = np.ones((8, 8), bool)
    valid[6, 6] = False
    detector = _threshold_detector(0.1)
    frame = _frame(mean, valid)
    probability = detector.probability(frame)
    assert probability[3, 4] == pytest.approx(1 / (1 + math.exp(-100 * (math.log(1.2) - 0.1))))
    assert probability[6, 6] == 0.0 and probability.max() == probability[3, 4]
    found = detector.find(frame)
    assert found.sum() == 1 and found[3, 4]
    assert not detector.with_threshold(0.9999).find(frame).any()
    no_target = np.zeros(64, bool)
    screened, rejected = reject_outlier_zones(frame, detector, no_target)
    assert rejected.reshape(8, 8)[3, 4] and rejected.sum() == 1
    assert not screened.valid[3, 4] and screened.valid.sum() == frame.valid.sum() - 1
    # Nothing found: the frame itself.
    same, none = reject_outlier_zones(_frame(np.full((8, 8), 2.0)), detector, no_target)
    assert not none.any() and same.valid.all()


def test_detector_round_trips_through_json_and_refuses_bad_dicts() -> None:
    rng = np.random.default_rng(0)
    size = len(ZONE_FEATURE_NAMES)
    layers = ((rng.normal(size=(size, 4)), rng.normal(size=4)),
              (rng.normal(size=(4, 1)), rng.normal(size=1)))
    detector = OutlierDetector(rng.normal(size=size), rng.uniform(0.5, 2, size), layers, 0.7)
    stored = json.loads(json.dumps(detector.to_dict()))
    again = outlier_rule_from_dict(stored)
    assert isinstance(again, OutlierDetector) and again.threshold == 0.7
    assert again == detector and hash(again) == hash(detector)
    assert detector.with_threshold(0.5) != detector and len({again, detector}) == 1
    # It keeps read-only copies: what it is hashed on cannot change under it.
    layers[0][0][0, 0] += 1.0
    assert detector == again and not detector.layers[0][0].flags.writeable
    mean = rng.uniform(1, 3, (8, 8))
    assert np.array_equal(again.probability(_frame(mean)), detector.probability(_frame(mean)))
    assert resolve_outlier_rule("auto", {"zone_outlier_rule": stored}).threshold == 0.7
    with pytest.raises(ValueError, match="exactly the keys"):
        OutlierDetector.from_dict({**stored, "extra": 1})
    with pytest.raises(ValueError, match="threshold"):
        OutlierDetector.from_dict({**stored, "threshold": 1.5})
    with pytest.raises(ValueError, match="layer 1"):
        OutlierDetector.from_dict({**stored, "layers": [stored["layers"][0],
                                                        {"weight": [[1.0]], "bias": [0.0]}]})
    bad = json.loads(json.dumps(stored))
    bad["layers"][0]["weight"][0][0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        OutlierDetector.from_dict(bad)
    with pytest.raises(ValueError, match="feature_mean"):
        OutlierDetector.from_dict({**stored, "feature_mean": [0.0]})


def _room(rng: np.random.Generator) -> ZoneFrame:
    """An 8 x 8 reading of a tilted wall with a nearer box in front: log-planar depth
    (1-4 m) with a step edge, as rooms give at the scale of zones."""
    rows, cols = np.mgrid[0:8, 0:8]
    log_depth = rng.uniform(0.2, 1.2) + rng.normal(0, 0.04) * rows + rng.normal(0, 0.04) * cols
    box = (rows >= rng.integers(2, 6)) & (cols < rng.integers(2, 7))
    log_depth = np.where(box, log_depth - rng.uniform(0.2, 0.6), log_depth)
    mean = np.exp(log_depth)
    return ZoneFrame(mean_m=mean, sigma_m=0.02 * mean, valid=np.ones((8, 8), bool))


def test_a_fitted_detector_finds_biased_zones_the_rule_misses() -> None:
    import torch

    from deltar.sensor.augment import SignalAugmentation

    rng = np.random.default_rng(0)
    rooms = [_room(rng) for _ in range(24)]
    fitted = fit_outlier_detector(rooms, hidden=8, seed=0)
    again = fit_outlier_detector(rooms, hidden=8, seed=0)
    assert np.array_equal(fitted.layers[0][0], again.layers[0][0])  # reproducible
    # New rooms, degraded as the detector learnt (the defaults: 20 % dropped, 30 % of
    # the rest biased by N(0.10, 0.15) m).
    degrade = SignalAugmentation(0.2, 0.3, 0.10, 0.15)
    generator = torch.Generator().manual_seed(1)
    counts = {"biased": 0, "detector": 0, "rule": 0, "clean flagged": 0, "clean zones": 0}
    for _ in range(60):
        clean = _room(rng)
        mean, sigma, valid = (t.numpy().reshape(8, 8) for t in degrade(
            torch.from_numpy(clean.mean_m.reshape(-1)),
            torch.from_numpy(clean.sigma_m.reshape(-1)),
            torch.from_numpy(clean.valid.reshape(-1)), generator))
        biased = valid & (np.abs(np.log(np.maximum(mean, 1e-6) / clean.mean_m)) > 0.1)
        noisy = ZoneFrame(mean_m=mean, sigma_m=sigma, valid=valid)
        counts["biased"] += biased.sum()
        counts["detector"] += (fitted.find(noisy) & biased).sum()
        counts["rule"] += (find_outlier_zones(mean, valid, 0.05) & biased).sum()
        counts["clean flagged"] += fitted.find(clean).sum()
        counts["clean zones"] += clean.valid.sum()
    assert counts["biased"] > 200
    assert counts["detector"] > 0.5 * counts["biased"]
    assert counts["detector"] > 1.5 * counts["rule"]
    assert counts["clean flagged"] < 0.03 * counts["clean zones"]


def test_fit_refuses_what_it_cannot_learn_from() -> None:
    rooms = [_room(np.random.default_rng(0))]
    with pytest.raises(ValueError, match="at least one frame"):
        fit_outlier_detector([])
    with pytest.raises(ValueError, match="draws"):
        fit_outlier_detector(rooms, draws=0)
    with pytest.raises(ValueError, match="no biased zone"):
        fit_outlier_detector(rooms, bias_prob=0.0)
    with pytest.raises(ValueError, match="weight_decay"):
        fit_outlier_detector(rooms, weight_decay=float("nan"))
    with pytest.raises(ValueError, match="threshold"):
        fit_outlier_detector(rooms, threshold=1.0)
