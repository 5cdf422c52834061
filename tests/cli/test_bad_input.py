"""Bad input on every command: one ``error:`` line naming the option or file, early.

Each test asserts the message (not only the exit code). Commands use the random
``deltar-lite`` preset on 48x64 images; "before the model" is checked by the absence of
the preset's random-weights warning, printed when the network is built.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from deltar.calibration.rig import RigCalibration
from deltar.calibration.synthetic import synthetic_rig_frames, write_synthetic_recording
from deltar.camera import CameraIntrinsics
from deltar.cli.main import app
from deltar.io.zone_file import save_zone_frame, zone_frame_to_dict
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame

runner = CliRunner()
LITE = ["--preset", "deltar-lite", "--threads", "1"]
MODEL_BUILT = "random, untrained weights"


def _run(args, **kwargs):
    return runner.invoke(app, [str(a) for a in args], **kwargs)


def _one_error_line(result, *needles):
    """The run failed with exactly one ``error:`` line on stderr holding every needle."""
    assert result.exception is None or isinstance(result.exception, SystemExit), \
        result.exception
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.output
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def inputs(tmp_path, rng):
    folder = tmp_path / "in"
    folder.mkdir()
    Image.fromarray(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(folder / "a.png")
    frame = ZoneFrame(rng.uniform(0.5, 3, 64), np.full(64, 0.03), np.ones(64, bool))
    save_zone_frame(folder / "a.json", frame)
    return folder


def _zones(folder, name, **changes):
    data = json.loads((folder / "a.json").read_text())
    data.update(changes)
    (folder / name).write_text(json.dumps(data))
    return folder / name


def _predict(inputs, out, image="a.png", zones="a.json", *extra):
    return _run(["predict", "--image", inputs / image, "--zones", inputs / zones, "--out", out,
                 "--outputs", "npy", *LITE, *extra])


# ------------------------------------------------------------------ silently wrong before
def test_depth_png_as_image_is_refused(inputs, tmp_path):
    Image.fromarray(np.full((48, 64), 1500, np.uint16)).save(inputs / "depth.png")
    result = _predict(inputs, tmp_path / "out", "depth.png")
    assert result.exit_code == 1
    _one_error_line(result, "depth.png", "single-channel 16-bit image")
    assert MODEL_BUILT not in result.output and not (tmp_path / "out").exists()


@pytest.mark.parametrize("value, shown", [("1.5", "str '1.5'"), (True, "bool True")])
def test_zone_values_must_be_numbers(inputs, tmp_path, value, shown):
    zones = _zones(inputs, "bad.json", mean_m=[value] * 64)
    result = _predict(inputs, tmp_path / "out", zones=zones.name)
    assert result.exit_code == 1
    _one_error_line(result, "bad.json: mean_m must hold numbers", shown)


@pytest.mark.parametrize("content", [
    {"mean_m": [0.0] * 64, "sigma_m": [0.0] * 64, "valid": [False] * 64},
    {"distance_mm": [-3] * 64, "range_sigma_mm": [0] * 64, "target_status": [5] * 64},
], ids=["all-invalid", "driver-error-codes"])
def test_frame_without_valid_zone_is_refused_unless_allowed(inputs, tmp_path, content):
    path = inputs / "dark.json"
    base = json.loads((inputs / "a.json").read_text()) if "mean_m" in content else {}
    path.write_text(json.dumps({**base, **content}))
    refused = _predict(inputs, tmp_path / "out", zones="dark.json")
    assert refused.exit_code == 1
    _one_error_line(refused, "dark.json: no valid zone", "--allow-no-zones")
    assert MODEL_BUILT not in refused.output

    out = tmp_path / "allowed"
    allowed = _run(["predict", "--image", inputs / "a.png", "--zones", path, "--out", out,
                    "--outputs", "png16,npy,color,ply", "--allow-no-zones", *LITE])
    assert allowed.exit_code == 0, allowed.output
    assert "image-only estimate" in allowed.stderr and "(1 image-only)" in allowed.stdout
    note = b"image-only estimate: no valid zone, metric scale unknown"
    for name in ("a_depth_mm.png", "a_depth_color.png"):
        with Image.open(out / name) as img:
            assert img.text.get("deltar") == note.decode()
    assert note in (out / "a_cloud.ply").read_bytes().split(b"end_header")[0]
    assert np.isfinite(np.load(out / "a_depth_m.npy")).all()


@pytest.mark.parametrize("mean, shown", [([1e6] + [1.5] * 63, "1e+06"), ([0.0] * 64, "0 m")])
def test_impossible_distances_are_refused(inputs, tmp_path, mean, shown):
    zones = _zones(inputs, "far.json", mean_m=mean)
    result = _predict(inputs, tmp_path / "out", zones=zones.name)
    assert result.exit_code == 1
    _one_error_line(result, "far.json", "outside the VL53L5CX range 0 < d <= 4 m", shown)


def test_driver_zones_beyond_range_are_invalidated_with_one_warning_line(inputs, tmp_path):
    """In a real run (not under pytest's warning capture) a library warning is one line."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    dump = {"distance_mm": [1500] * 63 + [9000], "range_sigma_mm": [20] * 64,
            "target_status": [5] * 64}
    (inputs / "driver.json").write_text(json.dumps(dump))
    src = str(Path(__file__).resolve().parents[2] / "src")
    env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run([sys.executable, "-m", "deltar", "predict", "--image",
                           str(inputs / "a.png"), "--zones", str(inputs / "driver.json"),
                           "--out", str(tmp_path / "out"), "--outputs", "npy", *LITE],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    nominal = [line for line in lines if line.startswith("warning: no --calib: the zones")]
    assert len(nominal) == 1
    assert [line for line in lines if line not in nominal] == [
        "warning: 1 zone(s) with a valid status read more than the VL53L5CX's 4 m range "
        "(up to 9 m); marked invalid",
        "warning: preset 'deltar-lite' has random, untrained weights: its depth is "
        "meaningless"]


@pytest.mark.parametrize("args, option", [
    (["--threads", "0"], "--threads"), (["--threads", "-1"], "--threads")])
def test_predict_thread_counts_below_one_are_usage_errors(inputs, tmp_path, args, option):
    result = _predict(inputs, tmp_path / "out", "a.png", "a.json", *args)
    assert result.exit_code == 2
    _one_error_line(result, f"Invalid value for '{option}'", "deltar predict --help")


def test_replay_every_zero_is_a_usage_error(tmp_path):
    result = _run(["replay", tmp_path, "--out", tmp_path / "o", "--every", "0", *LITE])
    assert result.exit_code == 2
    _one_error_line(result, "'--every'")


@pytest.fixture
def zju_set(tmp_path):
    """A one-frame ZJU-L5-layout set (its data.json)."""
    data = tmp_path / "set" / "data.json"
    assert _run(["simulate", "procedural:1:0:48x64", data.parent]).exit_code == 0
    return data


def test_evaluate_refuses_to_overwrite_json_without_overwrite(tmp_path, zju_set):
    data = zju_set
    metrics = tmp_path / "metrics.json"
    metrics.write_text("keep\n")
    refused = _run(["evaluate", "--data", data, "--method", "nearest", "--json", metrics])
    assert refused.exit_code == 1
    _one_error_line(refused, f"--json {metrics} exists; pass --overwrite")
    assert metrics.read_text() == "keep\n"
    replaced = _run(["evaluate", "--data", data, "--method", "nearest", "--json", metrics,
                     "--overwrite"])
    assert replaced.exit_code == 0, replaced.output
    assert "nearest" in json.loads(metrics.read_text())


# ------------------------------------------------------------------ tracebacks before
def test_unwritable_out_is_found_before_the_model(inputs, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    result = _predict(inputs, blocker)
    _one_error_line(result, f"--out {blocker} is a file, not a folder")
    result = _predict(inputs, blocker / "sub")
    _one_error_line(result, f"{blocker} is a file, not a folder")
    assert MODEL_BUILT not in result.output


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a GPU")
def test_cuda_without_gpu_and_unknown_devices(inputs, tmp_path):
    result = _predict(inputs, tmp_path / "out", "a.png", "a.json", "--device", "cuda")
    assert result.exit_code == 2
    _one_error_line(result, "Invalid value for --device:", "no CUDA GPU is available")
    result = _predict(inputs, tmp_path / "out", "a.png", "a.json", "--device", "bogus")
    _one_error_line(result, "Invalid value for --device:", "unknown device 'bogus'")


@pytest.fixture
def recording(tmp_path):
    rec = tmp_path / "rec"
    assert _run(["record", rec, "--simulate", "wall:1.5:4:48x64"]).exit_code == 0
    return rec


def test_replay_show_without_display(recording, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    result = _run(["replay", recording, "--show", *LITE])
    assert result.exit_code == 1
    _one_error_line(result, "--show needs a display", "--out DIR")
    assert MODEL_BUILT not in result.output


def test_simulate_names_the_option_at_fault(tmp_path):
    source = tmp_path / "src"
    (source / "color").mkdir(parents=True)
    (source / "depth").mkdir()
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(source / "color" / "0.png")
    Image.fromarray(np.full((48, 64), 1500, np.uint16)).save(source / "depth" / "0.png")
    (source / "camera-intrinsics.txt").write_text("60 0 31.5\n0 60 23.5\n0 0 1\n")
    for args, option in ((["--intrinsics", "nan,60,31.5,23.5"], "--intrinsics"),
                         (["--depth-scale", "0"], "--depth-scale")):
        result = _run(["simulate", source, tmp_path / "out", *args])
        assert result.exit_code == 2
        _one_error_line(result, f"Invalid value for {option}")


def test_simulate_and_demo_refuse_tiny_sizes_and_files(tmp_path):
    result = _run(["simulate", "procedural:1:0:1x1", tmp_path / "s"])
    _one_error_line(result, "SRC", "8 to 4096 pixels a side, got 1x1")
    result = _run(["simulate", "procedural:2:0:100000x100000", tmp_path / "s"])
    _one_error_line(result, "SRC", "8 to 4096 pixels a side, got 100000x100000")
    result = _run(["simulate", "procedural:1000000000", tmp_path / "s", "--limit", "1",
                   "--cnh-bins", "100000000"])
    assert result.exit_code == 2 and "--cnh-bins" in result.output  # at once, bounded
    result = _run(["simulate", "procedural:1000000000:0:32x32", tmp_path / "s", "--limit",
                   "1"])  # the billion frames are not listed to take one
    assert result.exit_code == 0, result.output
    result = _run(["demo", tmp_path / "d", "--frames", "1", "--size", "1x1"])
    assert result.exit_code == 2
    _one_error_line(result, "Invalid value for --size:", "at least 8 pixels")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    result = _run(["demo", blocker, "--frames", "1", "--size", "48x64"])
    _one_error_line(result, f"OUT {blocker} is a file, not a folder")


def test_evaluate_model_variants_without_a_model(zju_set):
    for option in ("--flip", "--network"):
        result = _run(["evaluate", "--data", zju_set, "--method", "bilinear", option])
        assert result.exit_code == 2
        _one_error_line(result, f"Invalid value for {option}", "--checkpoint default")


def test_evaluate_save_vis_pointing_at_a_file(tmp_path, zju_set):
    blocker = tmp_path / "vis.txt"
    blocker.write_text("x")
    result = _run(["evaluate", "--data", zju_set, "--method", "nearest", "--save-vis", blocker])
    _one_error_line(result, f"--save-vis {blocker} is a file, not a folder")
    inside = _run(["evaluate", "--data", zju_set, "--method", "nearest", "--save-vis",
                   zju_set.parent / "vis"])
    _one_error_line(inside, "--save-vis", "is inside the input")


CAMERA = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [92.0, -1.0, 1.5], degrees=True).as_matrix(),
                        np.array([0.03, 0.01, -0.01]))


@pytest.fixture(scope="module")
def calib_recordings(tmp_path_factory):
    root = tmp_path_factory.mktemp("cal")
    frames = synthetic_rig_frames(TRUE, CAMERA, frames_per_plane=2, mean_noise_m=0.01, seed=5)
    write_synthetic_recording(root / "rec", frames, CAMERA)
    write_synthetic_recording(root / "nodepth", frames, CAMERA, with_depth=False)
    return root


def test_calibrate_refuses_nan_roll_and_checks_plot_before_writing(calib_recordings, tmp_path):
    result = _run(["calibrate", calib_recordings / "rec", "--out", tmp_path / "c.json",
                   "--nominal-roll-deg", "nan"])
    assert result.exit_code == 2
    _one_error_line(result, "Invalid value for --nominal-roll-deg:", "finite")
    blocker = tmp_path / "plot.txt"
    blocker.write_text("x")
    result = _run(["calibrate", calib_recordings / "rec", "--out", tmp_path / "c.json",
                   "--plot", blocker])
    _one_error_line(result, f"--plot {blocker} is a file, not a folder")
    assert not (tmp_path / "c.json").exists()  # no partial output


def test_calibrate_explains_fov_missing_depth_and_wrong_roll(calib_recordings, tmp_path):
    result = _run(["calibrate", calib_recordings / "rec", "--out", tmp_path / "c.json",
                   "--fov", "0,0"])
    _one_error_line(result, "Invalid value for --fov:", "(0, 180) degrees")
    result = _run(["calibrate", calib_recordings / "nodepth", "--out", tmp_path / "c.json"])
    _one_error_line(result, "no depth image within 0.02 s of any zone frame",
                    "SLAM map")
    result = _run(["calibrate", calib_recordings / "rec", "--out", tmp_path / "c.json",
                   "--nominal-roll-deg", "-90"])
    assert result.exit_code == 1
    _one_error_line(result, "--nominal-roll-deg -90 may be wrong",
                    "with --nominal-roll-deg 90 this recording calibrates")


def test_calibrate_counts_zone_frames_without_an_image(calib_recordings, tmp_path):
    rec = tmp_path / "rec"
    import shutil

    shutil.copytree(calib_recordings / "rec", rec)
    lines = (rec / "zones.jsonl").read_text().splitlines()
    extra = json.loads(lines[-1])
    extra["timestamp_s"] += 100.0  # a zone frame long after the last image
    (rec / "zones.jsonl").write_text("\n".join([*lines, json.dumps(extra)]) + "\n")
    result = _run(["calibrate", rec, "--out", tmp_path / "c.json"])
    assert result.exit_code == 0, result.output
    assert "zone frames without an image within 0.02 s: 1" in result.stdout


# ------------------------------------------------------------------ misleading before
def test_checkpoint_errors_never_advise_unsafe_loading(inputs, tmp_path):
    text = tmp_path / "text.pt"
    text.write_text("e" * 200)
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"PK\x03\x04" + bytes(100))
    for path, reason in ((text, "not a PyTorch file"), (broken, "corrupt or truncated")):
        result = _run(["predict", "--image", inputs / "a.png", "--zones", inputs / "a.json",
                       "--out", tmp_path / "out", "--checkpoint", path])
        line = _one_error_line(result, f"{path}: cannot read checkpoint", reason)
        assert "weights_only" not in result.output and ": 101" not in line


