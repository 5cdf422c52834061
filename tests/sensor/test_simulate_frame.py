"""The numpy single-frame simulator (deltar.sensor.simulate_frame) and its batched twin:
several targets per zone (secondary_targets, max_targets)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.sensor import SimulatorConfig, simulate_zone_frame, simulate_zones
from deltar.sensor import compiled as compiled_kernels
from deltar.sensor.simulate_frame import secondary_targets, strongest_run

BIN = 0.04
COMPILED_PATHS = [False] + ([True] if compiled_kernels.kernels() is not None else [])


def _one_zone_rects(height: int, width: int, zones: int = 16) -> np.ndarray:
    """``zones`` identical rectangles covering the whole map (a frame needs 16 or 64)."""
    return np.tile(np.array([[-0.5, -0.5, height - 0.5, width - 0.5]], np.float32),
                   (zones, 1))


def _surfaces(*parts: tuple[float, int], height: int = 40) -> np.ndarray:
    """A depth map of vertical bands: (depth in metres, width in pixels) each."""
    return np.concatenate([np.full((height, width), depth, np.float32)
                           for depth, width in parts], axis=1)


@pytest.mark.parametrize("compiled", COMPILED_PATHS)
def test_two_surfaces_far_apart_are_two_targets_with_their_means(compiled):
    # A depth edge inside the zone: 1.0 m on 60 % of the pixels, 2.5 m on the rest.
    depth = _surfaces((1.0, 30), (2.5, 20))
    rects = _one_zone_rects(*depth.shape)
    zones = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects), max_targets=4,
                           compiled=compiled)
    assert zones.target_mean_m.shape == (16, 4)
    mean, sigma, valid = (t[0].numpy() for t in (zones.target_mean_m, zones.target_sigma_m,
                                                 zones.target_valid))
    assert valid.tolist() == [True, True, False, False]
    assert abs(mean[0] - 1.0) <= BIN / 2 + 1e-6 and abs(mean[1] - 2.5) <= BIN / 2 + 1e-6
    assert np.all(sigma[:2] < 1e-6) and np.all(mean[2:] == 0) and np.all(sigma[2:] == 0)
    frame = simulate_zone_frame(depth, rects, max_targets=4)
    np.testing.assert_allclose(frame.target_mean_m[0, 0], mean, atol=1e-5, rtol=0)
    assert frame.target_valid[0, 0].tolist() == valid.tolist()
    # Signal: the target's share of the zone (its counts after the noise floor) over its
    # squared distance, so that signal * distance^2 gives back the 60 / 40 split.
    for signal in (zones.target_signal[0].numpy(), frame.target_signal[0, 0]):
        area = signal[:2] * mean[:2] ** 2
        np.testing.assert_allclose(area / area.sum(), [0.6, 0.4], atol=0.01)
        assert 0.55 < area.sum() <= 1.0
        assert np.all(signal[2:] == 0)


def test_surfaces_closer_than_the_separation_are_one_target():
    depth = _surfaces((1.0, 30), (1.4, 20))  # 0.4 m apart: one target (ST: < 600 mm)
    rects = _one_zone_rects(*depth.shape)
    frame = simulate_zone_frame(depth, rects, max_targets=4)
    assert frame.target_valid[0, 0].tolist() == [True, False, False, False]
    assert frame.target_mean_m[0, 0, 0] == frame.mean_m[0, 0]
    # With a smaller separation the same zone reports both.
    frame = simulate_zone_frame(depth, rects, SimulatorConfig(target_separation_m=0.3),
                                max_targets=4)
    assert frame.target_valid[0, 0].tolist() == [True, True, False, False]
    assert abs(frame.target_mean_m[0, 0, 1] - 1.4) <= BIN / 2 + 1e-6


def test_secondary_clusters_closer_than_the_separation_merge_into_one_target():
    # Primary at 1.0 m; two weaker clusters at 2.0 and 2.4 m (0.4 m apart) merge into one
    # target at their count-weighted mean, with the spread of both in its sigma.
    depth = _surfaces((1.0, 40), (2.0, 12), (2.4, 8))
    rects = _one_zone_rects(*depth.shape)
    frame = simulate_zone_frame(depth, rects, max_targets=3)
    assert frame.target_valid[0, 0].tolist() == [True, True, False]
    centres = np.array([2.02, 2.42])  # the bins' centres
    weights = np.array([12 * 40 - 20, 8 * 40 - 20], np.float64)  # after the noise floor
    merged = float(np.average(centres, weights=weights))
    spread = float(np.sqrt(np.average((centres - merged) ** 2, weights=weights)))
    assert frame.target_mean_m[0, 0, 1] == pytest.approx(merged, abs=1e-5)
    assert frame.target_sigma_m[0, 0, 1] == pytest.approx(spread, abs=1e-5)


def test_clusters_near_the_primary_are_not_reported_separately():
    # The 1.5 m cluster is 0.5 m from the primary (1.0 m): part of it, not a target;
    # the 3.0 m cluster is reported.
    depth = _surfaces((1.0, 30), (1.5, 10), (3.0, 10))
    frame = simulate_zone_frame(depth, _one_zone_rects(*depth.shape), max_targets=4)
    assert frame.target_valid[0, 0].tolist() == [True, True, False, False]
    assert abs(frame.target_mean_m[0, 0, 1] - 3.0) <= BIN / 2 + 1e-6


def test_target_order_strongest_or_closest_after_the_primary():
    # Primary 3.0 m (most pixels); 2.0 m has more pixels than 1.0 m.
    depth = _surfaces((1.0, 8), (2.0, 14), (3.0, 28))
    rects = _one_zone_rects(*depth.shape)
    for order, expected in (("strongest", [3.0, 2.0, 1.0]), ("closest", [3.0, 1.0, 2.0])):
        frame = simulate_zone_frame(depth, rects, max_targets=4, target_order=order)
        assert frame.target_order == order
        assert frame.target_valid[0, 0].tolist() == [True, True, True, False]
        np.testing.assert_allclose(frame.target_mean_m[0, 0, :3], expected, atol=BIN / 2 + 1e-6)
        zones = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects),
                               max_targets=4, target_order=order)
        np.testing.assert_allclose(zones.target_mean_m[0].numpy(),
                                   frame.target_mean_m[0, 0], atol=1e-5, rtol=0)
    # Fewer slots than targets: the first ones in the order.
    frame = simulate_zone_frame(depth, rects, max_targets=2, target_order="closest")
    np.testing.assert_allclose(frame.target_mean_m[0, 0], [3.0, 1.0], atol=BIN / 2 + 1e-6)


def test_one_target_is_the_default_and_changes_nothing(rng):
    depth = rng.uniform(0.2, 4.5, size=(48, 64)).astype(np.float32)
    depth[:, 30:] = 2.0
    rects = _random_rects(rng, 64, 48, 64)
    frame = simulate_zone_frame(depth, rects)
    assert frame.target_mean_m is None and frame.targets_per_zone == 1
    for compiled in COMPILED_PATHS:
        default = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects),
                                 compiled=compiled)
        assert default.target_mean_m.shape == (64, 1)
        assert torch.equal(default.target_mean_m[:, 0], default.mean_m)
        assert torch.equal(default.target_sigma_m[:, 0], default.sigma_m)
        assert torch.equal(default.target_valid[:, 0], default.valid)
        more = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects), max_targets=4,
                              compiled=compiled)
        for name in ("mean_m", "sigma_m", "valid", "histogram", "cluster", "no_target"):
            assert torch.equal(getattr(more, name), getattr(default, name)), name
        assert torch.equal(more.target_mean_m[:, 0], default.mean_m)
        assert torch.equal(more.target_valid[:, 0], default.valid)


def _random_rects(rng: np.random.Generator, zones: int, height: int, width: int) -> np.ndarray:
    rects = np.empty((zones, 4), dtype=np.float32)
    rects[:, :2] = rng.uniform(-10, max(height, width) - 10, size=(zones, 2))
    rects[:, 2:] = rects[:, :2] + rng.uniform(4, 40, size=(zones, 2))
    return rects


def _banded_depth(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Random vertical bands of random depth (many zones with several surfaces)."""
    edges = np.sort(rng.choice(np.arange(1, width), size=7, replace=False))
    depth = np.empty((height, width), np.float32)
    for start, stop in zip(np.r_[0, edges], np.r_[edges, width], strict=True):
        depth[:, start:stop] = rng.uniform(0.1, 4.4)
    depth += rng.normal(0, 0.03, size=depth.shape).astype(np.float32)
    depth[rng.random(depth.shape) < 0.05] = 0.0
    return depth


