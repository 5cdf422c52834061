"""The THDR3K reader on tiny sets of its documented layout."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deltar.data.thdr3k import THDR3KDataset, read_thdr3k_sample, thdr3k_zone_rects
from deltar.data.zju_l5 import ZJUL5Dataset
from deltar.data.zone_sets import open_zone_set
from deltar.sensor.cnh import CNHConfig
from tests.data.thdr3k_set import write_sample, write_set, zone_truth


def test_zone_rects_cover_the_centre_square_in_60px_zones():
    rects = thdr3k_zone_rects(480, 640)
    assert rects.shape == (64, 4)
    np.testing.assert_array_equal(rects[0], [0, 60, 60, 120])
    np.testing.assert_array_equal(rects[7], [0, 480, 60, 540])
    np.testing.assert_array_equal(rects[63], [420, 480, 480, 540])
    np.testing.assert_allclose(thdr3k_zone_rects(240, 320)[9], [30, 60, 60, 90])


def test_sample_is_rotated_masked_and_normalised(tmp_path):
    truth = write_sample(tmp_path / "s" / "000001", seed=0, height=480, width=640)
    sample = read_thdr3k_sample(tmp_path / "s" / "000001")
    assert sample.rgb.shape == (480, 640, 3) and sample.depth_m.shape == (480, 640)
    _, (r, c) = zone_truth(0)
    valid = sample.zone_valid.reshape(8, 8)
    assert not valid[r, c] and valid.sum() == 63  # the no-target zone, nothing else
    assert np.flatnonzero(sample.zone_no_target).tolist() == [r * 8 + c]
    means = sample.zone_mean_sigma[:, 0].reshape(8, 8)
    # Image orientation: zone (row, col) carries the truth of that place in the image.
    np.testing.assert_allclose(means[valid], truth[valid], atol=1e-6)
    assert means[r, c] == 0.0  # the stale 0.3 m reading is not kept
    # Ground truth inside zone (2, 5) equals that zone's reading.
    y0, x0, y1, x1 = sample.zone_rects[2 * 8 + 5].astype(int)
    np.testing.assert_allclose(sample.depth_m[y0:y1, x0:x1], truth[2, 5], atol=1e-6)
    assert sample.hist_counts.shape == (64, 18) and sample.hist_edges_m.shape == (19,)
    np.testing.assert_allclose(sample.hist_counts.sum(1), 1.0, atol=1e-6)
    assert sample.hist_counts.min() >= 0
    # The histogram peak of each valid zone holds its distance.
    peak = sample.hist_counts.argmax(1)
    edges = sample.hist_edges_m
    flat_valid = sample.zone_valid
    inside = (edges[peak] <= sample.zone_mean_sigma[:, 0]) & \
        (sample.zone_mean_sigma[:, 0] <= edges[peak + 1])
    assert inside[flat_valid].all()
    assert np.all(sample.zone_mean_sigma[flat_valid, 1] > 0)


def test_bin_configuration_from_the_file_wins(tmp_path):
    cfg = CNHConfig(start_bin=10, num_bins=12, sub_sample=8)
    write_sample(tmp_path / "a", seed=1, config=cfg, write_config=True)
    sample = read_thdr3k_sample(tmp_path / "a")
    np.testing.assert_allclose(sample.hist_edges_m, cfg.edges_m(), rtol=1e-6)
    # Without it in the file, the reader's configuration is used.
    write_sample(tmp_path / "b", seed=1, config=cfg)
    assert read_thdr3k_sample(tmp_path / "b", cnh_config=cfg).hist_counts.shape == (64, 12)
    with pytest.raises(ValueError, match="expected 64 zones x 18 bins"):
        read_thdr3k_sample(tmp_path / "b")


def test_dataset_splits_and_autodetection(tmp_path):
    list_path = write_set(tmp_path / "set", train=2, test=1)
    train = THDR3KDataset(list_path, split="train")
    assert len(train) == 2 and train[1].name == "scene_train/000001"
    test = open_zone_set(list_path, split="test")
    assert isinstance(test, THDR3KDataset) and len(test) == 1
    with pytest.raises(ValueError, match="no split 'val'"):
        THDR3KDataset(list_path, split="val")


def test_an_entry_outside_the_set_is_refused(tmp_path):
    list_path = tmp_path / "list.json"
    list_path.write_text(json.dumps({"test": [{"filename": "../elsewhere/x"}]}))
    with pytest.raises(ValueError, match=r"THDR3K file list .*list\.json: '\.\./elsewhere/x' "
                       "must be a relative path without '..'"):
        THDR3KDataset(list_path)


def test_zju_sets_are_still_detected_as_zju(tmp_path, rng):
    from deltar.data.zju_l5 import write_zju_l5
    from tests.data.test_zju_l5 import _sample

    index = write_zju_l5(tmp_path / "z", [_sample(rng, "a/1")])
    assert isinstance(open_zone_set(index), ZJUL5Dataset)
    assert isinstance(open_zone_set(tmp_path / "z"), ZJUL5Dataset)


def test_missing_and_corrupt_files_are_named(tmp_path):
    root = tmp_path / "s" / "x"
    write_sample(root, seed=2)
    depth = root.with_name("x_depth.png")
    depth.unlink()
    with pytest.raises(FileNotFoundError, match=r"x_depth\.png"):
        read_thdr3k_sample(root)
    write_sample(root, seed=2)
    tof = root.with_name("x_tof.json")
    data = json.loads(tof.read_text())
    del data["nb_target_detected"]
    tof.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"x_tof.json: missing fields \['nb_target_detected'\]"):
        read_thdr3k_sample(root)
    data["nb_target_detected"] = [1] * 64
    data["distance_mm"] = data["distance_mm"][:60]
    tof.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"x_tof\.json: distance_mm has 60 zones"):
        read_thdr3k_sample(root)