def test_record_grid_three_names_the_option(tmp_path):
    result = _run(["record", tmp_path / "r", "--simulate", "wall:1.5:2:48x64", "--grid", "3"])
    assert result.exit_code == 2
    _one_error_line(result, "Invalid value for --grid:", "must be 4 or 8, got 3")


def test_messages_are_printed_literally(tmp_path, inputs):
    result = _run(["predict", "--image", tmp_path / "[scan]missing.png", "--zones",
                   inputs / "a.json", "--out", tmp_path / "out", *LITE])
    _one_error_line(result, "[scan]missing.png")


# ------------------------------------------------------------------ fail fast, resume
def test_bad_calibration_and_existing_outputs_are_found_before_the_model(inputs, tmp_path):
    (tmp_path / "calib.json").write_text("[1, 2")
    result = _predict(inputs, tmp_path / "out", "a.png", "a.json", "--calib",
                      tmp_path / "calib.json")
    _one_error_line(result, "calib.json: corrupt JSON")
    assert MODEL_BUILT not in result.output
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a_depth_m.npy").write_bytes(b"earlier")
    result = _predict(inputs, tmp_path / "out")
    _one_error_line(result, "refusing to overwrite 1 existing output", "--skip-existing")
    assert MODEL_BUILT not in result.output
    assert (tmp_path / "out" / "a_depth_m.npy").read_bytes() == b"earlier"
    calib = RigCalibration(CameraIntrinsics(500, 500, 319.5, 239.5, 640, 480),
                           SensorExtrinsics()).save(tmp_path / "c640.json")
    result = _predict(inputs, tmp_path / "o2", "a.png", "a.json", "--calib", calib)
    _one_error_line(result, "a.png is 48x64 pixels", "calibrated resolution 480x640")
    assert MODEL_BUILT not in result.output