@pytest.mark.parametrize("order", ["strongest", "closest"])
def test_numpy_and_torch_twins_report_the_same_targets(rng, order):
    height, width = 60, 80
    depths = np.stack([_banded_depth(rng, height, width) for _ in range(3)])
    rects = _random_rects(rng, 64, height, width)
    config = SimulatorConfig(noise_floor_counts=5.0)
    for compiled in COMPILED_PATHS:
        batch = simulate_zones(torch.from_numpy(depths), torch.from_numpy(rects), config,
                               compiled=compiled, max_targets=4, target_order=order)
        assert batch.target_mean_m.shape == (3, 64, 4)
        for index, depth in enumerate(depths):
            frame = simulate_zone_frame(depth, rects, config, max_targets=4,
                                        target_order=order)
            mean, sigma, valid = frame.flat_targets()
            assert np.array_equal(valid, batch.target_valid[index].numpy())
            np.testing.assert_allclose(mean, batch.target_mean_m[index].numpy(), atol=1e-5,
                                       rtol=0)
            np.testing.assert_allclose(sigma, batch.target_sigma_m[index].numpy(), atol=1e-5,
                                       rtol=0)
            np.testing.assert_allclose(frame.target_signal.reshape(64, 4),
                                       batch.target_signal[index].numpy(), rtol=1e-5,
                                       atol=1e-7)
    assert batch.target_valid[..., 1].sum() > 10  # the test covers second targets


