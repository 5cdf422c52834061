"""Folder prediction as a library call: plan, resume, image-only frames and failures as values."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from deltar.inference.estimator import DepthEstimator
from deltar.inference.folder import check_valid_zones, plan_jobs, run_jobs
from deltar.io.zone_file import save_zone_frame
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet

torch.set_num_threads(1)


def _write_frame(folder, stem, rng, valid=True):
    Image.fromarray(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(
        folder / f"{stem}.png")
    mean = np.full(64, 1.5 if valid else 0.0)
    save_zone_frame(folder / f"{stem}.json",
                    ZoneFrame(mean, np.full(64, 0.02), np.full(64, valid)))
    return folder / f"{stem}.png", folder / f"{stem}.json"


@pytest.fixture
def frames(tmp_path):
    rng = np.random.default_rng(0)
    inputs = tmp_path / "in"
    inputs.mkdir()
    return [_write_frame(inputs, "a", rng), _write_frame(inputs, "b", rng, valid=False)]


def test_run_reports_image_only_frames_and_resumes(tmp_path, frames):
    out = tmp_path / "out"
    out.mkdir()
    estimator = DepthEstimator(ZonePainterNet(), weights="painter", blend=None)
    jobs, complete, existing = plan_jobs(frames, out, ("npy",), overwrite=False,
                                         skip_existing=False)
    assert (len(jobs), complete, existing) == (2, 0, [])
    seen = []
    summary = run_jobs(jobs, estimator, out, allow_no_zones=True,
                       on_prediction=lambda job, rgb, pred: seen.append(job.image.name))
    assert summary.written == 2 and summary.image_only == ["b.png"] and not summary.failed
    assert seen == ["a.png", "b.png"]
    depth = np.load(out / "a_depth_m.npy")
    assert depth.shape == (48, 64) and np.median(depth) == pytest.approx(1.5, abs=1e-5)
    # A second plan finds every output: refused by default, left out when resuming.
    _, _, existing = plan_jobs(frames, out, ("npy",), overwrite=False, skip_existing=False)
    assert sorted(p.name for p in existing) == ["a_depth_m.npy", "b_depth_m.npy"]
    jobs, complete, _ = plan_jobs(frames, out, ("npy", "png16"), overwrite=False,
                                  skip_existing=True)
    assert complete == 0 and [job.kinds for job in jobs] == [("png16",), ("png16",)]


def test_a_failing_frame_stops_the_run_or_is_reported(tmp_path, frames):
    out = tmp_path / "out"
    out.mkdir()
    estimator = DepthEstimator(ZonePainterNet(), weights="painter", blend=None)
    jobs, _, _ = plan_jobs(frames, out, ("npy",), overwrite=False, skip_existing=False)
    with pytest.raises(ValueError, match=r"b\.json: no valid zone.*pass --allow"):
        run_jobs(jobs, estimator, out, allow_option="--allow")
    failures = []
    summary = run_jobs(jobs, estimator, out, overwrite=True, keep_going=True,
                       on_failure=lambda name, err: failures.append(name))
    assert summary.written == 1 and failures == ["b.png"]
    assert summary.failed[0][0] == "b.png" and isinstance(summary.failed[0][1], ValueError)


def test_outputs_show_the_undistorted_image_the_depth_belongs_to(tmp_path, frames):
    """With lens distortion the depth is for the undistorted image: the pictures and the
    point cloud's colours take that image, not the raw one."""
    from deltar.calibration.extrinsic import nominal_extrinsics
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.data.rgbd_files import read_color
    from deltar.inference.outputs import depth_to_points
    from deltar.io.ply import read_ply

    calib = RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48),
                           nominal_extrinsics(),
                           distortion=(-0.3, 0.1, 0.0, 0.0, 0.0))
    out = tmp_path / "out"
    out.mkdir()
    estimator = DepthEstimator(ZonePainterNet(), weights="painter", blend=None)
    jobs, _, _ = plan_jobs(frames[:1], out, ("ply",), overwrite=False, skip_existing=False)
    shown = []
    run_jobs(jobs, estimator, out, calibration=calib,
             on_prediction=lambda job, rgb, pred: shown.append((rgb, pred)))
    shown, prediction = shown[0]
    raw = read_color(frames[0][0])
    np.testing.assert_array_equal(shown, calib.undistort_image(raw))
    assert np.abs(shown.astype(int) - raw).mean() > 5
    _, expected = depth_to_points(prediction.depth_m, prediction.intrinsics, shown)
    np.testing.assert_array_equal(read_ply(out / "a_cloud.ply").colors, expected)


def test_an_output_that_would_replace_an_input_is_refused(tmp_path, frames):
    # a.png's colour output is a_depth_color.png, the image of another pair.
    clash = _write_frame(frames[0][0].parent, "a_depth_color", np.random.default_rng(1))
    with pytest.raises(ValueError, match=r"a_depth_color\.png would overwrite an input"):
        plan_jobs([frames[0], clash], frames[0][0].parent, ("color",), overwrite=True,
                  skip_existing=False)


def test_a_frame_without_valid_zones_is_refused_saying_why(tmp_path):
    empty = np.zeros((8, 8))
    open_space = ZoneFrame(empty, empty, np.zeros((8, 8), bool),
                           no_target=np.ones((8, 8), bool))
    with pytest.raises(ValueError, match=r"z\.json: no valid zone \(all 64 report no target: "
                                         r"nothing within the sensor's range\).*--allow"):
        check_valid_zones(open_space, tmp_path / "z.json", allow="--allow-no-zones")
    some = np.zeros((8, 8), bool)
    some[0, :3] = True
    failed = ZoneFrame(empty, empty, np.zeros((8, 8), bool), no_target=some)
    with pytest.raises(ValueError, match=r"all 64 invalid: error codes.*; 3 report no target"):
        check_valid_zones(failed, tmp_path / "z.json")
    dark = ZoneFrame(empty, empty, np.zeros((8, 8), bool))
    with pytest.raises(ValueError, match=r"all 64 invalid: error codes, out of range or "
                                         r"flagged invalid\)"):
        check_valid_zones(dark, tmp_path / "z.json")
    check_valid_zones(open_space, tmp_path / "z.json", allow_no_zones=True)
