"""The reading boundary: any failure of reading a user's file names the file."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from PIL import Image

from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.data.rgbd_files import read_color
from deltar.io.input_file import InputFileError, input_file, input_folder, reading
from deltar.io.json_file import read_json
from deltar.io.recording import Recording
from deltar.io.zone_file import load_zone_frame, save_zone_frame
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame


def test_paths_are_told_apart(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"^calibration file not found: .*nope\.json$"):
        input_file(tmp_path / "nope.json", "calibration file")
    with pytest.raises(IsADirectoryError, match=f"^calibration file {tmp_path} is a folder, "
                       "not a file$"):
        input_file(tmp_path, "calibration file")
    with pytest.raises(InputFileError, match="^calibration file /dev/null is not a regular "
                       r"file \(a device, pipe or socket\)$"):
        input_file(os.devnull, "calibration file")
    (tmp_path / "f").write_text("x")
    with pytest.raises(NotADirectoryError, match=r"recording folder .*/f is a file, not a "
                       "folder$"):
        input_folder(tmp_path / "f", "recording folder")


def test_deep_json_huge_numbers_and_bad_utf8_name_the_file(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputFileError, match=r"deep\.json: cannot read zone frame file: "
                       "nested too deeply to parse$") as caught:
        load_zone_frame(deep)
    assert isinstance(caught.value.__cause__, RecursionError)
    digits = tmp_path / "digits.json"
    digits.write_text("1" * 5000)
    with pytest.raises(ValueError, match=r"digits\.json: cannot read calibration file: "):
        read_json(digits, "calibration file")
    latin = tmp_path / "latin.json"
    latin.write_bytes(b'{"a": "\xe9"}')
    with pytest.raises(ValueError, match=r"latin\.json: cannot read x: not UTF-8 text "
                       r"\(byte 0xe9 at position 7\)$"):
        read_json(latin, "x")


def test_truncated_npz_names_the_file(tmp_path):
    path = save_zone_frame(tmp_path / "z.npz", ZoneFrame(np.full(64, 1.5), np.full(64, 0.02),
                                                         np.ones(64, bool)))
    data = path.read_bytes()
    for cut in (len(data) // 2, 30):
        (tmp_path / "t.npz").write_bytes(data[:cut])
        with pytest.raises(ValueError, match=r"t\.npz: cannot read zone frame file: corrupt "
                           "or truncated file"):
            load_zone_frame(tmp_path / "t.npz")


def test_decompression_bomb_names_the_image(tmp_path, monkeypatch):
    Image.new("RGB", (64, 48)).save(tmp_path / "big.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 3072 > 2 x 1000: the error
    with pytest.raises(ValueError, match=r"big\.png: cannot read colour image: the image is "
                       "too large to decode safely"):
        read_color(tmp_path / "big.png")


@pytest.fixture
def calib_dict(tmp_path):
    path = RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48),
                          SensorExtrinsics()).save(tmp_path / "c.json")
    return json.loads(path.read_text())


@pytest.mark.parametrize("change, message", [
    (("intrinsics", "width", float("inf")), "width must be an integer, got inf"),
    (("intrinsics", "width", 64.5), "width must be an integer, got 64.5"),
    (("intrinsics", "fx", "60"), "fx must be a number, got '60'"),
    (("residuals", None, [1, 2]), "residuals must be an object of numbers, got list"),
    (("residuals", None, {"a": "x"}), "residuals.a must be a number, got 'x'"),
    (("grid", None, True), "grid must be a number, got True"),
    (("extrinsics", None, [1]), "invalid calibration: "),
    (("intrinsics", None, [1]), "camera intrinsics must be an object, got list"),
], ids=["inf-size", "fraction-size", "string", "residuals-list", "residual-string",
        "bool-grid", "extrinsics-list", "intrinsics-list"])
def test_odd_calibration_fields_name_the_file_and_field(tmp_path, calib_dict, change,
                                                        message):
    key, sub, value = change
    if sub is None:
        calib_dict[key] = value
    else:
        calib_dict[key][sub] = value
    path = tmp_path / "odd.json"
    path.write_text(json.dumps(calib_dict))
    with pytest.raises(ValueError) as caught:
        RigCalibration.load(path)
    assert str(caught.value).startswith(f"{path}: ")
    assert message in str(caught.value)


def test_recording_zone_lines_of_the_wrong_kind_name_the_line(tmp_path):
    from deltar.io.recording import RecordingMeta, RecordingWriter

    writer = RecordingWriter(tmp_path / "rec", RecordingMeta(
        intrinsics=CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)))
    writer.add_color(0.0, np.zeros((48, 64, 3), np.uint8))
    zones = tmp_path / "rec" / "zones.jsonl"
    zones.write_text('{"mean_m": {"a": 1}, "sigma_m": [], "valid": [], '
                     '"schema_version": 1}\n' + "[" * 100_000 + "\n{}\n")
    with pytest.raises(ValueError, match=r"zones\.jsonl"):
        Recording(tmp_path / "rec").zone_frames()


def test_internal_errors_are_not_disguised(tmp_path):
    with pytest.raises(NameError), reading(tmp_path / "x.json", "x"):
        raise NameError("a bug")
    with pytest.raises(AssertionError), reading(tmp_path / "x.json", "x"):
        raise AssertionError("a bug")


def test_outputs_never_resolve_to_inputs(tmp_path):
    from deltar.io.input_file import refuse_input_as_output

    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "meta.json").write_text("{}")
    (tmp_path / "link.json").symlink_to(rec / "meta.json")
    os.link(rec / "meta.json", tmp_path / "hard.json")
    with pytest.raises(ValueError, match=r"^--out .*link\.json is inside the input .*rec; "):
        refuse_input_as_output(tmp_path / "link.json", [rec], "--out")
    with pytest.raises(ValueError, match=r"hard\.json is the input .*meta\.json \(a link"):
        refuse_input_as_output(tmp_path / "hard.json", [rec], "--out")
    with pytest.raises(ValueError, match=r"^--json .*link\.json is the input .*rec/meta\.json; "):
        refuse_input_as_output(tmp_path / "link.json", [None, rec / "meta.json"], "--json")
    with pytest.raises(ValueError, match=r"^OUT .*sub is inside the input "):
        refuse_input_as_output(rec / "sub", [rec], "OUT", folder=True)
    # A new file beside the inputs replaces nothing: allowed.
    assert refuse_input_as_output(rec / "calib.json", [rec], "--out") == rec / "calib.json"


def test_every_reader_goes_through_the_boundary(tmp_path):
    from deltar.calibration.slam import read_tum_trajectory as read_slam_trajectory
    from deltar.io.ply import read_ply
    from deltar.io.torch_file import read_torch_file
    from deltar.mapping.poses import read_pose_file, read_tum_trajectory
    from deltar.weights import resolve_checkpoint

    utf16 = tmp_path / "t.txt"
    utf16.write_bytes("0 0 0 0 0 0 0 1\n".encode("utf-16"))
    for read in (read_tum_trajectory, read_slam_trajectory):
        with pytest.raises(InputFileError, match=r"t\.txt: cannot read trajectory file: not "
                           r"UTF-8 text \(byte 0xff at position 0\)$"):
            read(utf16)
    with pytest.raises(ValueError, match=r"t\.txt: not a 4x4 matrix of numbers: 'utf-8'"):
        read_pose_file(utf16)
    ply = tmp_path / "cut.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\n"
                    b"property float x\nproperty float y\nproperty float z\nend_header\n")
    with pytest.raises(ValueError, match=r"cut\.ply"):
        read_ply(ply)
    with pytest.raises(IsADirectoryError, match=f"^checkpoint {tmp_path} is a folder"):
        read_torch_file(resolve_checkpoint(tmp_path), "checkpoint", weights_only=True)
    with pytest.raises(InputFileError, match=r"^checkpoint /dev/null is not a regular file"):
        read_torch_file(resolve_checkpoint(os.devnull), "checkpoint", weights_only=True)
