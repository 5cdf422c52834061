"""Training data: hold-out blocks, sharding, mid-epoch resumption, dataset items."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.models.config import InputConfig
from deltar.training.config import DataConfig, SourceConfig
from deltar.training.data import (
    ResumableDataLoader,
    ShardedSampler,
    build_datasets,
    holdout_split,
)


@pytest.mark.parametrize(("frames", "fraction", "held"), [(100, 0.1, 10), (7, 0.2, 1),
                                                            (3, 0.9, 2), (2, 0.01, 1)])
def test_holdout_is_one_contiguous_block(frames, fraction, held):
    train, val = holdout_split(frames, fraction, "end")
    assert val == list(range(frames - held, frames))
    assert train == list(range(frames - held))
    train, val = holdout_split(frames, fraction, "start")
    assert val == list(range(held)) and train == list(range(held, frames))


def test_holdout_rejects_bad_arguments():
    with pytest.raises(ValueError, match="at least 2 frames"):
        holdout_split(1, 0.5)
    with pytest.raises(ValueError, match="fraction"):
        holdout_split(10, 0.0)
    with pytest.raises(ValueError, match="position"):
        holdout_split(10, 0.5, "middle")


def test_a_train_val_source_of_one_frame_is_named():
    # A source thinned to one frame (every: 100): the message names which, and the fix.
    config = DataConfig(sources=[SourceConfig(kind="procedural", frames=10, every=100,
                                              resize=[64, 96])],
                        training_grid=4, training_zone_px=12)
    config.validate("data")
    with pytest.raises(ValueError, match=r"^data.sources.0 \(procedural, 10 frames from seed "
                       r"0\): need at least 2 frames to hold some out, got 1"):
        build_datasets(config)


def test_sharded_sampler_splits_every_epoch_between_ranks():
    items = 11
    shards = [ShardedSampler(items, True, seed=3, rank=r, world_size=2) for r in range(2)]
    seen_orders = []
    for epoch in range(3):
        for s in shards:
            s.set_epoch(epoch)
        a, b = (s.indices() for s in shards)
        assert len(a) == len(b) == 6  # padded to equal length
        assert set(a) | set(b) == set(range(items))
        assert len(set(a) & set(b)) <= 1  # only the one wrapped-around pad item repeats
        seen_orders.append(a + b)
    assert seen_orders[0] != seen_orders[1]  # reshuffled per epoch
    again = ShardedSampler(items, True, seed=3, rank=0, world_size=2)
    again.set_epoch(1)
    assert again.indices() == seen_orders[1][:6]  # deterministic


def test_unpadded_sampler_partitions_exactly():
    parts = [ShardedSampler(7, False, rank=r, world_size=3, pad=False).indices()
             for r in range(3)]
    assert sorted(i for p in parts for i in p) == list(range(7))
    assert [len(p) for p in parts] == [3, 2, 2]


class _Items(torch.utils.data.Dataset):
    def __init__(self, n):
        self.n, self.epoch = n, 0

    def set_epoch(self, epoch):
        self.epoch = epoch

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return torch.tensor([i, self.epoch])


def _loader(num_workers=0):
    sampler = ShardedSampler(10, True, seed=1)
    return ResumableDataLoader(_Items(10), sampler, batch_size=3, drop_last=True,
                               num_workers=num_workers)


@pytest.mark.parametrize("num_workers", [0, 1])
def test_loader_resumes_mid_epoch(num_workers):
    full = _loader()
    full.sampler.set_epoch(2)
    expected = [b.tolist() for b in full]
    assert len(expected) == 3 and all(row[1] == 2 for b in expected for row in b)

    first = _loader()
    first.sampler.set_epoch(2)
    iterator = iter(first)
    next(iterator)
    state = first.state_dict()
    assert state == {"epoch": 2, "batches": 1}

    resumed = _loader(num_workers)
    resumed.load_state_dict(state)
    resumed.sampler.set_epoch(2)
    assert [b.tolist() for b in resumed] == expected[1:]
    # The skip applies once: the next pass over the epoch is whole again.
    assert [b.tolist() for b in resumed] == expected


def test_loader_ignores_state_of_another_epoch():
    loader = _loader()
    loader.load_state_dict({"epoch": 0, "batches": 2})
    loader.sampler.set_epoch(1)
    assert len(list(loader)) == 3


def test_shared_rgbd_source_holds_out_the_end_of_the_sequence(shared_data):
    folder = shared_data / "icl_livingroom1"
    config = DataConfig(
        sources=[SourceConfig(kind="rgbd", path=str(folder), resize=[64, 96],
                              intrinsics=[525.0, 525.0, 319.5, 239.5], holdout_fraction=0.1)],
        zone_layout="calibrated", grid=8, num_hypotheses=4, num_workers=0)
    config.image_augmentation.enabled = False
    train, val = build_datasets(config, seed=0)
    frames = len(sorted((folder / "color").glob("*.jpg")))
    held = round(frames * 0.1)
    assert len(train) + len(val) == frames and len(val) == held
    assert val.datasets[0].reader.indices == list(range(frames - held, frames))
    item = val[0]
    assert item["index"].item() == 0
    assert item["image"].shape == (3, 64, 96) and item["depth"].shape == (1, 64, 96)
    assert item["hypotheses"].shape == (64, 4) and item["zone_rects"].shape == (64, 4)
    # The held-out item is the first frame of the block, resized to 64x96.
    last_block_first = sorted((folder / "depth").glob("*.png"))[frames - held]
    import cv2

    raw = cv2.imread(str(last_block_first), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
    resized = cv2.resize(raw, (96, 64), interpolation=cv2.INTER_NEAREST)
    np.testing.assert_allclose(item["depth"][0].numpy(), resized, atol=1e-6)


@pytest.mark.parametrize(("depth_scale", "median"), [(1e6, r"0\.00\d+ m"),
                                                     (1.0, r"\d{3,4}(\.\d+)? m")])
def test_a_source_read_in_the_wrong_depth_units_is_refused(shared_data, depth_scale, median):
    """Millimetre PNGs read as if they held metres (or the other way) would train to the
    end without a word; the median depth of a few frames tells, naming the setting."""
    config = DataConfig(
        sources=[SourceConfig(kind="rgbd", path=str(shared_data / "icl_livingroom1"),
                              resize=[64, 96], intrinsics=[525.0, 525.0, 319.5, 239.5],
                              depth_scale=depth_scale)],
        zone_layout="calibrated", grid=8, num_hypotheses=4, num_workers=0)
    with pytest.raises(ValueError, match=rf"data\.sources\.0 \(.*icl_livingroom1\): its depth "
                                         rf"reads a median of {median}, outside .*set "
                                         r"depth_scale"):
        build_datasets(config, seed=0)


def test_a_blank_first_depth_frame_does_not_refuse_its_source(tmp_path):
    """Recordings often start with a blank depth frame (the camera warming up): the
    units are read from frames spread through the source."""
    import cv2

    for folder in ("color", "depth"):
        (tmp_path / folder).mkdir()
    for i in range(6):
        cv2.imwrite(str(tmp_path / "color" / f"{i:06d}.png"), np.full((64, 96, 3), 90, np.uint8))
        depth = np.zeros((64, 96), np.uint16) if i == 0 else np.full((64, 96), 1500, np.uint16)
        cv2.imwrite(str(tmp_path / "depth" / f"{i:06d}.png"), depth)
    (tmp_path / "camera-intrinsics.txt").write_text("80 0 47.5\n0 80 31.5\n0 0 1\n")
    config = DataConfig(sources=[SourceConfig(kind="rgbd", path=str(tmp_path))],
                        zone_layout="calibrated", grid=8, num_hypotheses=4, num_workers=0)
    train, val = build_datasets(config, seed=0)
    assert len(train) + len(val) == 6
    for i in range(1, 6):  # all blank: refused, naming the source
        cv2.imwrite(str(tmp_path / "depth" / f"{i:06d}.png"), np.zeros((64, 96), np.uint16))
    with pytest.raises(ValueError, match=r"data\.sources\.0 \(.*\): the 5 frames read to "
                                         r"check it have no depth"):
        build_datasets(config, seed=0)


def test_frames_the_network_cannot_take_are_refused_before_training(shared_data):
    """Sides not divisible by 32 fail at the first batch (for a held-out block, only at
    the first validation, an epoch in); found when the data is set up, naming the fix."""
    source = SourceConfig(kind="rgbd", path=str(shared_data / "icl_livingroom1"),
                          resize=[60, 90], intrinsics=[525.0, 525.0, 319.5, 239.5])
    config = DataConfig(sources=[source], zone_layout="calibrated", grid=8,
                        num_hypotheses=4, num_workers=0)
    with pytest.raises(ValueError, match=r"data\.sources\.0 \(rgbd .*icl_livingroom1\): "
                                         r"frames are 60x90, the "
                                         r"network takes sides divisible by 32: set "
                                         r"data\.sources\.0\.resize \(e\.g\. \[64, 96\]\)"):
        build_datasets(config, seed=0)
    # A training-only source cropped by the augmentation is not held out: it may.
    source.role = "train"
    config.image_augmentation.crop = [32, 64]
    config.sources.append(SourceConfig(kind="procedural", frames=2, resize=[64, 96],
                                       role="val"))
    train, _ = build_datasets(config, seed=0)
    assert train[0]["image"].shape == (3, 32, 64)
    # A crop larger than the frames is named with the config key, not at the first batch.
    config.image_augmentation.crop = [64, 128]
    with pytest.raises(ValueError, match=r"^data\.image_augmentation\.crop \[64, 128\] is "
                       r"larger than the 60x90 frames of data\.sources\.0 "):
        build_datasets(config, seed=0)


def test_nyu_release_layout_source_with_border_crop(tmp_path, rng):
    import json

    import h5py

    root = tmp_path / "nyudepthv2_sync"
    (root / "scene").mkdir(parents=True)
    for i in range(2):
        with h5py.File(root / "scene" / f"{i:05d}.h5", "w") as f:
            f["rgb"] = rng.integers(0, 255, (3, 480, 640), dtype=np.uint8)
            f["depth"] = rng.uniform(0.5, 5.0, (480, 640)).astype(np.float32)
    split = tmp_path / "split" / "nyu_sync.json"
    split.parent.mkdir()
    entries = [{"filename": f"scene/{i:05d}.h5"} for i in range(2)]
    split.write_text(json.dumps({"train": entries, "test": entries}), encoding="utf-8")
    config = DataConfig(sources=[
        SourceConfig(kind="nyu", path=str(split), data_root=str(root), split="train",
                     crop_border=True, role="train"),
        SourceConfig(kind="nyu", path=str(split), data_root=str(root), split="test",
                     role="val")], num_hypotheses=4, num_workers=0)
    config.image_augmentation.crop = [416, 544]
    train, val = build_datasets(config)
    assert len(train) == len(val) == 2
    # Border crop (480 - 24, 640 - 32), then the random 416x544 crop.
    assert train.datasets[0].reader[0].depth_m.shape == (456, 608)
    assert train[0]["image"].shape == (3, 416, 544)
    assert train[0]["zone_rects"].shape == (36, 4)  # 6x6 training zones
    assert val[0]["image"].shape == (3, 480, 640)


def test_thdr3k_source_trains_from_its_histograms_and_flips_them(tmp_path):
    """With the network's ``histogram_hypotheses`` the items' hypotheses are the
    histograms' quantiles (mirrored with the image); without it, the Gaussian's."""
    from deltar.sensor.sampling import sample_hypotheses, sample_hypotheses_from_histogram
    from tests.data.thdr3k_set import write_set

    list_path = write_set(tmp_path / "thdr", train=3, test=1, height=64, width=96)
    config = DataConfig(sources=[
        SourceConfig(kind="thdr3k", path=str(list_path), split="train", role="train"),
        SourceConfig(kind="thdr3k", path=str(list_path), split="test", role="val")],
        num_hypotheses=8)
    config.image_augmentation.flip_prob = 1.0
    gaussian = build_datasets(config, seed=0)[1][0]["hypotheses"]
    train, val = build_datasets(config, seed=0, inputs=InputConfig(histogram_hypotheses=True))
    assert (len(train), len(val)) == (3, 1)
    item, flipped = val[0], train[0]
    sample = train.datasets[0].samples[0]
    expected = sample_hypotheses_from_histogram(
        torch.from_numpy(sample.hist_edges_m), torch.from_numpy(sample.hist_counts),
        torch.from_numpy(sample.zone_valid), 8)
    order = np.arange(64).reshape(8, 8)[:, ::-1].ravel()
    torch.testing.assert_close(flipped["hypotheses"], expected[order])
    assert item["hypotheses"].shape == (64, 8) and item["depth"].shape == (1, 64, 96)
    assert not bool(item["zone_valid"].all())  # the no-target zone stays invalid
    test_sample = val.datasets[0].samples[0]
    mean_sigma = torch.from_numpy(test_sample.zone_mean_sigma).float()
    valid = torch.from_numpy(test_sample.zone_valid)
    torch.testing.assert_close(gaussian, sample_hypotheses(
        torch.where(valid, mean_sigma[:, 0], 0.0), torch.where(valid, mean_sigma[:, 1], 0.0),
        valid, 8, config.sampling))
    assert not torch.allclose(gaussian, item["hypotheses"], atol=1e-3)


def test_thdr3k_sources_refuse_resize():
    config = DataConfig(sources=[SourceConfig(kind="thdr3k", path="x.json", resize=[32, 32])])
    with pytest.raises(ValueError, match="resize is not supported for thdr3k"):
        config.validate("data")


def test_a_batch_of_frames_of_several_sizes_is_refused_with_the_fix():
    from deltar.training.data import collate_frames

    same = collate_frames([{"image": torch.zeros(3, 32, 64)}, {"image": torch.ones(3, 32, 64)}])
    assert same["image"].shape == (2, 3, 32, 64)
    with pytest.raises(ValueError, match=r"several sizes \(\[\(32, 64\), \(64, 96\)\].*"
                                         r"data\.sources\.N\.resize"):
        collate_frames([{"image": torch.zeros(3, 32, 64)}, {"image": torch.zeros(3, 64, 96)}])
    # Same frames, other zone grids: named as such, not as a size to resize.
    with pytest.raises(ValueError, match=r"items whose zone_valid differ in shape.*zone grids"):
        collate_frames([{"image": torch.zeros(3, 32, 64), "zone_valid": torch.ones(36)},
                        {"image": torch.zeros(3, 32, 64), "zone_valid": torch.ones(64)}])


def test_the_validation_frames_are_read_before_training_as_far_as_they_are_validated(
        tmp_path):
    """A missing validation frame fails the check; with validation off (limit 0) or
    limited to the batches before it, it is not read."""
    from typer.testing import CliRunner

    from deltar.cli.main import app
    from deltar.training.data import DeltarDataModule

    done = CliRunner().invoke(app, ["simulate", "procedural:4:0:64x96", str(tmp_path / "val")])
    assert done.exit_code == 0, done.output
    sorted((tmp_path / "val").rglob("*.h5"))[-1].unlink()  # the last frame, 4th batch
    config = DataConfig(sources=[
        SourceConfig(kind="procedural", frames=2, resize=[64, 96], role="train"),
        SourceConfig(kind="zju_l5", path=str(tmp_path / "val" / "data.json"), split="test",
                     role="val")], training_grid=8, training_zone_px=8, num_hypotheses=4,
        num_workers=0, val_batch_size=1)
    data = DeltarDataModule(config)
    data.setup()
    with pytest.raises(FileNotFoundError, match=r"procedural-3\.h5"):
        data.check_val_frames(0, 1)
    data.check_val_frames(0, 1, 0)
    data.check_val_frames(0, 1, 3)
    data.check_val_frames(0, 1, 0.5)
