"""Tests of the zone simulator (deltar.sensor.simulate)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from deltar.sensor import (
    SimulatorConfig,
    ZoneFrame,
    simulate_zone_frame,
    simulate_zones,
    training_zone_rects,
    zone_rects_to_pixel_bounds,
)
from deltar.sensor import compiled as compiled_kernels
from deltar.sensor.simulate import strongest_cluster
from deltar.sensor.zone_histograms import zone_histograms

from .loop_reference import simulate_zones_loop

BIN = 0.04


def _one_zone(depth: np.ndarray) -> tuple[float, float, bool]:
    """Simulate a single zone covering the whole (H, W) map."""
    h, w = depth.shape
    out = simulate_zones(torch.from_numpy(depth.astype(np.float32)),
                         torch.tensor([[-0.5, -0.5, h - 0.5, w - 0.5]]))
    return float(out.mean_m[0]), float(out.sigma_m[0]), bool(out.valid[0])


def _read_depth_mm(path) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None, f"could not read {path}"
    depth = raw.astype(np.float32) / 1000.0
    depth[(raw == 0) | (raw == 65535)] = 0.0
    return depth


def test_flat_wall_gives_bin_centre_and_zero_sigma():
    # 1.50 m lies inside bin [1.48, 1.52): every pixel in one bin, centre 1.50 m.
    mean, sigma, valid = _one_zone(np.full((40, 50), 1.50))
    assert valid
    assert mean == pytest.approx(1.50, abs=1e-6)
    assert sigma == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("depth", [0.37, 1.234, 2.5, 3.71])
def test_flat_wall_mean_within_half_a_bin(depth):
    mean, sigma, valid = _one_zone(np.full((30, 30), depth))
    assert valid
    assert abs(mean - depth) <= BIN / 2 + 1e-6
    assert sigma < 1e-6


def test_slanted_wall_mean_and_sigma_match_the_depth_spread():
    # Depth ramps linearly over 1.0..1.4 m across columns: 10 bins of equal counts.
    depth = np.tile(np.linspace(1.0, 1.4, 400, endpoint=False), (30, 1))
    mean, sigma, valid = _one_zone(depth)
    assert valid
    assert mean == pytest.approx(1.2, abs=BIN / 2)
    # A uniform spread of width 0.4 m has std 0.4 / sqrt(12) = 0.115 m.
    assert sigma == pytest.approx(0.4 / np.sqrt(12), abs=0.01)


def test_two_surfaces_pick_the_stronger_one():
    depth = np.full((20, 50), 1.02)  # 600 px near, 400 px far
    depth[12:] = 2.02
    mean, sigma, valid = _one_zone(depth)
    assert valid
    assert mean == pytest.approx(1.02, abs=1e-6)
    assert sigma == pytest.approx(0.0, abs=1e-6)


def test_cluster_strength_is_the_total_of_contiguous_bins_after_the_floor():
    # Near surface: 5 consecutive bins x 100 px -> (100 - 20) * 5 = 400 counts.
    # Far surface: one bin x 300 px -> 280 counts, the higher peak but the weaker cluster.
    near_centres = 1.02 + BIN * np.arange(5)
    depth = np.concatenate([np.repeat(near_centres, 100), np.full(300, 3.02)]).reshape(10, 80)
    mean, sigma, valid = _one_zone(depth)
    assert valid
    assert mean == pytest.approx(near_centres.mean(), abs=1e-5)
    assert sigma == pytest.approx(np.std(near_centres), abs=1e-5)


def test_an_empty_bin_splits_clusters():
    # Bins 25 and 27 (1.02 m, 1.10 m) are not adjacent: two clusters, the larger one wins.
    depth = np.concatenate([np.full(300, 1.02), np.full(200, 1.10)]).reshape(10, 50)
    mean, _, _ = _one_zone(depth)
    assert mean == pytest.approx(1.02, abs=1e-6)
    # A bin with at most 20 px is empty after the floor, so it does not join its neighbours.
    depth = np.concatenate([np.full(300, 1.02), np.full(20, 1.06), np.full(200, 1.10)])
    mean, _, _ = _one_zone(depth.reshape(10, 52))
    assert mean == pytest.approx(1.02, abs=1e-6)


def test_noise_floor_decides_validity():
    depth = np.zeros((10, 10))
    depth.flat[:20] = 2.02
    assert not _one_zone(depth)[2]  # 20 px - 20 = nothing left
    depth.flat[:21] = 2.02
    mean, _, valid = _one_zone(depth)
    assert valid and mean == pytest.approx(2.02, abs=1e-6)


def test_first_bin_and_zero_depth_are_ignored():
    depth = np.full((20, 20), 0.02)  # all in the first bin (< 4 cm)
    assert not _one_zone(depth)[2]
    depth[:, :10] = 0.0  # invalid pixels
    depth[:, 10:] = 0.70
    mean, _, valid = _one_zone(depth)
    assert valid and mean == pytest.approx(0.70, abs=BIN / 2)


def test_beyond_range_is_invalid_and_max_range_is_the_last_bin():
    assert not _one_zone(np.full((20, 20), 4.5))[2]
    mean, _, valid = _one_zone(np.full((20, 20), 4.0))
    assert valid and mean == pytest.approx(3.98, abs=1e-6)


def test_zones_beyond_the_range_report_no_target_and_empty_zones_do_not():
    depth = torch.zeros(40, 80)
    depth[:, :20] = 1.5  # a wall in range: valid
    depth[:, 20:40] = 6.0  # all beyond the range: no target
    depth[:, 40:52] = 6.0  # mostly beyond, a strip in range too thin for a reading
    depth[:, 52:60] = 2.0
    depth[:, 60:80] = 0.0  # no depth at all (a hole): no information, not "far"
    depth[0, 60:75] = 2.0  # a few in-range pixels, too few for a reading
    rects = torch.tensor([[0.0, 0.0, 40.0, 20.0], [0.0, 20.0, 40.0, 40.0],
                          [0.0, 40.0, 2.0, 60.0], [0.0, 60.0, 40.0, 80.0]])
    out = simulate_zones(depth, rects)
    assert out.valid.tolist() == [True, False, False, False]
    assert out.no_target.tolist() == [False, True, True, False]
    # One rule for a batch and for the zone frame.
    batch = simulate_zones(depth.expand(2, -1, -1), rects)
    assert batch.no_target.tolist() == [[False, True, True, False]] * 2
    frame = simulate_zone_frame(depth.numpy(), np.tile(rects.numpy(), (4, 1)))
    assert frame.flat_no_target().tolist() == [False, True, True, False] * 4


def test_zone_outside_the_image_is_invalid():
    depth = torch.full((48, 64), 1.5)
    rects = torch.tensor([[-30.0, -40.0, -5.0, -10.0],  # above-left of the image
                          [10.0, 70.0, 30.0, 90.0],  # right of the image
                          [10.0, 10.0, 30.0, 30.0]])
    out = simulate_zones(depth, rects)
    assert out.valid.tolist() == [False, False, True]
    assert out.histogram[:2].sum() == 0
    assert out.mean_m[:2].tolist() == [0.0, 0.0] and out.sigma_m[:2].tolist() == [0.0, 0.0]


def test_partially_outside_zone_counts_only_pixels_inside():
    depth = torch.full((48, 64), 1.5)
    out = simulate_zones(depth, torch.tensor([[-10.0, -10.0, 10.0, 10.0]]))
    assert out.histogram.sum() == 100  # rows 0..9, cols 0..9


def test_configurable_parameters():
    depth = np.full((10, 10), 1.02)
    depth[:, 5:] = 1.07  # 50 px each; with a floor of 60 nothing is left
    cfg = SimulatorConfig(noise_floor_counts=60.0)
    out = simulate_zones(torch.from_numpy(depth).float(), torch.tensor([[0.0, 0.0, 10.0, 10.0]]),
                         cfg)
    assert not bool(out.valid[0])
    cfg = SimulatorConfig(bin_width_m=0.1, max_range_m=2.0, noise_floor_counts=0.0)
    out = simulate_zones(torch.from_numpy(depth).float(), torch.tensor([[0.0, 0.0, 10.0, 10.0]]),
                         cfg)
    assert out.histogram.shape == (1, 20)
    assert float(out.mean_m[0]) == pytest.approx(1.05, abs=1e-6)  # both in bin [1.0, 1.1)
    assert not bool(simulate_zones(torch.full((5, 5), 2.5), torch.tensor([[0.0, 0, 5, 5]]),
                                   cfg).valid[0])


def test_strongest_cluster_by_hand():
    # Run totals 7, 8 and 9: the long flat run wins over the highest peak.
    counts = torch.tensor([[0.0, 3, 4, 0, 8, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1],
                           [0.0, 2, 0, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],  # tie: first run
                           [0.0] * 15])
    kept = strongest_cluster(counts)
    assert kept[0].tolist() == [0.0] * 6 + [1.0] * 9
    assert kept[1].tolist() == [0.0, 2] + [0.0] * 13
    assert kept[2].sum() == 0


def test_vectorised_equals_per_zone_loop_on_random_zones(rng):
    depth = rng.uniform(0.0, 4.5, size=(60, 80)).astype(np.float32)
    depth[rng.random((60, 80)) < 0.1] = 0.0
    # Smooth regions so clusters span several bins, plus random overlapping rects.
    depth[:30, :40] = np.linspace(0.5, 1.5, 40, dtype=np.float32)
    rects = np.empty((64, 4), dtype=np.float32)
    rects[:, :2] = rng.uniform(-20, 70, size=(64, 2))
    rects[:, 2:] = rects[:, :2] + rng.uniform(0, 40, size=(64, 2))
    out = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects),
                         SimulatorConfig(noise_floor_counts=2.0))
    mean, sigma, valid, hist = simulate_zones_loop(depth, rects, noise_floor_counts=2.0)
    assert np.array_equal(out.histogram.numpy(), hist)
    assert np.array_equal(out.valid.numpy(), valid)
    assert 0 < valid.sum() < 64
    np.testing.assert_allclose(out.mean_m.numpy(), mean, atol=1e-6)
    np.testing.assert_allclose(out.sigma_m.numpy(), sigma, atol=1e-6)


def test_vectorised_equals_per_zone_loop_on_real_frames(shared_data):
    paths = [shared_data / "7scenes_redkitchen" / "frame-000000.depth.png",
             shared_data / "icl_livingroom1" / "depth" / "00000.png"]
    depths = np.stack([_read_depth_mm(p) for p in paths])
    rects = training_zone_rects(480, 640, grid=8, zone_px=62) + np.float32(0.3)
    out = simulate_zones(torch.from_numpy(depths), torch.from_numpy(rects))
    for frame, depth in enumerate(depths):
        mean, sigma, valid, hist = simulate_zones_loop(depth, rects)
        assert np.array_equal(out.histogram[frame].numpy(), hist)
        assert np.array_equal(out.valid[frame].numpy(), valid)
        np.testing.assert_allclose(out.mean_m[frame].numpy(), mean, atol=1e-6)
        np.testing.assert_allclose(out.sigma_m[frame].numpy(), sigma, atol=1e-6)


@pytest.mark.parametrize("relative", ["7scenes_redkitchen/frame-000000.depth.png",
                                      "7scenes_redkitchen/frame-000500.depth.png",
                                      "icl_livingroom1/depth/00100.png",
                                      "realsense_office/depth/depth00002.png"])
def test_real_frames_simulate_sensibly(shared_data, relative):
    path = shared_data / relative
    depth = _read_depth_mm(path)
    rects = training_zone_rects(*depth.shape, grid=8, zone_px=56)
    out = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects))
    assert out.valid.sum() >= 32, f"{path}: only {int(out.valid.sum())} valid zones"
    bounds = zone_rects_to_pixel_bounds(rects, *depth.shape)
    for z in np.flatnonzero(out.valid.numpy()):
        y0, x0, y1, x1 = bounds[z]
        zone = depth[y0:y1, x0:x1]
        zone = zone[(zone > 0) & (zone <= 4.0)]
        assert zone.min() - BIN <= out.mean_m[z] <= zone.max() + BIN
        assert 0 <= out.sigma_m[z] <= (zone.max() - zone.min()) / 2 + BIN


def test_batch_equals_single_frames_and_shared_rects(rng):
    depths = rng.uniform(0.3, 3.0, size=(3, 32, 48)).astype(np.float32)
    rects = training_zone_rects(32, 48, grid=4, zone_px=10)
    batched = simulate_zones(torch.from_numpy(depths), torch.from_numpy(rects),
                             SimulatorConfig(noise_floor_counts=0.0))
    assert batched.mean_m.shape == (3, 16) and batched.histogram.shape == (3, 16, 100)
    for i in range(3):
        single = simulate_zones(torch.from_numpy(depths[i]), torch.from_numpy(rects),
                                SimulatorConfig(noise_floor_counts=0.0))
        assert single.mean_m.shape == (16,)
        assert torch.equal(single.mean_m, batched.mean_m[i])
        assert torch.equal(single.valid, batched.valid[i])
    per_frame_rects = torch.from_numpy(np.stack([rects] * 3))
    again = simulate_zones(torch.from_numpy(depths), per_frame_rects,
                           SimulatorConfig(noise_floor_counts=0.0))
    assert torch.equal(again.sigma_m, batched.sigma_m)


def test_bad_inputs_raise():
    rects = torch.tensor([[0.0, 0.0, 4.0, 4.0]])
    compiled_paths = [False] + ([True] if compiled_kernels.kernels() is not None else [])
    for compiled in compiled_paths:
        # Anywhere in the map, inside a zone or not, NaN or infinite.
        for row, col, value in ((2, 3, float("nan")), (7, 7, float("nan")),
                                (6, 1, float("inf")), (0, 7, -float("inf"))):
            bad = torch.ones(8, 8)
            bad[row, col] = value
            with pytest.raises(ValueError, match="depth_m has NaN or infinite"):
                simulate_zones(bad, rects, compiled=compiled)
    with pytest.raises(ValueError, match="depth_m"):
        simulate_zones(torch.ones(8, 8, dtype=torch.int32), rects)
    with pytest.raises(ValueError, match="depth_m"):
        simulate_zones(torch.ones(8), rects)
    with pytest.raises(ValueError, match="rects"):
        simulate_zones(torch.ones(8, 8), torch.ones(3, 3))
    with pytest.raises(ValueError, match="rects"):
        simulate_zones(torch.ones(8, 8), torch.tensor([[0.0, 0.0, float("nan"), 4.0]]))
    with pytest.raises(ValueError, match="batch"):
        simulate_zones(torch.ones(2, 8, 8), torch.ones(3, 1, 4))


def test_simulate_zone_frame():
    depth = np.full((480, 640), 2.0, dtype=np.float32)
    frame = simulate_zone_frame(depth, training_zone_rects(480, 640, grid=8, zone_px=56),
                                timestamp_s=1.5)
    assert isinstance(frame, ZoneFrame)
    assert frame.grid == 8 and frame.valid.all() and frame.timestamp_s == 1.5
    np.testing.assert_allclose(frame.mean_m, 2.02, atol=1e-6)  # 2.0 m is bin [2.0, 2.04)
    assert frame.hist_counts.shape == (8, 8, 100) and frame.hist_edges_m.shape == (101,)
    assert frame.hist_counts.sum() == 64 * 56 * 56
    frame4 = simulate_zone_frame(depth, training_zone_rects(480, 640, grid=4, zone_px=100))
    assert frame4.grid == 4
    with pytest.raises(ValueError, match="rects"):
        simulate_zone_frame(depth, training_zone_rects(480, 640, grid=6))


@pytest.mark.parametrize("config", [SimulatorConfig(), SimulatorConfig(max_range_m=3.0,
                                                                         bin_width_m=0.05)])
def test_compiled_and_pytorch_cell_counts_are_identical(rng, config):
    # Both paths, on depth that hits bin edges exactly, the range's end, beyond it, zero,
    # negative and huge values, with overlapping zones running past the image; one
    # range a power of two (one product) and one not (product, then division).
    pytest.importorskip("numba")

    edges = config.bin_edges_m().numpy().astype(np.float32)
    depth = rng.uniform(-0.5, config.max_range_m + 0.5, size=(3, 48, 72)).astype(np.float32)
    depth.reshape(-1)[: edges.size] = edges
    depth[0, 0, :4] = [0.0, config.max_range_m, 3e38, -3e38]
    rects = np.empty((3, 64, 4), dtype=np.float32)
    rects[..., :2] = rng.uniform(-10, 60, size=(3, 64, 2))
    rects[..., 2:] = rects[..., :2] + rng.uniform(0, 30, size=(3, 64, 2))
    depth_t, rects_t = torch.from_numpy(depth), torch.from_numpy(rects)
    compiled = zone_histograms(depth_t, rects_t, config, compiled=True)
    reference = zone_histograms(depth_t, rects_t, config, compiled=False)
    assert torch.equal(compiled, reference) and compiled.sum() > 0
    depth_t[1, 5, 5] = float("inf")
    for path in (True, False):
        with pytest.raises(ValueError, match="NaN or infinite"):
            zone_histograms(depth_t, rects_t, config, compiled=path)
    # The whole simulation: clusters (ties, the noise floor, ignored bins) and moments.
    finite = torch.from_numpy(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32))
    for floor in (0.0, 2.0):
        cfg = SimulatorConfig(max_range_m=config.max_range_m, bin_width_m=config.bin_width_m,
                              noise_floor_counts=floor)
        fast = simulate_zones(finite, rects_t, cfg, compiled=True)
        slow = simulate_zones(finite, rects_t, cfg, compiled=False)
        assert torch.equal(fast.histogram, slow.histogram)
        assert torch.equal(fast.cluster, slow.cluster) and torch.equal(fast.valid, slow.valid)
        assert 0 < int(fast.valid.sum()) < fast.valid.numel()
        torch.testing.assert_close(fast.mean_m, slow.mean_m, rtol=0, atol=1e-6)
        torch.testing.assert_close(fast.sigma_m, slow.sigma_m, rtol=0, atol=1e-6)


def test_strongest_cluster_ties_go_to_the_first_run_in_both_paths():
    pytest.importorskip("numba")
    depth = np.zeros((20, 20), np.float32)
    depth[:, :10] = 1.005  # two runs of 200 pixels each: bins 25 and 75 (4 cm bins)
    depth[:, 10:] = 3.005
    rects = torch.tensor([[0.0, 0.0, 20.0, 20.0]])
    for compiled in (True, False):
        out = simulate_zones(torch.from_numpy(depth), rects, compiled=compiled)
        assert out.valid.item() and out.mean_m.item() == pytest.approx(1.0, abs=0.03)


def test_compiled_simulator_without_numba_says_how_to_get_it(monkeypatch):
    from deltar.sensor import compiled

    monkeypatch.setattr(compiled, "kernels", lambda: None)
    with pytest.raises(RuntimeError, match=r"deltar\[fast\]"):
        compiled.cell_counts(np.zeros((1, 2, 2), np.float32), np.zeros((1, 2), np.int64),
                             np.zeros((1, 2), np.int64), 404, 100, 4.0)


def _assert_frame_equals_batched(depth: np.ndarray, rects: np.ndarray,
                                 config: SimulatorConfig | None = None) -> ZoneFrame:
    """The numpy one-frame simulator against the batched PyTorch one (both paths)."""
    frame = simulate_zone_frame(depth, rects, config)
    compiled_paths = [False] + ([True] if compiled_kernels.kernels() is not None else [])
    for compiled in compiled_paths:
        out = simulate_zones(torch.from_numpy(depth), torch.from_numpy(rects), config,
                             compiled=compiled)
        grid = frame.grid
        assert np.array_equal(frame.hist_counts.reshape(grid * grid, -1), out.histogram.numpy())
        assert np.array_equal(frame.valid.reshape(-1), out.valid.numpy())
        assert np.array_equal(frame.no_target.reshape(-1), out.no_target.numpy())
        np.testing.assert_allclose(frame.mean_m.reshape(-1), out.mean_m.numpy(), atol=1e-6,
                                   rtol=0)
        np.testing.assert_allclose(frame.sigma_m.reshape(-1), out.sigma_m.numpy(), atol=1e-6,
                                   rtol=0)
        assert np.array_equal(frame.hist_edges_m, out.bin_edges_m.numpy())
    return frame


@pytest.mark.parametrize("config", [SimulatorConfig(noise_floor_counts=2.0),
                                    SimulatorConfig(max_range_m=3.0, bin_width_m=0.05)])
def test_numpy_frame_simulator_equals_the_batched_one(rng, config):
    depth = rng.uniform(0.0, 4.5, size=(60, 80)).astype(np.float32)
    depth[rng.random((60, 80)) < 0.1] = 0.0
    depth[:30, :40] = np.linspace(0.5, 1.5, 40, dtype=np.float32)
    depth[40:, 60:] = 5.0  # beyond the range: no target
    depth[0, :8] = [0.04, 0.08, 3.0, 4.0, 2.0, -1.0, 1e6, 3.9999]  # edges, end, outliers
    rects = np.empty((64, 4), dtype=np.float32)
    rects[:, :2] = rng.uniform(-20, 70, size=(64, 2))
    rects[:, 2:] = rects[:, :2] + rng.uniform(0, 40, size=(64, 2))
    frame = _assert_frame_equals_batched(depth, rects, config)
    assert 0 < frame.valid.sum() < 64


def test_numpy_frame_simulator_equals_the_batched_one_on_real_frames(shared_data):
    for path in (shared_data / "7scenes_redkitchen" / "frame-000000.depth.png",
                 shared_data / "realsense_office" / "depth" / "depth00002.png"):
        depth = _read_depth_mm(path)
        rects = training_zone_rects(*depth.shape, grid=8, zone_px=62) + np.float32(0.3)
        frame = _assert_frame_equals_batched(depth, rects)
        assert frame.valid.sum() >= 32


def test_numpy_frame_simulator_refuses_bad_input():
    rects = training_zone_rects(32, 32, grid=4, zone_px=8)
    with pytest.raises(ValueError, match="depth_m has NaN"):
        simulate_zone_frame(np.full((32, 32), np.nan, np.float32), rects)
    with pytest.raises(ValueError, match="depth_m"):
        simulate_zone_frame(np.ones((32, 32), np.int32), rects)
    with pytest.raises(ValueError, match="rects has NaN"):
        simulate_zone_frame(np.ones((32, 32), np.float32), np.full((16, 4), np.nan))