def test_folder_run_keeps_going_and_resumes(inputs, tmp_path, monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "0")
    frames = tmp_path / "frames"
    frames.mkdir()
    for stem in ("f1", "f2", "f3"):
        (frames / f"{stem}.png").write_bytes((inputs / "a.png").read_bytes())
        (frames / f"{stem}.json").write_text((inputs / "a.json").read_text())
    (frames / "f2.json").write_text("{broken")
    out = tmp_path / "out"
    args = ["predict", "--images", frames, "--zones-dir", frames, "--out", out, "--outputs",
            "npy,png16", *LITE]
    stopped = _run(args)
    assert stopped.exit_code == 1
    _one_error_line(stopped, "f2.json: corrupt JSON")
    assert sorted(p.name for p in out.iterdir()) == ["f1_depth_m.npy", "f1_depth_mm.png"]

    kept = _run([*args, "--skip-existing", "--keep-going"])
    assert kept.exit_code == 1
    assert "1 frame(s) already have every output" in kept.stdout
    assert "warning: skipped f2.png:" in kept.stderr
    _one_error_line(kept, "1 of 2 frames failed (first: f2.png:", "--skip-existing")
    assert {p.name for p in out.iterdir()} >= {"f3_depth_m.npy", "f3_depth_mm.png"}

    # Fix the frame and lose one output of f3 (as if stopped in the middle of it).
    (frames / "f2.json").write_text((inputs / "a.json").read_text())
    (out / "f3_depth_mm.png").unlink()
    kept_file = out / "f3_depth_m.npy"
    before = kept_file.stat().st_mtime_ns
    resumed = _run([*args, "--skip-existing"])
    assert resumed.exit_code == 0, resumed.output
    assert "wrote 2 prediction(s)" in resumed.stdout
    assert "predicting: 1/2 frames" in resumed.stdout and "frames/s" in resumed.stdout
    assert "predicting: 2/2 frames" in resumed.stdout and "done in" in resumed.stdout
    assert kept_file.stat().st_mtime_ns == before and (out / "f3_depth_mm.png").exists()
    assert len(list(out.iterdir())) == 6

    both = _run([*args, "--skip-existing", "--overwrite"])
    assert both.exit_code == 2
    _one_error_line(both, "--overwrite or --skip-existing, not both")