def _reference_targets(cleaned: np.ndarray, centres: np.ndarray, separation: float,
                       count: int, order: str) -> list[list[tuple[float, float]]]:
    """Per-zone loop of the documented rule, for comparison with the vectorised one."""
    out = []
    for counts in cleaned:
        runs, start = [], None
        for index in range(len(counts) + 1):
            if index < len(counts) and counts[index] > 0:
                start = index if start is None else start
            elif start is not None:
                runs.append((start, index))
                start = None
        if not runs:
            out.append([])
            continue
        totals = [float(counts[a:b].astype(np.float64).sum()) for a, b in runs]
        means = [float((counts[a:b] * centres[a:b]).sum() / total)
                 for (a, b), total in zip(runs, totals, strict=True)]
        strongest = int(np.argmax(totals))
        groups: list[list[int]] = []
        for run, run_mean in enumerate(means):
            if run == strongest or abs(run_mean - means[strongest]) < separation:
                continue
            if groups:
                members = groups[-1]
                group_mean = sum(totals[m] * means[m] for m in members) / sum(
                    totals[m] for m in members)
                if run_mean - group_mean < separation:
                    members.append(run)
                    continue
            groups.append([run])
        found = []
        for members in groups:
            bins = np.concatenate([np.arange(*runs[m]) for m in members])
            weights = counts[bins].astype(np.float64)
            mean = float(np.average(centres[bins], weights=weights))
            sigma = float(np.sqrt(np.average((centres[bins] - mean) ** 2, weights=weights)))
            found.append((weights.sum(), mean, sigma))
        if order == "strongest":
            found.sort(key=lambda item: -item[0])  # stable: the closer first on ties
        out.append([(mean, sigma, total) for total, mean, sigma in found[:count]])
    return out


@pytest.mark.parametrize("order", ["strongest", "closest"])
def test_secondary_targets_follow_the_documented_rule(rng, order):
    bins = 100
    cleaned = rng.integers(0, 6, size=(300, bins)).astype(np.float32)
    cleaned[rng.random((300, bins)) < 0.5] = 0.0
    cleaned[:20] = 0.0  # zones without counts
    centres = (np.arange(bins) + 0.5) * BIN
    mean, sigma, valid, counts = secondary_targets(cleaned, strongest_run(cleaned), centres,
                                                   0.6, 3, order)
    expected = _reference_targets(cleaned, centres, 0.6, 3, order)
    for zone, targets in enumerate(expected):
        assert valid[zone].sum() == len(targets)
        for slot, (ref_mean, ref_sigma, ref_total) in enumerate(targets):
            assert counts[zone, slot] == pytest.approx(ref_total, rel=1e-6)
            assert mean[zone, slot] == pytest.approx(ref_mean, abs=1e-6)
            assert sigma[zone, slot] == pytest.approx(ref_sigma, abs=1e-6)
    assert valid[:, 1].sum() > 0


@pytest.mark.parametrize("kwargs, message", [
    (dict(max_targets=0), "max_targets must be an integer in 1..4, got 0"),
    (dict(max_targets=5), "max_targets must be an integer in 1..4, got 5"),
    (dict(max_targets=2.0), "max_targets must be an integer in 1..4, got 2.0"),
    (dict(target_order="nearest"), "target_order must be 'strongest' or 'closest'"),
])
def test_bad_target_options_are_refused(kwargs, message):
    depth = np.ones((16, 16), np.float32)
    rects = _one_zone_rects(16, 16)
    with pytest.raises(ValueError, match=message):
        simulate_zone_frame(depth, rects, **kwargs)
    with pytest.raises(ValueError, match=message):
        simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects), **kwargs)


def test_target_separation_must_be_positive():
    with pytest.raises(ValueError, match="target_separation_m must be > 0"):
        SimulatorConfig(target_separation_m=0.0)
