"""RGB-D folder readers on the shared real folders and on small generated folders."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from PIL import Image

from deltar.camera import CameraIntrinsics
from deltar.data.rgbd import (
    FolderReader,
    SevenScenesReader,
    TUMReader,
    detect_layout,
    open_rgbd,
)


def _raw_depth(path) -> np.ndarray:
    return np.asarray(Image.open(path))


def test_seven_scenes_shared_folder(shared_data):
    folder = shared_data / "7scenes_redkitchen"
    reader = open_rgbd(folder)
    assert isinstance(reader, SevenScenesReader)
    assert len(reader) == 500
    frame = reader[0]
    assert frame.name == "frame-000000"
    assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
    assert (frame.intrinsics.fx, frame.intrinsics.fy, frame.intrinsics.cx,
            frame.intrinsics.cy) == (585.0, 585.0, 320.0, 240.0)
    raw = _raw_depth(folder / "frame-000000.depth.png")
    invalid = (raw == 0) | (raw == 65535)
    assert np.all(frame.depth_m[invalid] == 0.0)
    np.testing.assert_allclose(frame.depth_m[~invalid], raw[~invalid] / 1000.0, rtol=1e-6)
    assert 0.3 < np.median(frame.depth_m[~invalid]) < 6.0


def test_realsense_office_is_read_in_millimetres(shared_data):
    folder = shared_data / "realsense_office"
    assert detect_layout(folder) == "tum"
    intr = CameraIntrinsics(615.0, 615.0, 320.0, 240.0, 640, 480)
    reader = open_rgbd(folder, intrinsics=intr)
    assert isinstance(reader, TUMReader)
    assert reader.depth_scale == 1000.0
    assert len(reader) == 97
    frame = reader[0]
    assert frame.name == "rgb00002"
    assert frame.timestamp_s == pytest.approx(0.00585412979126)
    raw = _raw_depth(folder / "depth" / "depth00002.png")
    np.testing.assert_allclose(frame.depth_m[raw > 0], raw[raw > 0] / 1000.0, rtol=1e-6)
    # A desk scene in millimetres: a median of a metre or so, not a fifth of it.
    assert 0.4 < np.median(frame.depth_m[raw > 0]) < 4.0
    assert frame.intrinsics == intr


def test_icl_folder_loads_with_default_intrinsics_warning(shared_data):
    folder = shared_data / "icl_livingroom1"
    with pytest.warns(UserWarning, match="intrinsics"):
        reader = open_rgbd(folder)
    assert isinstance(reader, FolderReader)
    assert len(reader) == 211
    frame = reader[3]
    assert frame.name == "00003"
    assert (frame.intrinsics.fx, frame.intrinsics.cx, frame.intrinsics.cy) == (
        525.0, 319.5, 239.5)
    assert 0.3 < np.median(frame.depth_m[frame.depth_m > 0]) < 8.0


def _write_png16(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array.astype(np.uint16)).save(path)


def _write_rgb(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def test_tum_benchmark_lists_are_associated_with_scale_5000(tmp_path, rng):
    for i, t in enumerate((1.00, 2.00)):
        _write_rgb(tmp_path / "rgb" / f"{t:.2f}.png",
                   rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
        _write_png16(tmp_path / "depth" / f"{t + 0.01:.2f}.png", np.full((6, 8), 5000 * (i + 1)))
    (tmp_path / "rgb.txt").write_text("# colour\n1.00 rgb/1.00.png\n2.00 rgb/2.00.png\n")
    # The second depth frame is 10 ms off, the third has no colour partner.
    (tmp_path / "depth.txt").write_text("1.01 depth/1.01.png\n2.01 depth/2.01.png\n"
                                        "9.00 depth/none.png\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = open_rgbd(tmp_path)
    assert isinstance(reader, TUMReader) and reader.depth_scale == 5000.0
    assert len(reader) == 2
    np.testing.assert_allclose(reader[1].depth_m, 2.0)
    assert reader[1].timestamp_s == pytest.approx(2.0)


def test_sidecar_sets_scale_and_intrinsics(tmp_path, rng):
    _write_rgb(tmp_path / "color" / "a.jpg", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "depth" / "a.png", np.full((6, 8), 300))
    (tmp_path / "deltar_rgbd.json").write_text(json.dumps(
        {"depth_scale": 100.0, "intrinsics": {"fx": 10, "fy": 11, "cx": 3.5, "cy": 2.5}}))
    frame = open_rgbd(tmp_path)[0]
    np.testing.assert_allclose(frame.depth_m, 3.0)
    assert frame.intrinsics == CameraIntrinsics(10.0, 11.0, 3.5, 2.5, 8, 6)
    # Keyword arguments win over the sidecar.
    np.testing.assert_allclose(open_rgbd(tmp_path, depth_scale=1000.0)[0].depth_m, 0.3)


def test_size_mismatch_names_the_file(tmp_path, rng):
    intr = CameraIntrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    _write_rgb(tmp_path / "color" / "a.png", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "depth" / "a.png", np.full((6, 7), 300))
    with pytest.raises(ValueError, match=r"a\.png"):
        FolderReader(tmp_path, 1000.0, intr)[0]


def test_images_without_a_partner_are_left_out_with_a_warning(tmp_path, rng):
    intr = CameraIntrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    for stem in ("a", "b", "c"):
        _write_rgb(tmp_path / "color" / f"{stem}.png",
                   rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    for stem in ("a", "c"):
        _write_png16(tmp_path / "depth" / f"{stem}.png", np.full((6, 8), 300))
    with pytest.warns(UserWarning, match=r"1 image\(s\) without a partner .* left out "
                      r"\(e\.g\. 'b'\); 2 pairs are read"):
        reader = FolderReader(tmp_path, 1000.0, intr)
    assert len(reader) == 2


def test_unknown_layout_and_missing_intrinsics_file(tmp_path, rng):
    with pytest.raises(ValueError, match="cannot tell the layout"):
        open_rgbd(tmp_path)
    _write_rgb(tmp_path / "frame-000000.color.png",
               rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "frame-000000.depth.png", np.full((6, 8), 1000))
    with pytest.raises(FileNotFoundError, match=r"camera-intrinsics\.txt"):
        open_rgbd(tmp_path)
    (tmp_path / "camera-intrinsics.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(ValueError, match="3x3"):
        open_rgbd(tmp_path)


@pytest.mark.parametrize("layout", ["7scenes", "folder"])
def test_an_intrinsics_file_that_is_a_folder_is_refused_naming_it(tmp_path, rng, layout):
    """The folder layout ignored it and fell back to the Kinect default with a warning."""
    colour, depth = (("frame-000000.color.png", "frame-000000.depth.png") if layout == "7scenes"
                     else ("color/000000.png", "depth/000000.png"))
    _write_rgb(tmp_path / colour, rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / depth, np.full((6, 8), 1000))
    (tmp_path / "camera-intrinsics.txt").mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not the default-intrinsics warning
        with pytest.raises(IsADirectoryError, match=r"intrinsics file .*camera-intrinsics\.txt "
                           "is a folder, not a file"):
            open_rgbd(tmp_path)


def test_a_frames_intrinsics_file_that_is_a_folder_is_refused_naming_it(tmp_path, rng):
    _write_rgb(tmp_path / "color" / "a.png", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "depth" / "a.png", np.full((6, 8), 1000))
    (tmp_path / "camera-intrinsics.txt").write_text("7 0 3.5\n0 7 2.5\n0 0 1\n")
    (tmp_path / "intrinsics" / "a.txt").mkdir(parents=True)
    with pytest.raises(IsADirectoryError, match=r"intrinsics file .*intrinsics/a\.txt is a "
                       "folder, not a file"):
        open_rgbd(tmp_path)


def test_tum_lists_with_bad_lines_name_the_file_line_and_columns(tmp_path):
    (tmp_path / "associations.txt").write_text("# t rgb t depth\n\n0.5 c.png 0.5\n")
    with pytest.raises(ValueError, match=r"associations\.txt:3: expected 'timestamp rgb "
                       r"timestamp depth', got '0\.5 c\.png 0\.5'"):
        TUMReader(tmp_path)
    (tmp_path / "associations.txt").write_text("0.5 c.png later d.png\n")
    with pytest.raises(ValueError, match=r"associations\.txt:1: bad timestamp 'later'"):
        TUMReader(tmp_path)
    (tmp_path / "associations.txt").unlink()
    (tmp_path / "rgb.txt").write_text("1.0\n")
    (tmp_path / "depth.txt").write_text("1.0 d.png\n")
    with pytest.raises(ValueError, match=r"rgb\.txt:1: expected 'timestamp path'"):
        TUMReader(tmp_path)


@pytest.mark.parametrize("stamp", ["nan", "inf", "-Infinity", "1e400"])
@pytest.mark.parametrize("listed", ["associations.txt", "rgb.txt", "depth.txt"])
def test_a_tum_time_stamp_that_is_not_finite_is_refused_naming_file_and_line(tmp_path, rng,
                                                                             stamp, listed):
    for name in ("c", "d"):
        _write_rgb(tmp_path / f"{name}.png", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    lines = {"rgb.txt": "1.0 c.png\n", "depth.txt": "1.0 d.png\n"}
    if listed == "associations.txt":
        lines = {listed: "1.0 c.png 1.0 d.png\n"}
    lines[listed] += f"{stamp} c.png {stamp} d.png\n"
    for name, text in lines.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=rf"{listed.replace('.', '[.]')}:2: bad timestamp "
                       f"'{stamp}' \\(not a finite number of seconds\\)"):
        TUMReader(tmp_path)


def test_sidecar_intrinsics_for_a_tum_folder_with_other_subfolders(tmp_path, rng):
    _write_rgb(tmp_path / "cam" / "c1.png", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "tof" / "d1.png", np.full((6, 8), 2000))
    (tmp_path / "associations.txt").write_text("0.5 cam/c1.png 0.5 tof/d1.png\n")
    (tmp_path / "deltar_rgbd.json").write_text(json.dumps(
        {"intrinsics": {"fx": 7, "fy": 7, "cx": 3.5, "cy": 2.5}}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # intrinsics are given: no fallback warning
        frame = open_rgbd(tmp_path)[0]
    assert frame.intrinsics == CameraIntrinsics(7.0, 7.0, 3.5, 2.5, 8, 6)
    np.testing.assert_allclose(frame.depth_m, 2.0)  # associations only: millimetres


def test_per_frame_intrinsics_folder(shared_data):
    """arc_totes: three cameras in one folder, each frame with its intrinsics/<stem>.txt."""
    folder = shared_data / "arc_totes"
    reader = open_rgbd(folder)
    for index in range(len(reader)):
        frame = reader[index]
        expected = np.loadtxt(folder / "intrinsics" / f"{frame.name}.txt")
        assert (frame.intrinsics.fx, frame.intrinsics.cy) == pytest.approx(
            (expected[0, 0], expected[1, 2]))
    assert len({reader[i].intrinsics.cy for i in range(len(reader))}) > 1
    # Intrinsics given by the caller win over the per-frame files.
    given = CameraIntrinsics(600.0, 600.0, 320.0, 240.0, width=640, height=480)
    assert open_rgbd(folder, intrinsics=given)[1].intrinsics == given


def test_the_frames_poses_from_the_folders_pose_files(shared_data, tmp_path, rng):
    from deltar.io.pose_file import read_pose_file

    cabinet = open_rgbd(shared_data / "tum_fr3_cabinet")
    poses = cabinet.poses()
    assert len(poses) == len(cabinet) == 58
    np.testing.assert_array_equal(
        poses[3], read_pose_file(shared_data / "tum_fr3_cabinet" / "pose" / "000003.txt"))
    kitchen = open_rgbd(shared_data / "7scenes_redkitchen").poses()
    assert all(pose is not None for pose in kitchen) and len(kitchen) == 500
    assert open_rgbd(shared_data / "apc_shelf").poses() is None
    # A folder whose frames only partly have poses; a pose that is no rotation is named.
    intr = CameraIntrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    for stem in ("a", "b"):
        _write_rgb(tmp_path / "color" / f"{stem}.png",
                   rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
        _write_png16(tmp_path / "depth" / f"{stem}.png", np.full((6, 8), 1000))
    (tmp_path / "pose").mkdir()
    (tmp_path / "pose" / "b.txt").write_text("1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    partial = FolderReader(tmp_path, 1000.0, intr).poses()
    assert partial[0] is None and partial[1][0, 3] == 0.5
    (tmp_path / "pose" / "a.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"a\.txt: the pose's 3x3 block is not a rotation"):
        FolderReader(tmp_path, 1000.0, intr).poses()


@pytest.mark.parametrize("settings, words", [
    ({"depth_scale": "1000"}, "depth_scale must be a finite number > 0"),
    ({"depth_scale": [1000]}, "depth_scale must be a finite number > 0"),
    ({"depth_scale": -1}, "depth_scale must be a finite number > 0"),
    ({"layout": "xyz"}, "layout must be one of"),
    ({"intrinsics": 5}, "intrinsics must be an object with fx, fy, cx, cy"),
    ({"intrinsics": {"fx": "a", "fy": 1, "cx": 1, "cy": 1}}, "intrinsics fx must be a number"),
])
def test_sidecar_values_of_the_wrong_kind_name_the_file(tmp_path, rng, settings, words):
    _write_rgb(tmp_path / "color" / "a.png", rng.integers(0, 256, (6, 8, 3), dtype=np.uint8))
    _write_png16(tmp_path / "depth" / "a.png", np.full((6, 8), 300))
    (tmp_path / "deltar_rgbd.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match=r"deltar_rgbd\.json: " + words):
        open_rgbd(tmp_path)


def test_a_tum_list_that_is_not_text_names_the_file(tmp_path):
    (tmp_path / "associations.txt").write_bytes(b"\xff\xfe\x00 binary\n")
    with pytest.raises(ValueError, match=r"associations\.txt: cannot read TUM list: not UTF-8"):
        open_rgbd(tmp_path)