def test_progress_lines_when_not_a_terminal(recording, tmp_path, monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "0")
    result = _run(["replay", recording, "--out", tmp_path / "o", *LITE])
    assert result.exit_code == 0, result.output
    assert "replaying: 1/2 frames" in result.stdout and "ETA" in result.stdout
    assert "replaying: 2/2 frames" in result.stdout


def test_replay_keep_going_reports_a_corrupt_frame_and_exits_1(recording, tmp_path):
    from deltar.io.recording import Recording

    rec = Recording(recording)
    bad = rec.pairs()[0].color_path
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    stopped = _run(["replay", recording, "--out", tmp_path / "o1", "--outputs", "npy", *LITE])
    _one_error_line(stopped, bad.name, "unreadable image")
    going = _run(["replay", recording, "--out", tmp_path / "o2", "--outputs", "npy",
                  "--keep-going", *LITE])
    assert going.exit_code == 1
    assert f"warning: skipped {bad.name}" in going.stderr
    _one_error_line(going, "1 of 2 frames failed", bad.name)
    assert "wrote 1 files" in going.stdout and len(list((tmp_path / "o2").iterdir())) == 1


def test_replay_skips_frames_without_zones_unless_allowed(tmp_path):
    from deltar.io.recording import RecordingMeta, RecordingWriter

    writer = RecordingWriter(tmp_path / "rec", RecordingMeta(
        intrinsics=CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48), sensor_model="VL53L5CX",
        grid=8, fov_deg=(45.0, 45.0)))
    image = np.zeros((48, 64, 3), np.uint8)
    for i, valid in enumerate((True, False)):
        writer.add_color(0.1 * i, image)
        writer.add_zone_frame(ZoneFrame(np.full(64, 1.5 if valid else 0.0), np.full(64, 0.02),
                                        np.full(64, valid), timestamp_s=0.1 * i))
    with pytest.warns(UserWarning, match="t = 0.100 s has no valid zone; skipped"):
        skipped = _run(["replay", tmp_path / "rec", "--out", tmp_path / "o1", "--outputs",
                        "npy", *LITE])
    assert skipped.exit_code == 0, skipped.output
    assert len(list((tmp_path / "o1").glob("*.npy"))) == 1
    allowed = _run(["replay", tmp_path / "rec", "--out", tmp_path / "o2", "--outputs", "npy",
                    "--allow-no-zones", *LITE])
    assert allowed.exit_code == 0, allowed.output
    assert len(list((tmp_path / "o2").glob("*.npy"))) == 2


def test_zone_dict_round_trip_still_loads(tmp_path):
    """Integers and 0/1 validity flags are numbers, not coerced strings: still accepted."""
    frame = ZoneFrame(np.full(16, 2.0), np.full(16, 0.02), np.ones(16, bool))
    data = zone_frame_to_dict(frame)
    data["mean_m"] = [2] * 16
    data["valid"] = [1] * 16
    (tmp_path / "z.json").write_text(json.dumps(data))
    from deltar.io.zone_file import load_zone_frame

    assert load_zone_frame(tmp_path / "z.json").valid.all()


