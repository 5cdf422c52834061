"""NYU readers on small files written in the official layouts."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from deltar.camera import CameraIntrinsics
from deltar.data.nyu import NYU_INTRINSICS, NYUH5Reader, NYULabeledReader

SMALL = CameraIntrinsics(5.0, 5.0, 3.5, 2.5, 8, 6)  # 6 rows x 8 columns


def test_labeled_mat_is_transposed_back(tmp_path, rng):
    images = rng.integers(0, 256, (3, 6, 8, 3), dtype=np.uint8)  # (N, H, W, C) truth
    depths = rng.uniform(0.5, 5.0, (3, 6, 8)).astype(np.float32)
    depths[1, 0, 0] = np.nan
    path = tmp_path / "nyu_depth_v2_labeled.mat"
    with h5py.File(path, "w") as f:
        # MATLAB's column-major storage as h5py sees it: every axis order reversed.
        f["images"] = images.transpose(0, 3, 2, 1)  # (N, 3, W, H)
        f["depths"] = depths.transpose(0, 2, 1)  # (N, W, H)
    reader = NYULabeledReader(path, indices=[2, 1], intrinsics=SMALL)
    assert len(reader) == 2
    frame = reader[0]
    assert frame.name == "nyu_labeled/00002"
    np.testing.assert_array_equal(frame.image, images[2])
    np.testing.assert_array_equal(frame.depth_m, depths[2])
    assert reader[1].depth_m[0, 0] == 0.0  # NaN hole -> 0.0
    with pytest.raises(ValueError, match="out of range"):
        NYULabeledReader(path, indices=[3], intrinsics=SMALL)
    with pytest.raises(ValueError, match="intrinsics"):
        NYULabeledReader(path)  # NYU's 480x640 intrinsics do not fit 6x8 images


def test_labeled_mat_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        NYULabeledReader(tmp_path / "none.mat")
    old = tmp_path / "v5.mat"
    old.write_bytes(b"MATLAB 5.0 MAT-file" + bytes(200))
    with pytest.raises(ValueError, match=r"v7\.3"):
        NYULabeledReader(old)
    with h5py.File(tmp_path / "nodepth.mat", "w") as f:
        f["images"] = np.zeros((1, 3, 8, 6), np.uint8)
    with pytest.raises(ValueError, match="depths"):
        NYULabeledReader(tmp_path / "nodepth.mat")


def test_release_h5_json_layout(tmp_path, rng):
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 5.0, (6, 8)).astype(np.float32)
    frame_path = tmp_path / "data" / "train" / "kitchen_0028b" / "00045.h5"
    frame_path.parent.mkdir(parents=True)
    with h5py.File(frame_path, "w") as f:
        f["rgb"], f["depth"] = rgb.transpose(2, 0, 1), depth
    split = tmp_path / "nyu_sync.json"
    split.write_text(json.dumps({"train": [{"filename": "train/kitchen_0028b/00045.h5"}],
                                 "test": [{"filename": "test/missing/00001.h5"}]}))
    reader = NYUH5Reader(split, "train", data_root=tmp_path / "data", intrinsics=SMALL)
    frame = reader[0]
    assert frame.name == "train/kitchen_0028b/00045"
    np.testing.assert_array_equal(frame.image, rgb)
    np.testing.assert_array_equal(frame.depth_m, depth)
    with pytest.raises(FileNotFoundError, match=r"00001\.h5"):
        NYUH5Reader(split, "test", data_root=tmp_path / "data")[0]
    with pytest.raises(ValueError, match="no split 'val'"):
        NYUH5Reader(split, "val")


def test_release_border_crop(tmp_path, rng):
    rgb = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 5.0, (30, 40)).astype(np.float32)
    with h5py.File(tmp_path / "f.h5", "w") as f:
        f["rgb"], f["depth"] = rgb.transpose(2, 0, 1), depth
    (tmp_path / "split.json").write_text(json.dumps({"train": [{"filename": "f.h5"}]}))
    frame = NYUH5Reader(tmp_path / "split.json", intrinsics=CameraIntrinsics(
        5.0, 5.0, 20.5, 14.5, 40, 30), crop_border=True)[0]
    # 30x40 minus 12 rows and 16 columns on each side.
    np.testing.assert_array_equal(frame.image, rgb[12:18, 16:24])
    np.testing.assert_array_equal(frame.depth_m, depth[12:18, 16:24])
    assert (frame.intrinsics.cx, frame.intrinsics.cy) == (4.5, 2.5)


def test_default_intrinsics_are_nyu():
    assert (NYU_INTRINSICS.fx, NYU_INTRINSICS.fy, NYU_INTRINSICS.cx, NYU_INTRINSICS.cy) == (
        518.86, 519.47, 325.58, 253.74)


def test_integer_depth_and_datasets_of_the_wrong_kind_name_the_file(tmp_path):
    """Millimetre depth would read 1000 times too far; a group where an array belongs
    was a TypeError / AttributeError traceback."""
    with h5py.File(tmp_path / "mm.mat", "w") as f:
        f["images"] = np.zeros((1, 3, 8, 6), np.uint8)
        f["depths"] = np.full((1, 8, 6), 1500, np.uint16)
    with pytest.raises(ValueError, match=r"mm\.mat: depths must be float metres, got uint16"):
        NYULabeledReader(tmp_path / "mm.mat", intrinsics=SMALL)
    with h5py.File(tmp_path / "float_images.mat", "w") as f:
        f["images"] = np.full((1, 3, 8, 6), 0.5)
        f["depths"] = np.full((1, 8, 6), 1.5)
    with pytest.raises(ValueError, match=r"float_images\.mat: images must be uint8"):
        NYULabeledReader(tmp_path / "float_images.mat", intrinsics=SMALL)
    with h5py.File(tmp_path / "group.mat", "w") as f:
        f.create_group("images")
        f["depths"] = np.full((1, 8, 6), 1.5)
    with pytest.raises(ValueError, match=r"group\.mat: cannot read NYU labeled file"):
        NYULabeledReader(tmp_path / "group.mat", intrinsics=SMALL)
    with h5py.File(tmp_path / "mm.h5", "w") as f:
        f["rgb"], f["depth"] = np.zeros((3, 6, 8), np.uint8), np.full((6, 8), 1500, np.uint16)
    with h5py.File(tmp_path / "group.h5", "w") as f:
        f["rgb"] = np.zeros((3, 6, 8), np.uint8)
        f.create_group("depth")
    (tmp_path / "split.json").write_text(json.dumps(
        {"train": [{"filename": "mm.h5"}, {"filename": "group.h5"}]}))
    reader = NYUH5Reader(tmp_path / "split.json", intrinsics=SMALL)
    with pytest.raises(ValueError, match=r"mm\.h5: depth must be float metres, got uint16"):
        reader[0]
    with pytest.raises(ValueError, match=r"group\.h5: cannot read NYU frame file"):
        reader[1]
