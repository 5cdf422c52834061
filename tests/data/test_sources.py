"""open_source: every source kind the CLI accepts, and clear errors."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from deltar.camera import CameraIntrinsics
from deltar.data.nyu import NYUH5Reader, NYULabeledReader
from deltar.data.procedural import ProceduralReader
from deltar.data.rgbd import SevenScenesReader
from deltar.data.sources import open_source

SMALL = CameraIntrinsics(5.0, 5.0, 3.5, 2.5, 8, 6)


def test_folder_and_procedural(shared_data):
    assert isinstance(open_source(shared_data / "7scenes_redkitchen"), SevenScenesReader)
    reader = open_source("procedural:2:7:16x24")
    assert isinstance(reader, ProceduralReader)
    assert (len(reader), reader.seed, reader.height, reader.width) == (2, 7, 16, 24)


def test_nyu_files(tmp_path):
    with h5py.File(tmp_path / "labeled.mat", "w") as f:
        f["images"] = np.zeros((2, 3, 8, 6), np.uint8)
        f["depths"] = np.ones((2, 8, 6), np.float32)
    assert isinstance(open_source(tmp_path / "labeled.mat", intrinsics=SMALL), NYULabeledReader)
    (tmp_path / "split.json").write_text(json.dumps({"test": [{"filename": "a.h5"}]}))
    reader = open_source(tmp_path / "split.json", split="test")
    assert isinstance(reader, NYUH5Reader) and len(reader) == 1


def test_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_source(tmp_path / "absent")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="cannot tell"):
        open_source(tmp_path / "notes.txt")
    with pytest.raises(ValueError, match="procedural source"):
        open_source("procedural:ten")