# ------------------------------------------------------------------ round 2: reading boundary
def test_unreadable_inputs_give_one_line_naming_the_file(inputs, tmp_path, monkeypatch):
    (inputs / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    save_zone_frame(inputs / "z.npz", ZoneFrame(np.full(64, 1.5), np.full(64, 0.02),
                                                np.ones(64, bool)))
    (inputs / "t.npz").write_bytes((inputs / "z.npz").read_bytes()[:40])
    calib = json.loads(RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48),
                                      SensorExtrinsics()).save(tmp_path / "c.json").read_text())
    calib["intrinsics"]["width"] = float("inf")
    (tmp_path / "inf.json").write_text(json.dumps(calib))
    for args, line in (
            (["--zones", inputs / "deep.json"],
             f"error: {inputs / 'deep.json'}: cannot read zone frame file: nested too deeply "
             "to parse"),
            (["--zones", inputs / "t.npz"],
             f"error: {inputs / 't.npz'}: cannot read zone frame file: corrupt or truncated "
             "file (File is not a zip file)"),
            (["--zones", inputs / "a.json", "--calib", tmp_path / "inf.json"],
             f"error: {tmp_path / 'inf.json'}: invalid calibration: width must be an "
             "integer, got inf"),
            (["--zones", inputs / "a.json", "--calib", tmp_path / "none.json"],
             f"error: calibration file not found: {tmp_path / 'none.json'}"),
            (["--zones", inputs / "a.json", "--calib", tmp_path],
             f"error: calibration file {tmp_path} is a folder, not a file"),
            (["--zones", inputs / "a.json", "--calib", "/dev/null"],
             "error: calibration file /dev/null is not a regular file (a device, pipe or "
             "socket)")):
        result = _run(["predict", "--image", inputs / "a.png", *args, "--out", tmp_path / "o",
                       *LITE])
        assert result.exit_code == 1
        assert _one_error_line(result) == line
        assert MODEL_BUILT not in result.output
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    result = _predict(inputs, tmp_path / "o")
    _one_error_line(result, f"{inputs / 'a.png'}: cannot read colour image: the image is too "
                    "large to decode safely (Image size (3072 pixels) exceeds limit")


def test_image_paths_told_apart(inputs, tmp_path):
    for path, line in ((inputs, f"error: colour image {inputs} is a folder, not a file"),
                       ("/dev/null", "error: colour image /dev/null is not a regular file (a "
                        "device, pipe or socket)"),
                       (inputs / "none.png", f"error: colour image not found: "
                        f"{inputs / 'none.png'}")):
        result = _run(["predict", "--image", path, "--zones", inputs / "a.json", "--out",
                       tmp_path / "o", *LITE])
        assert result.exit_code == 1
        assert _one_error_line(result) == line


def test_traceback_switch_shows_the_reading_error_and_its_cause(inputs, tmp_path,
                                                                monkeypatch):
    (inputs / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    monkeypatch.setenv("DELTAR_TRACEBACK", "1")
    result = _predict(inputs, tmp_path / "o", "a.png", "deep.json")
    assert isinstance(result.exception, ValueError)
    assert isinstance(result.exception.__cause__, RecursionError)


# ------------------------------------------------------------------ round 2: outputs vs inputs
def test_calibrate_never_writes_over_its_recording(calib_recordings, tmp_path):
    import os
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(calib_recordings / "rec", rec)
    before = {p: p.read_bytes() for p in (rec / "meta.json", rec / "zones.jsonl")}
    os.link(rec / "meta.json", tmp_path / "linked.json")
    for out, line in (
            (rec / "meta.json", f"error: --out {rec / 'meta.json'} is inside the input {rec}; "
             "choose a path outside it"),
            (rec / "zones.jsonl", f"error: --out {rec / 'zones.jsonl'} is inside the input "
             f"{rec}; choose a path outside it"),
            (tmp_path / "linked.json", f"error: --out {tmp_path / 'linked.json'} is the input "
             f"{rec / 'meta.json'} (a link to it); an output never replaces an input "
             "(whatever --overwrite says): choose another path")):
        result = _run(["calibrate", rec, "--out", out, "--overwrite"])
        assert result.exit_code == 1
        assert _one_error_line(result) == line
    result = _run(["calibrate", rec, "--out", tmp_path / "c.json", "--plot", rec / "color"])
    _one_error_line(result, f"--plot {rec / 'color'} is inside the input {rec}")
    assert {p: p.read_bytes() for p in before} == before


def test_evaluate_json_never_replaces_a_frame_or_the_index(tmp_path, zju_set):
    frame = next(zju_set.parent.rglob("*.h5"))
    content = frame.read_bytes()
    for target in (frame, zju_set):
        result = _run(["evaluate", "--data", zju_set, "--method", "nearest", "--json", target,
                       "--overwrite"])
        assert result.exit_code == 1
        assert _one_error_line(result) == (
            f"error: --json {target} is the input {target}; an output never replaces an input "
            "(whatever --overwrite says): choose another path")
    assert frame.read_bytes() == content
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"weights")
    for option in ("--checkpoint", "--official"):
        result = _run(["evaluate", "--data", zju_set, option, checkpoint, "--json",
                       checkpoint, "--overwrite"])
        assert result.exit_code == 1
        _one_error_line(result, f"--json {checkpoint} is the input {checkpoint}")
    assert checkpoint.read_bytes() == b"weights"


