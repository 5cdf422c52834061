"""ZJU-L5 reader and writer: round trip, the release's layout, and clear errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics
from deltar.data.zju_l5 import ZJUL5Dataset, ZJUL5Sample, write_zju_l5


def _sample(rng: np.random.Generator, name: str, height: int = 24, width: int = 32,
            zones: int = 64) -> ZJUL5Sample:
    valid = rng.random(zones) > 0.2
    mean_sigma = np.stack([rng.uniform(0.5, 3.5, zones), rng.uniform(0.01, 0.1, zones)], 1)
    mean_sigma[~valid] = 0.0
    return ZJUL5Sample(
        rgb=rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
        depth_m=rng.uniform(0.0, 4.0, (height, width)).astype(np.float32),
        zone_mean_sigma=mean_sigma,
        zone_rects=rng.uniform(-10, 40, (zones, 4)),
        zone_valid=valid,
        name=name,
        intrinsics=CameraIntrinsics(30.0, 31.0, 15.5, 11.5, width, height),
        zone_no_target=~valid & (rng.random(zones) > 0.5),
    )


def _write_release_file(path, rgb, depth, hist, fr, mask):
    """A frame file exactly as the release stores it (no extra attributes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["rgb"], f["depth"], f["hist_data"], f["fr"], f["mask"] = rgb, depth, hist, fr, mask


def test_round_trip_preserves_every_array(tmp_path, rng):
    samples = [_sample(rng, "kitchen/00001"), _sample(rng, "office/00007", zones=16)]
    index = write_zju_l5(tmp_path / "set", samples, split="test")
    assert json.loads(index.read_text()) == {
        "test": [{"filename": "kitchen/00001.h5"}, {"filename": "office/00007.h5"}]}
    ds = ZJUL5Dataset(index)
    assert len(ds) == 2
    for original, loaded in zip(samples, ds, strict=True):
        assert loaded.name == original.name
        np.testing.assert_array_equal(loaded.rgb, original.rgb)
        np.testing.assert_array_equal(loaded.depth_m, original.depth_m)
        np.testing.assert_array_equal(loaded.zone_mean_sigma, original.zone_mean_sigma)
        np.testing.assert_array_equal(loaded.zone_rects, original.zone_rects)
        np.testing.assert_array_equal(loaded.zone_valid, original.zone_valid)
        np.testing.assert_array_equal(loaded.zone_no_target, original.zone_no_target)
        np.testing.assert_array_equal(loaded.zone_frame().flat_no_target(),
                                      original.zone_no_target)
        assert loaded.intrinsics == original.intrinsics
    assert ds[1].grid == 4


def test_reads_release_layout_and_cleans_invalid_depth(tmp_path, rng):
    depth = rng.uniform(0.5, 3.0, (480, 640)).astype(np.float64)
    depth[0, 0], depth[1, 1] = np.nan, -1.0
    mask = np.ones(64, bool)
    mask[5] = False
    hist = np.full((64, 2), 1.5)
    hist[5] = (np.nan, 2.0)  # a masked zone with stale values
    _write_release_file(tmp_path / "scene" / "0.h5", rng.integers(0, 256, (480, 640, 3),
                                                                   dtype=np.uint8),
                        depth, hist, np.zeros((64, 4)), mask)
    (tmp_path / "data.json").write_text(json.dumps({"test": [{"filename": "scene/0.h5"}]}))
    sample = ZJUL5Dataset(tmp_path)[0]
    assert sample.name == "scene/0"
    assert sample.depth_m.dtype == np.float32
    assert sample.depth_m[0, 0] == 0.0 and sample.depth_m[1, 1] == 0.0
    assert sample.depth_m[2, 2] == pytest.approx(depth[2, 2])
    assert not sample.zone_valid[5] and sample.zone_valid.sum() == 63
    assert sample.zone_mean_sigma[5].tolist() == [0.0, 0.0]
    assert sample.zone_mean_sigma[6].tolist() == [1.5, 1.5]
    # Release files carry no intrinsics: the paper's ZJU-L5 camera is filled in.
    assert sample.intrinsics == ZJU_L5_INTRINSICS
    # Nor no-target flags: none is known.
    assert sample.zone_no_target is None and not sample.zone_frame().flat_no_target().any()


@pytest.mark.parametrize(("mask", "shown"), [
    (np.full(64, 0.5), "float64 holding 0.5"), (np.full(64, 2, np.uint8), "uint8 holding 2"),
    (np.full(64, np.nan), "float64 holding nan"), (np.array(["1"] * 64, "S1"), "|S1")])
def test_a_mask_that_is_not_bool_or_0_1_is_refused_naming_the_file(tmp_path, rng, mask, shown):
    """Cast to bool, 0.5 read as a valid zone."""
    rgb = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
    _write_release_file(tmp_path / "0.h5", rgb, np.ones((8, 8)), np.ones((64, 2)),
                        np.zeros((64, 4)), mask)
    (tmp_path / "data.json").write_text(json.dumps({"test": [{"filename": "0.h5"}]}))
    with pytest.raises(ValueError, match=r"ZJU-L5 file .*0\.h5: mask must be bool \(or 0/1\), "
                       f"got {re.escape(shown)}$"):
        ZJUL5Dataset(tmp_path)[0]


def test_a_mask_of_0_1_numbers_or_an_8x8_grid_still_reads(tmp_path, rng):
    rgb = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
    mask = np.ones((8, 8), np.float32)
    mask[0, 5] = 0
    _write_release_file(tmp_path / "0.h5", rgb, np.ones((8, 8)), np.ones((64, 2)),
                        np.zeros((64, 4)), mask)
    (tmp_path / "data.json").write_text(json.dumps({"test": [{"filename": "0.h5"}]}))
    valid = ZJUL5Dataset(tmp_path)[0].zone_valid
    assert valid.dtype == bool and valid.sum() == 63 and not valid[5]


def test_writer_refuses_to_overwrite(tmp_path, rng):
    write_zju_l5(tmp_path, [_sample(rng, "a")])
    with pytest.raises(FileExistsError, match=r"data\.json"):
        write_zju_l5(tmp_path, [_sample(rng, "b")])


def test_writer_refuses_an_empty_split_name_or_no_frames(tmp_path, rng):
    # Both wrote a set silently (``{"": [...]}`` / ``{"test": []}``), e.g. from
    # ``deltar simulate --split ""`` or simulate_set(..., indices=[]).
    with pytest.raises(ValueError, match="split must be a non-empty name, got ''"):
        write_zju_l5(tmp_path / "a", [_sample(rng, "a")], split="")
    with pytest.raises(ValueError, match="no frames to write"):
        write_zju_l5(tmp_path / "b", [])
    assert not (tmp_path / "a").exists() and not (tmp_path / "b" / "data.json").exists()


def test_a_failing_frame_leaves_no_partial_set(tmp_path, rng):
    def frames():  # the third frame's source cannot be read
        yield _sample(rng, "scene/0001")
        yield _sample(rng, "scene/0002")
        raise ValueError("cannot decode depth image scene/0003.png")

    existing = tmp_path / "keep.txt"  # what was in the folder before stays
    existing.write_text("x")
    with pytest.raises(ValueError, match="0003"):
        write_zju_l5(tmp_path, frames())
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["keep.txt"]
    with pytest.raises(ValueError, match="share the name"):
        write_zju_l5(tmp_path / "new", [_sample(rng, "a/b"), _sample(rng, "a/b")])
    assert not (tmp_path / "new").exists()  # the folders it made are gone too
    write_zju_l5(tmp_path, [_sample(rng, "scene/0001")])  # a re-run starts over
    assert (tmp_path / "data.json").is_file()


@pytest.mark.parametrize("stopped_after", ["scene/0002.h5", "data.json"])
def test_a_stop_right_after_a_files_rename_leaves_no_partial_set(tmp_path, rng, monkeypatch,
                                                                 stopped_after):
    """Ctrl+C landing just after a frame file or data.json is renamed into place (before
    the writer could note it) still removes every file the call made; a frame file that
    was there before is never removed."""
    import deltar.data.zju_l5 as zju_l5

    def stopped(write):
        def after_the_rename(path, *args, **kwargs):
            written = write(path, *args, **kwargs)
            if Path(path).as_posix().endswith(stopped_after):
                raise KeyboardInterrupt
            return written
        return after_the_rename

    monkeypatch.setattr(zju_l5, "write_bytes_atomic", stopped(zju_l5.write_bytes_atomic))
    with pytest.raises(KeyboardInterrupt):
        write_zju_l5(tmp_path / "set", [_sample(rng, "scene/0001"), _sample(rng, "scene/0002")])
    assert not (tmp_path / "set").exists()
    theirs = tmp_path / "other" / "scene" / "0001.h5"
    theirs.parent.mkdir(parents=True)
    theirs.write_bytes(b"not this call's")
    with pytest.raises(FileExistsError, match=r"0001\.h5"):
        write_zju_l5(tmp_path / "other", [_sample(rng, "scene/0001")])
    assert theirs.read_bytes() == b"not this call's"


@pytest.mark.parametrize("raced", ["scene/0002.h5", "data.json"])
def test_a_file_another_writer_makes_first_is_left_to_it(tmp_path, rng, monkeypatch, raced):
    """Two writers of one set: a file the other one made first is refused and left as
    the other wrote it, while this call's own files are removed (the last moment's race
    is deltar.io.atomic's, tested there)."""
    import deltar.data.zju_l5 as zju_l5

    write = zju_l5.write_bytes_atomic

    def other_writer_first(path, *args, **kwargs):
        if Path(path).as_posix().endswith(raced):
            Path(path).write_bytes(b"the other writer's")
        return write(path, *args, **kwargs)

    monkeypatch.setattr(zju_l5, "write_bytes_atomic", other_writer_first)
    with pytest.raises(FileExistsError, match=raced.replace(".", r"\.")):
        write_zju_l5(tmp_path, [_sample(rng, "scene/0001"), _sample(rng, "scene/0002")])
    assert (tmp_path / raced).read_bytes() == b"the other writer's"
    assert not (tmp_path / "scene" / "0001.h5").exists()


def test_writer_rejects_duplicate_and_unsafe_names(tmp_path, rng):
    with pytest.raises(ValueError, match="share the name"):
        write_zju_l5(tmp_path / "dup", [_sample(rng, "a"), _sample(rng, "a")])
    assert not (tmp_path / "dup" / "data.json").exists()
    with pytest.raises(ValueError, match="relative path"):
        write_zju_l5(tmp_path / "up", [_sample(rng, "../escape")])


def test_missing_split_and_missing_file(tmp_path):
    (tmp_path / "data.json").write_text(json.dumps({"test": [{"filename": "x/1.h5"}]}))
    with pytest.raises(ValueError, match="no split 'train'"):
        ZJUL5Dataset(tmp_path / "data.json", split="train")
    with pytest.raises(FileNotFoundError, match=r"1\.h5"):
        ZJUL5Dataset(tmp_path)[0]
    with pytest.raises(FileNotFoundError, match="index not found"):
        ZJUL5Dataset(tmp_path / "nope.json")


@pytest.mark.parametrize("entry", ["/etc/passwd.h5", "../outside/1.h5", "x/../../1.h5", ""])
def test_an_entry_outside_the_set_is_refused_naming_data_json(tmp_path, entry):
    """Such an entry would read a file outside the set's folder."""
    (tmp_path / "data.json").write_text(json.dumps({"test": [{"filename": "x/1.h5"},
                                                             {"filename": entry}]}))
    with pytest.raises(ValueError, match=r"ZJU-L5 index .*data\.json: '" +
                       entry.replace(".", r"\.") + "' must be a relative path without '..'"):
        ZJUL5Dataset(tmp_path)


def test_a_split_of_no_frames_is_refused_naming_it_and_data_json(tmp_path):
    (tmp_path / "data.json").write_text(json.dumps({"test": [], "train": [{"filename": "a"}]}))
    with pytest.raises(ValueError, match=r"ZJU-L5 index .*data\.json: split 'test' lists no "
                       "frames"):
        ZJUL5Dataset(tmp_path)


def test_corrupt_h5_and_missing_key_and_bad_shapes(tmp_path, rng):
    (tmp_path / "bad.h5").write_bytes(b"not an hdf5 file at all")
    rgb = rng.integers(0, 256, (8, 8, 3), dtype=np.uint8)
    with h5py.File(tmp_path / "nokey.h5", "w") as f:
        f["rgb"], f["depth"] = rgb, np.ones((8, 8))
    _write_release_file(tmp_path / "shape.h5", rgb, np.ones((8, 8)), np.ones((64, 3)),
                        np.zeros((64, 4)), np.ones(64, bool))
    _write_release_file(tmp_path / "size.h5", rgb, np.ones((8, 9)), np.ones((64, 2)),
                        np.zeros((64, 4)), np.ones(64, bool))
    _write_release_file(tmp_path / "mm.h5", rgb, np.full((8, 8), 1500, np.uint16),
                        np.ones((64, 2)), np.zeros((64, 4)), np.ones(64, bool))
    entries = [{"filename": n} for n in ("bad.h5", "nokey.h5", "shape.h5", "size.h5", "mm.h5")]
    (tmp_path / "data.json").write_text(json.dumps({"test": entries}))
    ds = ZJUL5Dataset(tmp_path)
    with pytest.raises(ValueError, match=r"mm\.h5: depth must be float metres, got uint16 "
                       r"\(millimetres\?"):
        ds[4]
    with pytest.raises(ValueError, match=r"bad\.h5"):
        ds[0]
    with pytest.raises(ValueError, match=r"nokey\.h5.*missing.*hist_data"):
        ds[1]
    with pytest.raises(ValueError, match=r"shape\.h5.*zone_mean_sigma"):
        ds[2]
    with pytest.raises(ValueError, match=r"size\.h5.*depth_m shape"):
        ds[3]


def test_sample_validation_names_the_field(rng):
    good = _sample(rng, "x")
    with pytest.raises(ValueError, match="zone_valid"):
        ZJUL5Sample(good.rgb, good.depth_m, good.zone_mean_sigma[:10], good.zone_rects[:10],
                    good.zone_valid[:10], "x")
    bad_ms = good.zone_mean_sigma.copy()
    bad_ms[np.flatnonzero(good.zone_valid)[0], 0] = np.nan
    with pytest.raises(ValueError, match="zone_mean_sigma"):
        ZJUL5Sample(good.rgb, good.depth_m, bad_ms, good.zone_rects, good.zone_valid, "x")
    with pytest.raises(ValueError, match="zone_no_target must be"):
        ZJUL5Sample(good.rgb, good.depth_m, good.zone_mean_sigma, good.zone_rects,
                    good.zone_valid, "x", zone_no_target=np.zeros(16, bool))
    with pytest.raises(ValueError, match="zone_no_target marks valid zones"):
        ZJUL5Sample(good.rgb, good.depth_m, good.zone_mean_sigma, good.zone_rects,
                    good.zone_valid, "x", zone_no_target=good.zone_valid)
    # Stored as a grid (as some files store masks): read as the flat row-major flags.
    grid_flags = np.zeros((8, 8), bool)
    grid_flags.reshape(-1)[np.flatnonzero(~good.zone_valid)[:1]] = True
    sample = ZJUL5Sample(good.rgb, good.depth_m, good.zone_mean_sigma, good.zone_rects,
                         good.zone_valid, "x", zone_no_target=grid_flags)
    np.testing.assert_array_equal(sample.zone_no_target, grid_flags.reshape(-1))


def test_a_frame_with_datasets_of_the_wrong_shape_names_the_file(tmp_path, rng):
    sample = _sample(rng, "scene/0001")
    index = write_zju_l5(tmp_path, [sample])
    frame = tmp_path / "scene" / "0001.h5"
    with h5py.File(frame, "r+") as f:
        del f["rgb"]
        f["rgb"] = np.uint8(3)
    with pytest.raises(ValueError, match=rf"^{frame}: cannot read ZJU-L5 frame file: "):
        ZJUL5Dataset(index, intrinsics=None)[0]


def test_targets_round_trip_and_are_checked(tmp_path, rng):
    sample = _sample(rng, "kitchen/00003", zones=16)
    valid = sample.zone_valid
    mean = np.zeros((16, 2), np.float32)
    mean[:, 0] = sample.zone_mean_sigma[:, 0]
    mean[valid, 1] = mean[valid, 0] + 1.0
    sigma = np.where(mean > 0, 0.02, 0.0).astype(np.float32)
    sigma[:, 0] = sample.zone_mean_sigma[:, 1]
    targets = dict(target_mean_m=mean, target_sigma_m=sigma, target_valid=mean > 0,
                   target_signal=np.where(mean > 0, 0.5, 0.0))
    with_targets = ZJUL5Sample(**{**sample.__dict__, **targets})
    write_zju_l5(tmp_path / "set", [with_targets])
    back = ZJUL5Dataset(tmp_path / "set" / "data.json")[0]
    for key, value in targets.items():
        np.testing.assert_allclose(getattr(back, key), value)
    frame = back.zone_frame()
    assert frame.target_mean_m.shape == (4, 4, 2)
    np.testing.assert_allclose(frame.target_signal.reshape(16, 2), targets["target_signal"])
    with pytest.raises(ValueError, match="given together"):
        ZJUL5Sample(**{**sample.__dict__, "target_mean_m": mean})
    with pytest.raises(ValueError, match="target_sigma_m must have"):
        ZJUL5Sample(**{**sample.__dict__, **targets, "target_sigma_m": mean[:, :1]})
    with pytest.raises(ValueError, match="target_signal must be finite"):
        ZJUL5Sample(**{**sample.__dict__, **targets,
                       "target_signal": np.full((16, 2), -1.0)})
