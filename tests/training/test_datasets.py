"""The training Datasets: SimulatedL5Dataset (item contract, simulated values, seeding,
augmentation geometry) and ZJUL5TrainingDataset (measured zones, flips)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.camera import CameraIntrinsics
from deltar.data.procedural import ProceduralReader
from deltar.data.rgbd import RGBDFrame, open_rgbd
from deltar.data.transforms import ImageAugmentation
from deltar.data.zju_l5 import ZJUL5Dataset, ZJUL5Sample, write_zju_l5
from deltar.sensor.augment import SignalAugmentation
from deltar.training.datasets import SimulatedL5Dataset, ZJUL5TrainingDataset

NO_JITTER = dict(max_rotation_deg=0.0, photometric_prob=0.0)


class _ListReader(list):
    """A reader is any sequence of frames."""


def _frame(depth: np.ndarray, fx: float = 40.0) -> RGBDFrame:
    height, width = depth.shape
    rng = np.random.default_rng(1)
    return RGBDFrame(image=rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
                     depth_m=depth.astype(np.float32),
                     intrinsics=CameraIntrinsics(fx, fx, (width - 1) / 2, (height - 1) / 2,
                                                 width, height),
                     name="synthetic")


def test_item_contract_on_procedural_frames():
    ds = SimulatedL5Dataset(ProceduralReader(2, seed=5, height=64, width=96), num_hypotheses=8)
    item = ds[1]
    shapes = {k: tuple(v.shape) for k, v in item.items()}
    assert shapes == {"image": (3, 64, 96), "image_rgb": (64, 96, 3), "depth": (1, 64, 96),
                      "zone_mean_sigma": (64, 2), "zone_valid": (64,), "zone_no_target": (64,),
                      "zone_rects": (64, 4), "hypotheses": (64, 8), "intrinsics": (4,)}
    assert item["image"].dtype == torch.float32 and item["image_rgb"].dtype == torch.uint8
    assert item["zone_valid"].dtype == torch.bool
    # ImageNet normalisation of the unaugmented image, checked by hand on one pixel.
    rgb = item["image_rgb"][10, 20].double() / 255.0
    expected = (rgb - torch.tensor([0.485, 0.456, 0.406], dtype=torch.float64)) / torch.tensor(
        [0.229, 0.224, 0.225], dtype=torch.float64)
    torch.testing.assert_close(item["image"][:, 10, 20].double(), expected, atol=3e-3, rtol=0)
    valid = item["zone_valid"]
    assert valid.any()
    assert torch.all(item["hypotheses"][~valid] == 0)
    # icdf hypotheses straddle each valid zone's mean.
    means = item["zone_mean_sigma"][valid, 0]
    assert torch.all(item["hypotheses"][valid, 0] <= means)
    assert torch.all(item["hypotheses"][valid, -1] >= means)


def test_flat_wall_gives_bin_centre_and_zero_sigma():
    # A fronto-parallel wall at 1.5 m: every zone sees one 4 cm bin [1.48, 1.52).
    ds = SimulatedL5Dataset(_ListReader([_frame(np.full((64, 64), 1.5))]), grid=4)
    item = ds[0]
    assert bool(item["zone_valid"].all())
    torch.testing.assert_close(item["zone_mean_sigma"][:, 0], torch.full((16,), 1.5))
    torch.testing.assert_close(item["zone_mean_sigma"][:, 1], torch.zeros(16))
    torch.testing.assert_close(item["hypotheses"], torch.full((16, 16), 1.5))
    # Calibrated 45 degree layout: the grid spans 2 * fx * tan(22.5 deg) pixels.
    rects = item["zone_rects"]
    span = float(rects[:, 3].max() - rects[:, 1].min())
    assert span == pytest.approx(2 * 40.0 * np.tan(np.deg2rad(22.5)), rel=1e-5)


def test_no_depth_gives_invalid_zones():
    item = SimulatedL5Dataset(_ListReader([_frame(np.zeros((32, 32)))]), grid=4)[0]
    assert not item["zone_valid"].any() and not item["zone_no_target"].any()
    assert torch.all(item["zone_mean_sigma"] == 0) and torch.all(item["hypotheses"] == 0)


def test_a_scene_scaled_past_the_range_reports_no_target_and_dropping_keeps_the_flags():
    # A wall at 3 m scaled by 2: beyond the 4 m range, every zone reports no target.
    frames = _ListReader([_frame(np.full((64, 64), 3.0))])
    item = SimulatedL5Dataset(frames, grid=4, depth_scale_range=(2.0, 2.0))[0]
    assert not item["zone_valid"].any() and bool(item["zone_no_target"].all())
    # Left half at 1.5 m, right half at 6 m: dropping half of the valid (left) zones
    # leaves them invalid but not "no target"; the right half keeps its flags.
    depth = np.full((64, 64), 1.5)
    depth[:, 32:] = 6.0
    split = _ListReader([_frame(depth)])
    clean = SimulatedL5Dataset(split, grid=4)[0]
    dropped = SimulatedL5Dataset(split, grid=4, signal_augmentation=SignalAugmentation(
        drop_fraction=0.5))[0]
    right = torch.arange(16) % 4 >= 2
    assert torch.equal(clean["zone_valid"], ~right) and torch.equal(clean["zone_no_target"], right)
    assert 0 < int(dropped["zone_valid"].sum()) < 8
    assert torch.equal(dropped["zone_no_target"], right)


def test_reproducible_per_seed_epoch_and_index():
    reader = ProceduralReader(2, seed=0, height=64, width=96)
    kwargs = dict(zone_layout="training", training_grid=4, training_zone_px=12,
                  training_max_offset_px=4, signal_augmentation=SignalAugmentation(),
                  image_augmentation=ImageAugmentation(crop_size=(48, 80)), seed=7)
    a, b = SimulatedL5Dataset(reader, **kwargs), SimulatedL5Dataset(reader, **kwargs)
    first, again = a[0], b[0]
    for key in first:
        torch.testing.assert_close(first[key], again[key])
    draws = []
    for epoch in range(4):
        a.set_epoch(epoch)
        item = a[0]
        draws.append((item["zone_rects"][0].tolist(), item["image_rgb"].float().mean().item()))
    assert len({str(d) for d in draws}) > 1  # epochs draw different augmentations


def test_flip_mirrors_fixed_rects_and_their_order():
    # Zones of 8 px with 4 px gaps; each zone column sees its own depth, with margin, so
    # the geometric mirror (x -> W - 1 - x) keeps every zone on its own depth block.
    width, height, grid = 64, 32, 4
    starts = np.array([8, 20, 32, 44])
    rects = np.array([[8 * r, x, 8 * r + 8, x + 8] for r in range(grid) for x in starts],
                     dtype=np.float32)
    depth = np.full((height, width), 3.8, np.float32)
    for c, x in enumerate(starts):
        depth[:, x - 2:x + 10] = 1.1 + 0.4 * c  # 4 cm bin centres
    reader = _ListReader([_frame(depth)])
    plain = SimulatedL5Dataset(reader, zone_layout=rects)[0]
    flipped = SimulatedL5Dataset(reader, zone_layout=rects, image_augmentation=ImageAugmentation(
        flip_prob=1.0, **NO_JITTER))[0]
    torch.testing.assert_close(flipped["depth"], plain["depth"].flip(-1))
    means = plain["zone_mean_sigma"][:, 0].reshape(grid, grid)
    torch.testing.assert_close(flipped["zone_mean_sigma"][:, 0].reshape(grid, grid),
                               means.flip(-1))
    torch.testing.assert_close(means[0], torch.tensor([1.1, 1.5, 1.9, 2.3]))
    # Zone 0 of the flipped frame is the mirror of zone 3 of the original: its columns
    # 44..51 land on 12..19.
    assert flipped["zone_rects"][0].tolist() == [0.0, 12.0, 8.0, 20.0]
    assert flipped["intrinsics"][2].item() == pytest.approx(width - 1 - (width - 1) / 2)


def test_crop_shifts_fixed_rects_and_intrinsics():
    depth = np.tile(np.linspace(1.0, 3.0, 64, dtype=np.float32), (48, 1))
    rects = np.array([[10, 10, 20, 20]] * 16, dtype=np.float32)
    ds = SimulatedL5Dataset(_ListReader([_frame(depth)]), zone_layout=rects, seed=3,
                            image_augmentation=ImageAugmentation(crop_size=(32, 40), flip_prob=0,
                                                                 **NO_JITTER))
    item = ds[0]
    _fx, _fy, cx, cy = item["intrinsics"].tolist()
    top, left = 23.5 - cy, 31.5 - cx  # principal point moves by the crop offset
    assert top == int(top) and left == int(left)
    assert item["zone_rects"][0].tolist() == [10 - top, 10 - left, 20 - top, 20 - left]
    torch.testing.assert_close(item["depth"][0], torch.from_numpy(
        depth[int(top):int(top) + 32, int(left):int(left) + 40]))


def test_real_folder_item(shared_data):
    reader = open_rgbd(shared_data / "7scenes_redkitchen")
    item = SimulatedL5Dataset(reader)[0]
    valid = item["zone_valid"]
    assert valid.sum() > 32
    means = item["zone_mean_sigma"][valid, 0]
    assert torch.all((means > 0.04) & (means < 4.0))


def test_bad_arguments():
    reader = ProceduralReader(1, height=16, width=16)
    with pytest.raises(ValueError, match="zone_layout"):
        SimulatedL5Dataset(reader, zone_layout="diagonal")
    with pytest.raises(ValueError, match="zone_layout array"):
        SimulatedL5Dataset(reader, zone_layout=np.zeros((5, 4)))
    with pytest.raises(ValueError, match="crop_size"):
        SimulatedL5Dataset(reader, image_augmentation=ImageAugmentation(crop_size=(32, 8)))[0]


def test_batches_through_a_dataloader():
    reader = ProceduralReader(4, seed=2, height=32, width=48)
    ds = SimulatedL5Dataset(reader, zone_layout="training", training_grid=3,
                            training_zone_px=8, num_hypotheses=4)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4)))
    assert batch["image"].shape == (4, 3, 32, 48)
    assert batch["hypotheses"].shape == (4, 9, 4)
    assert batch["zone_valid"].dtype == torch.bool


def _two_plane_depth(height=48, width=64) -> np.ndarray:
    depth = np.full((height, width), 1.5, dtype=np.float32)
    depth[:, width // 2:] = 2.0
    return depth


def test_depth_scale_augmentation_scales_ground_truth_and_zones_together():
    reader = _ListReader([_frame(_two_plane_depth())])
    plain = SimulatedL5Dataset(reader, grid=4, fov_deg=(60.0, 45.0))[0]
    scaled_set = SimulatedL5Dataset(reader, grid=4, fov_deg=(60.0, 45.0),
                                    depth_scale_range=(0.5, 2.0))
    item = scaled_set[0]
    k = float(item["depth"].max() / plain["depth"].max())
    assert 0.5 <= k <= 2.0 and abs(k - 1.0) > 1e-3
    torch.testing.assert_close(item["depth"], plain["depth"] * k)
    valid = plain["zone_valid"] & item["zone_valid"]
    assert valid.sum() >= 8
    # The simulator bins at 4 cm: zone means follow the scene within a bin.
    torch.testing.assert_close(item["zone_mean_sigma"][valid, 0],
                               plain["zone_mean_sigma"][valid, 0] * k, atol=0.04, rtol=0)
    assert torch.equal(item["zone_rects"], plain["zone_rects"])
    with pytest.raises(ValueError, match="depth_scale_range"):
        SimulatedL5Dataset(reader, depth_scale_range=(0.0, 2.0))


def test_layout_jitter_moves_the_rectangles_not_the_readings():
    from deltar.training.datasets import perturb_layout

    reader = _ListReader([_frame(_two_plane_depth())])
    plain = SimulatedL5Dataset(reader, grid=4, fov_deg=(60.0, 45.0))[0]
    jittered = SimulatedL5Dataset(reader, grid=4, fov_deg=(60.0, 45.0), layout_jitter_px=5.0,
                                  layout_rotation_deg=2.0)[0]
    assert torch.equal(jittered["zone_mean_sigma"], plain["zone_mean_sigma"])
    shift = (jittered["zone_rects"] - plain["zone_rects"]).abs()
    assert 0 < shift.max() <= 5.0 + 64 * np.sin(np.deg2rad(2.0))
    # By hand: a 90 degree turn about the centre of a 10 x 10 image, then a shift.
    rects = np.array([[0.0, 6.0, 2.0, 8.0]], dtype=np.float32)  # centre (1, 7)

    class Fixed:
        def uniform(self, low, high, size=None):
            return np.array([1.0, -2.0]) if size == 2 else np.pi / 2 * (180 / np.pi)

    out = perturb_layout(rects, (10, 10), 3.0, 90.0, Fixed())
    # Centre (1, 7) -> relative (-3.5, 2.5) -> rotated (2.5, 3.5) -> (7, 8), shift (1, -2).
    np.testing.assert_allclose(out, [[7.0, 5.0, 9.0, 7.0]], atol=1e-5)
    assert perturb_layout(rects, (10, 10), 0.0, 0.0, Fixed()) is rects


def test_normalisation_follows_the_given_contract():
    reader = _ListReader([_frame(_two_plane_depth())])
    imagenet = SimulatedL5Dataset(reader, grid=4)[0]
    half = SimulatedL5Dataset(reader, grid=4, image_mean=(0.5, 0.5, 0.5),
                              image_std=(0.5, 0.5, 0.5))[0]
    rgb = imagenet["image_rgb"][10, 20].double() / 255.0
    torch.testing.assert_close(half["image"][:, 10, 20].double(), (rgb - 0.5) / 0.5, atol=3e-3,
                               rtol=0)
    assert not torch.allclose(half["image"], imagenet["image"])


def _zju_set(tmp_path, rng):
    grid, height, width = 4, 32, 48
    rects = np.array([[r * 8, c * 12, r * 8 + 8, c * 12 + 12] for r in range(grid)
                      for c in range(grid)], dtype=np.float32)
    mean = rng.uniform(0.5, 3.0, 16).astype(np.float32)
    sigma = rng.uniform(0.01, 0.1, 16).astype(np.float32)
    valid = rng.random(16) > 0.2
    sample = ZJUL5Sample(
        rgb=rng.integers(0, 255, (height, width, 3), dtype=np.uint8),
        depth_m=rng.uniform(0.5, 3.0, (height, width)).astype(np.float32),
        zone_mean_sigma=np.stack([mean, sigma], 1), zone_rects=rects, zone_valid=valid,
        name="scene/00000", zone_no_target=~valid & (np.arange(16) % 4 == 0))
    write_zju_l5(tmp_path / "set", [sample], split="train")
    return ZJUL5Dataset(tmp_path / "set", split="train"), sample


def test_zju_items_use_the_measured_zones_and_flip_consistently(tmp_path, rng):
    samples, sample = _zju_set(tmp_path, rng)
    plain = ZJUL5TrainingDataset(samples, num_hypotheses=5, sampling="uniform")[0]
    flipped = ZJUL5TrainingDataset(samples, num_hypotheses=5, sampling="uniform",
                                   flip_prob=1.0)[0]
    valid = sample.zone_valid
    np.testing.assert_array_equal(plain["zone_valid"].numpy(), valid)
    # Uniform sampling spans mean +- 3 sigma in 5 steps: the middle one is the mean.
    np.testing.assert_allclose(plain["hypotheses"][valid, 2].numpy(),
                               sample.zone_mean_sigma[valid, 0], rtol=1e-6)
    assert torch.all(plain["hypotheses"][~torch.from_numpy(valid)] == 0)
    # Flipped: the image is mirrored and zone (r, c) is the original zone (r, 3 - c),
    # whose rectangle is mirrored about the image width (48 px).
    np.testing.assert_array_equal(flipped["image_rgb"].numpy(), sample.rgb[:, ::-1])
    order = np.arange(16).reshape(4, 4)[:, ::-1].ravel()
    np.testing.assert_array_equal(flipped["zone_valid"].numpy(), valid[order])
    # The no-target flags (written to the file, read back) follow their zones.
    flags = sample.zone_no_target
    assert flags.any()
    np.testing.assert_array_equal(plain["zone_no_target"].numpy(), flags)
    np.testing.assert_array_equal(flipped["zone_no_target"].numpy(), flags[order])
    np.testing.assert_allclose(flipped["hypotheses"].numpy(), plain["hypotheses"].numpy()[order])
    rows = flipped["zone_rects"].numpy()[:, [0, 2]]
    np.testing.assert_array_equal(rows, sample.zone_rects[order][:, [0, 2]])


def test_flipped_zone_rects_cover_the_mirrored_pixels(tmp_path, rng):
    samples, sample = _zju_set(tmp_path, rng)
    flipped = ZJUL5TrainingDataset(samples, num_hypotheses=5, flip_prob=1.0)[0]
    order = np.arange(16).reshape(4, 4)[:, ::-1].ravel()
    # Zone [0, 12) holds pixel columns 0..11; mirrored in a 48 px image: 36..47 = [36, 48).
    rect = flipped["zone_rects"].numpy()
    np.testing.assert_allclose(rect[:, 1], 48 - sample.zone_rects[order, 3])
    np.testing.assert_allclose(rect[:, 3], 48 - sample.zone_rects[order, 1])


def test_several_targets_per_zone_reach_the_items_as_the_sensor_reports_them():
    # Two walls 1.5 m and 3 m away: the zones on the seam see both.
    depth = np.full((64, 64), 1.5, dtype=np.float32)
    depth[:, 29:] = 3.0
    reader = _ListReader([_frame(depth)])
    single = SimulatedL5Dataset(reader, grid=4)[0]
    assert "zone_targets" not in single
    item = SimulatedL5Dataset(reader, grid=4, max_targets=4)[0]
    targets = item["zone_targets"]
    assert tuple(targets.shape) == (16, 2, 2)
    # Slot 0 is the primary reading; the seam zones' second slot is the other wall.
    torch.testing.assert_close(targets[:, 0, 0], item["zone_mean_sigma"][:, 0])
    second = targets[:, 1, 0] > 0
    assert second.any() and not second.all()
    assert torch.all((targets[second, 1, 0] - 3.0).abs() < 0.1)
    torch.testing.assert_close(targets[second].sum(dim=1)[:, 1], torch.ones(int(second.sum())))
    # The same sensor reading otherwise.
    torch.testing.assert_close(item["zone_mean_sigma"], single["zone_mean_sigma"])
    # A dropped zone loses all its targets.
    dropped = SimulatedL5Dataset(reader, grid=4, max_targets=4, signal_augmentation=(
        SignalAugmentation(drop_fraction=0.5, noise_prob=0.0)))[0]
    invalid = ~dropped["zone_valid"]
    assert invalid.any() and torch.all(dropped["zone_targets"][invalid] == 0)
    with pytest.raises(ValueError, match="max_targets"):
        SimulatedL5Dataset(reader, max_targets=5)


def test_zju_items_carry_their_targets_and_flip_them_with_their_zones(tmp_path, rng):
    samples, sample = _zju_set(tmp_path, rng)
    plain = ZJUL5TrainingDataset(samples, with_targets=True)[0]
    flipped = ZJUL5TrainingDataset(samples, with_targets=True, flip_prob=1.0)[0]
    assert "zone_targets" not in ZJUL5TrainingDataset(samples)[0]
    targets = plain["zone_targets"].numpy()
    # The set reports one target per zone: slot 0 is the reading, slot 1 empty.
    valid = sample.zone_valid
    np.testing.assert_allclose(targets[valid, 0, 0], sample.zone_mean_sigma[valid, 0])
    assert np.all(targets[:, 1] == 0) and np.all(targets[~valid] == 0)
    order = np.arange(16).reshape(4, 4)[:, ::-1].ravel()
    np.testing.assert_array_equal(flipped["zone_targets"].numpy(), targets[order])