def test_export_never_replaces_its_checkpoint_and_wall_test_stays_outside(tmp_path,
                                                                           recording):
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"weights")
    result = _run(["export", "--checkpoint", checkpoint, "--out", checkpoint, "--overwrite"])
    assert result.exit_code == 1  # the input is named first, whatever the suffix
    _one_error_line(result, f"--out {checkpoint} is the input {checkpoint}")
    assert checkpoint.read_bytes() == b"weights"
    result = _run(["export", "--checkpoint", checkpoint, "--out", tmp_path / "other.pt"])
    assert result.exit_code == 2 and "must end in .onnx" in result.output
    assert not (tmp_path / "other.pt").exists()
    exported = tmp_path / "model.onnx"
    exported.write_bytes(b"weights")
    result = _run(["export", "--checkpoint", exported, "--out", exported, "--overwrite"])
    assert result.exit_code == 1
    _one_error_line(result, f"--out {exported} is the input {exported}")
    assert exported.read_bytes() == b"weights"
    result = _run(["wall-test", recording, "--out", recording / "wall", *LITE])
    assert result.exit_code == 1
    assert _one_error_line(result) == (f"error: --out {recording / 'wall'} is inside the input "
                                       f"{recording}; choose a path outside it")
    assert MODEL_BUILT not in result.output and not (recording / "wall").exists()
    kept = tmp_path / "wall" / "wall_test.json"  # a checkpoint under an output's name
    kept.parent.mkdir()
    kept.write_bytes(b"weights")
    result = _run(["wall-test", recording, "--out", kept.parent, "--checkpoint", kept,
                   "--overwrite"])
    assert result.exit_code == 1
    _one_error_line(result, f"--out {kept} is the input {kept}")
    assert kept.read_bytes() == b"weights"


def test_replay_of_an_empty_recording_is_an_error(recording, tmp_path):
    (recording / "zones.jsonl").write_text("")
    result = _run(["replay", recording, "--out", tmp_path / "o", *LITE])
    assert result.exit_code == 1
    assert _one_error_line(result) == (f"error: {recording}: nothing to replay: zones.jsonl "
                                       "holds no zone frame")
    assert MODEL_BUILT not in result.output


# ------------------------------------------------------------------ round 2: the machine's limits
def test_thread_counts_beyond_the_machine_are_refused_before_work(inputs, tmp_path):
    from deltar.io.resources import cpu_count

    limit = 4 * cpu_count()
    shown = f"must be between 1 and {limit} (4 x the {cpu_count()} CPUs of this machine)"
    result = _predict(inputs, tmp_path / "o", "a.png", "a.json", "--threads", "1000000")
    assert result.exit_code == 2
    _one_error_line(result, f"--threads {shown}, got 1000000")
    assert MODEL_BUILT not in result.output
    result = _run(["bench", "--preset", "deltar-lite", "--threads", str(limit + 1)])
    assert result.exit_code == 2
    _one_error_line(result, f"--threads {shown}, got {limit + 1}")


def test_bench_refuses_a_json_folder_and_a_huge_matmul_before_running(tmp_path):
    result = _run(["bench", "--preset", "deltar-lite", "--json", tmp_path, "--overwrite"])
    assert result.exit_code == 1
    assert _one_error_line(result) == f"error: --json {tmp_path} is a folder, not a file"
    result = _run(["bench", "--preset", "deltar-lite", "--matmul-size", "60000"])
    assert result.exit_code == 2 and "--matmul-size" in result.output


def test_bench_batch_beyond_the_memory_is_refused(monkeypatch):
    from deltar.io import resources

    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 2**30)
    result = _run(["bench", "--preset", "deltar-lite", "--size", "480x640", "--batch", "64"])
    assert result.exit_code == 2
    assert _one_error_line(result) == (
        "error: Invalid value: --batch 64 at 480x640 needs about 19,200 MiB of memory, more "
        "than the "
        "1,024 MiB this machine has available; lower --batch or --size (see 'deltar bench "
        "--help')")


@pytest.mark.parametrize("override, message", [
    ("trainer.max_steps=0", "trainer.max_steps must be >= 1, or -1 for no limit, got 0 (0 "
     "steps would write an untrained model)"),
    ("trainer.devices=100000", "trainer.devices is 100000 but this machine has"),
    ("trainer.num_threads=100000", "trainer.num_threads must be between 1 and"),
])
def test_training_configs_the_machine_cannot_run_are_refused(tmp_path, override, message):
    from pathlib import Path

    config = Path(__file__).resolve().parents[2] / "configs" / "tiny_test.yaml"
    result = _run(["train", "--config", config, "--override", override, "--run-dir",
                   tmp_path / "run"])
    assert result.exit_code == 2
    _one_error_line(result, message)
    assert not (tmp_path / "run").exists()


def test_simulate_checks_free_space_and_reports_a_full_disk_in_one_line(tmp_path,
                                                                       monkeypatch):
    import os
    import resource
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from deltar.io import resources

    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(resources.shutil, "disk_usage",
                        lambda path: usage._replace(free=1000))
    result = _run(["simulate", "procedural:3:0:48x64", tmp_path / "s"])
    assert result.exit_code == 1
    assert _one_error_line(result) == (f"error: OUT {tmp_path / 's'} (3 frames of 48x64): "
                                       "needs up to 0.2 MiB but "
                                       f"{tmp_path} has 0.0 MiB free")
    assert not (tmp_path / "s").exists()

    # A disk that fills while writing (a file size limit stands in for it): one line.
    src = str(Path(__file__).resolve().parents[2] / "src")
    env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run(
        [sys.executable, "-m", "deltar", "simulate", "procedural:2:0:240x320",
         str(tmp_path / "full")], capture_output=True, text=True, env=env, timeout=300,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, 100_000)))
    assert done.returncode == 1, done.stderr
    assert done.stderr.splitlines() == [
        f"error: {tmp_path / 'full' / 'procedural' / 'procedural-0.h5'}: File too large"]
    assert not list((tmp_path / "full").rglob("*.h5"))


