"""pair_by_stem: images and zone files of two folders, paired by stem."""

from __future__ import annotations

import pytest

from deltar.io.file_pairs import pair_by_stem


def test_pairs_by_stem_and_reports_the_rest(tmp_path):
    images, zones = tmp_path / "img", tmp_path / "zones"
    images.mkdir()
    zones.mkdir()
    for name in ("b.PNG", "a.jpg", "only_image.png", "notes.txt"):
        (images / name).write_bytes(b"")
    for name in ("a.json", "b.npz", "only_zones.json"):
        (zones / name).write_bytes(b"")
    pairs, unpaired = pair_by_stem(images, zones)
    assert pairs == [(images / "a.jpg", zones / "a.json"), (images / "b.PNG", zones / "b.npz")]
    assert unpaired == ["only_image", "only_zones"]


def test_missing_folder_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"image folder not found: .*nope"):
        pair_by_stem(tmp_path / "nope", tmp_path)
    with pytest.raises(FileNotFoundError, match=r"zone folder not found: .*gone"):
        pair_by_stem(tmp_path, tmp_path / "gone")


def test_two_files_with_one_stem_are_refused_naming_both(tmp_path):
    for name in ("a.png", "a.JPG", "b.png", "a.json", "b.json"):
        (tmp_path / name).write_bytes(b"x")
    with pytest.raises(ValueError, match=r"^.*/a\.JPG and .*/a\.png are images with the same "
                       r"stem 'a'; frames pair by stem, so keep only one of them$"):
        pair_by_stem(tmp_path, tmp_path)
    (tmp_path / "a.JPG").unlink()
    (tmp_path / "b.npz").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"b\.json and .*b\.npz are zone files with the same "
                       "stem 'b'"):
        pair_by_stem(tmp_path, tmp_path)
