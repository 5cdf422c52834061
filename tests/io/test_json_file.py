"""The shared JSON readers name the file in every error."""

from __future__ import annotations

import json

import pytest

from deltar.io.json_file import read_json, read_split_filenames


def test_missing_and_corrupt_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"thing not found: .*nope\.json"):
        read_json(tmp_path / "nope.json", "thing")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"bad\.json: corrupt JSON"):
        read_json(bad, "thing")


def test_split_filenames_and_their_errors(tmp_path):
    index = tmp_path / "data.json"
    index.write_text(json.dumps({"test": [{"filename": "a/1.h5"}, {"filename": "a/2.h5"}]}))
    assert read_split_filenames(index, "test", "index") == ["a/1.h5", "a/2.h5"]
    with pytest.raises(ValueError, match=r"no split 'train' \(splits: \['test'\]\)"):
        read_split_filenames(index, "train", "index")
    other = tmp_path / "other.json"  # some other JSON: said to be no index at all
    other.write_text(json.dumps({"a": 1}))
    with pytest.raises(ValueError, match=r"other\.json is no index: no list of"):
        read_split_filenames(other, "test", "index")
    index.write_text(json.dumps({"test": [{"name": "x"}]}))
    with pytest.raises(ValueError, match="must be a list of"):
        read_split_filenames(index, "test", "index")


def test_relative_entries_are_checked_only_when_asked(tmp_path):
    index = tmp_path / "data.json"
    index.write_text(json.dumps({"test": [{"filename": "a/1.h5"}, {"filename": "../b.h5"}]}))
    assert read_split_filenames(index, "test", "index") == ["a/1.h5", "../b.h5"]
    with pytest.raises(ValueError, match=r"index .*data\.json: '\.\./b\.h5' must be a "
                       "relative path without '..'"):
        read_split_filenames(index, "test", "index", relative=True)