# ------------------------------------------------------------------ round 2: physical validity
@pytest.mark.parametrize("changes, message", [
    ({"sigma_m": [1e6] + [0.03] * 63}, "1 valid zone(s) have a sigma larger than the VL53L5CX "
     "range 4 m (zones [0]: 1e+06 m), which no reading within the range can have; mark such "
     "zones invalid"),
    ({"hist_edges_m": [0.0, 1.0, 2.0], "hist_counts": [[0.0, 0.0]] + [[1.0, 2.0]] * 63},
     "1 valid zone(s) have an all-zero histogram (zones [0]): a zone that counted no photons "
     "measured no distance; mark such zones invalid"),
    ({"status": [255] + [5] * 63}, "ZoneFrame zones [0] are valid but their status is 255 "
     "(no target); a zone either reads a distance or reports no target"),
    ({"status": [5.5] * 64}, "status must hold 64 integer codes in 0..255"),
], ids=["sigma-1e6", "zero-histogram", "valid-and-255", "fractional-status"])
def test_physically_impossible_zone_files_are_refused(inputs, tmp_path, changes, message):
    zones = _zones(inputs, "odd.json", **changes)
    result = _predict(inputs, tmp_path / "out", zones=zones.name)
    assert result.exit_code == 1
    assert _one_error_line(result) == f"error: {zones}: {message}"
    assert MODEL_BUILT not in result.output


def test_calibration_that_cannot_be_right_is_refused_before_the_model(inputs, tmp_path):
    calib = RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48),
                           SensorExtrinsics()).save(tmp_path / "c.json")
    data = json.loads(calib.read_text())
    data["intrinsics"]["cx"] = 640.0
    (tmp_path / "pp.json").write_text(json.dumps(data))
    data["intrinsics"]["cx"] = 31.5
    data["extrinsics"]["translation_m"] = [30.0, 0.0, 0.0]
    (tmp_path / "mm.json").write_text(json.dumps(data))
    for name, message in (("pp.json", "the principal point (cx, cy) = (640, 23.5) px lies "
                           "outside the 48x64 image"),
                          ("mm.json", "the sensor is 30 m from the camera (translation_m "
                           "[30.0, 0.0, 0.0]); a rig's sensor sits within 1 m of it "
                           "(millimetres written as metres?)")):
        result = _predict(inputs, tmp_path / "out", "a.png", "a.json", "--calib",
                          tmp_path / name)
        assert result.exit_code == 1
        assert _one_error_line(result) == (f"error: {tmp_path / name}: invalid calibration: "
                                           f"{message}")
        assert MODEL_BUILT not in result.output


def test_evaluate_refuses_zones_beyond_the_sensor_range(tmp_path, zju_set):
    import h5py

    frame = next(zju_set.parent.rglob("*.h5"))
    with h5py.File(frame, "r+") as f:
        zones = f["hist_data"][()]
        valid = f["mask"][()].reshape(-1)
        first = int(np.flatnonzero(valid)[0])
        zones[first, 0] = 1e6
        f["hist_data"][...] = zones
    result = _run(["evaluate", "--data", zju_set, "--method", "nearest"])
    assert result.exit_code == 1
    _one_error_line(result, f"frame '{frame.parent.name}/{frame.stem}' ({frame}): 1 valid "
                    "zone(s) read "
                    "distances outside the VL53L5CX range 0 < d <= 4 m", "1e+06")


def test_folder_mode_refuses_two_inputs_with_one_stem(inputs, tmp_path):
    (inputs / "a.jpg").write_bytes((inputs / "a.png").read_bytes())
    result = _run(["predict", "--images", inputs, "--zones-dir", inputs, "--out",
                   tmp_path / "out", *LITE])
    assert result.exit_code == 1
    assert _one_error_line(result) == (
        f"error: {inputs / 'a.jpg'} and {inputs / 'a.png'} are images with the same stem 'a'; "
        "frames pair by stem, so keep only one of them")
    assert MODEL_BUILT not in result.output


def test_simulated_set_without_any_valid_zone_is_said(tmp_path):
    result = _run(["simulate", "wall:10:2:48x64", tmp_path / "far"])
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines()[-1] == (
        "warning: 2 of 2 frames have no valid zone (the scene lies beyond the sensor's range, "
        "or returns no signal): depth from them has no metric anchor, and methods that need "
        "zones cannot use them; the set holds no zone reading at all")


@pytest.mark.parametrize("option, path, line", [
    ("--official", "{tmp}", "error: official weights {tmp} is a folder, not a file"),
    ("--onnx", "/dev/null", "error: ONNX model /dev/null is not a regular file (a device, "
     "pipe or socket)"),
    ("--checkpoint", "{tmp}", "error: checkpoint {tmp} is a folder, not a file"),
])
def test_model_paths_told_apart(inputs, tmp_path, option, path, line):
    result = _run(["predict", "--image", inputs / "a.png", "--zones", inputs / "a.json",
                   "--out", tmp_path / "o", option, path.format(tmp=tmp_path)])
    assert result.exit_code == 1
    assert _one_error_line(result) == line.format(tmp=tmp_path)


def test_mismatches_and_option_values_named_before_work(inputs, tmp_path, recording, zju_set):
    calib4 = RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48), SensorExtrinsics(),
                            grid=4).save(tmp_path / "c4.json")
    calib640 = RigCalibration(CameraIntrinsics(500, 500, 319.5, 239.5, 640, 480),
                              SensorExtrinsics()).save(tmp_path / "c640.json")
    _zones(inputs, "count.json", zone_count="64")
    (inputs / "mixed.json").write_text(json.dumps({
        "distance_mm": [1500] * 16, "range_sigma_mm": [20] * 64, "target_status": [5] * 64}))
    for args, code, line in (
            (["predict", "--image", inputs / "a.png", "--zones", inputs / "a.json", "--out",
              tmp_path / "o", "--calib", calib4, *LITE], 1,
             f"error: {inputs / 'a.json'} has a 8x8 zone grid but --calib {calib4} is for 4x4"),
            (["replay", recording, "--out", tmp_path / "o", "--calib", calib640, *LITE], 1,
             f"error: the recording {recording} is 48x64 pixels but --calib {calib640} is for "
             "the calibrated resolution 480x640; resize the images or recalibrate"),
            (["predict", "--image", inputs / "a.png", "--zones", inputs / "count.json", "--out",
              tmp_path / "o", *LITE], 1,
             f"error: {inputs / 'count.json'}: zone_count must be an integer, got '64'"),
            (["predict", "--image", inputs / "a.png", "--zones", inputs / "mixed.json", "--out",
              tmp_path / "o", *LITE], 1,
             f"error: {inputs / 'mixed.json'}: invalid driver output: distance_mm, "
             "range_sigma_mm and target_status must have the same length (one entry per zone "
             "and target), got [16, 64, 64]"),
            (["evaluate", "--data", zju_set, "--method", "nearest", "--min-depth", "5",
              "--max-depth", "1"], 2,
             "error: Invalid value for --min-depth/--max-depth: need 0 < --min-depth < "
             "--max-depth (metres, finite), got 5 and 1 (see 'deltar evaluate --help')"),
            (["simulate", "procedural:2:0:48x64", tmp_path / "s", "--bias-mean", "nan"], 2,
             "error: Invalid value for --bias-mean: must be a finite number, got nan (see "
             "'deltar simulate --help')"),
            (["record", tmp_path / "r", "--simulate", "wall:-1"], 1,
             "error: --simulate wall:-1: distance_m must be > 0, got -1.0"),
            (["record", tmp_path / "r", "--simulate", "wall:1e9:2:48x64"], 1,
             "error: --simulate wall:1e9:2:48x64: depths up to 1e+09 m do not fit a "
             "recording's depth images (16-bit millimetres, at most 65.535 m)"),
            (["export", "--preset", "deltar-lite", "--out", tmp_path / "m.onnx", "--size",
              "1x1"], 2,
             "error: Invalid value for --size: each side must be at least 8 pixels, got '1x1' "
             "(see 'deltar export --help')")):
        result = _run(args)
        assert result.exit_code == code, (args, result.output)
        assert _one_error_line(result) == line
        assert MODEL_BUILT not in result.output
    assert not (tmp_path / "r").exists() and not (tmp_path / "m.onnx").exists()


def test_export_of_several_sizes_refuses_their_weights_file_before_the_model(tmp_path):
    weights = tmp_path / "m.onnx.data"
    weights.write_bytes(b"an earlier export's weights")
    result = _run(["export", "--preset", "deltar-lite", "--out", tmp_path / "m.onnx", "--size",
                   "480x640,720x1280"])
    assert result.exit_code == 1, result.output
    assert _one_error_line(result) == (f"error: --out {weights} exists; pass --overwrite to "
                                       "replace it")
    assert MODEL_BUILT not in result.output
    assert weights.read_bytes() == b"an earlier export's weights"


def test_export_names_layout_from_when_its_file_is_no_calibration(tmp_path):
    picture = tmp_path / "notimage.png"
    picture.write_bytes(b"not a picture and not JSON")
    result = _run(["export", "--preset", "deltar-lite", "--out", tmp_path / "m.onnx",
                   "--layout-from", picture])
    assert result.exit_code == 1, result.output
    line = _one_error_line(result)
    assert line.startswith("error: --layout-from: ") and str(picture) in line
    assert MODEL_BUILT not in result.output and not (tmp_path / "m.onnx").exists()


def test_wall_test_refuses_a_recording_given_twice_and_text_is_no_checkpoint(recording,
                                                                            tmp_path):
    result = _run(["wall-test", recording, recording, "--out", tmp_path / "o", *LITE])
    assert result.exit_code == 2
    assert _one_error_line(result) == (
        f"error: Invalid value for RECORDINGS: {recording} is given more than once; each "
        "recording is one wall distance (see 'deltar wall-test --help')")
    # Existing results are refused before the model runs, not after the frames.
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "wall_test.png").write_bytes(b"earlier")
    result = _run(["wall-test", recording, "--out", tmp_path / "o", *LITE])
    assert result.exit_code == 1 and "--overwrite" in result.output
    assert MODEL_BUILT not in result.output
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["wall_test.png"]
    text = tmp_path / "data.json"
    text.write_text('{"test": []}\n')
    result = _run(["export", "--checkpoint", text, "--out", tmp_path / "m.onnx"])
    assert result.exit_code == 1
    assert _one_error_line(result) == (f"error: {text}: cannot read checkpoint: not a PyTorch "
                                       "file, or a corrupt or truncated one")


def test_a_bag_that_is_not_one_fails_before_the_model(tmp_path):
    (tmp_path / "notes.txt").write_text("not a bag\n")
    result = _run(["replay", "--bag", tmp_path / "notes.txt", "--out-bag", tmp_path / "b",
                   *LITE])
    assert result.exit_code == 1
    _one_error_line(result, f"{tmp_path / 'notes.txt'}: not a readable ROS 2 bag")
    assert MODEL_BUILT not in result.output and not (tmp_path / "b").exists()


def test_export_warns_when_the_layouts_camera_has_another_aspect(tmp_path):
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    calib = tmp_path / "calib.json"
    RigCalibration(intrinsics=CameraIntrinsics(500.0, 500.0, 319.5, 239.5, 640, 480),
                   extrinsics=SensorExtrinsics(), grid=8).save(calib)
    result = _run(["export", "--preset", "deltar-lite", "--out", tmp_path / "m.onnx",
                   "--size", "96x160", "--layout-from", calib])
    assert result.exit_code == 0, result.output
    warning = [line for line in result.stderr.splitlines() if "--layout-from" in line]
    assert warning == [f"warning: --layout-from {calib} is for 480x640 images, whose aspect "
                       "differs from --size 96x160: the zone layout is stretched with the "
                       "images; export at the camera's aspect (e.g. --size 96x128) unless "
                       "stretching is meant"]
