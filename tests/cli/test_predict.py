"""deltar predict / record / replay / wall-test / export through the CLI (lite, small)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from deltar.cli.main import app
from deltar.io.zone_file import save_zone_frame
from deltar.sensor.zone_frame import ZoneFrame

runner = CliRunner()
LITE = ["--preset", "deltar-lite", "--threads", "1"]


def _inputs(folder, stem, rng, zones=64):
    folder.mkdir(parents=True, exist_ok=True)
    image = folder / f"{stem}.png"
    Image.fromarray(rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)).save(image)
    grid = int(np.sqrt(zones))
    frame = ZoneFrame(rng.uniform(0.5, 3, (grid, grid)), np.full((grid, grid), 0.03),
                      np.ones((grid, grid), bool))
    zone_path = save_zone_frame(folder / f"{stem}.json", frame)
    return image, zone_path


def test_predict_single_image_writes_all_outputs_and_never_overwrites(tmp_path, rng):
    image, zones = _inputs(tmp_path / "in", "a", rng)
    out = tmp_path / "out"
    args = ["predict", "--image", str(image), "--zones", str(zones), "--out", str(out), *LITE]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "random" in result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["a_cloud.ply", "a_depth_color.png", "a_depth_m.npy", "a_depth_mm.png",
                     "a_panel.png", "a_sigma_m.npy"]
    depth = np.load(out / "a_depth_m.npy")
    assert depth.shape == (64, 96)
    sigma = np.load(out / "a_sigma_m.npy")
    assert sigma.shape == (64, 96) and sigma.dtype == np.float32 and (sigma > 0).all()
    with Image.open(out / "a_depth_mm.png") as img:
        mm = np.asarray(img).astype(np.int64)
    np.testing.assert_array_equal(mm, np.round(depth.astype(np.float64) * 1000).astype(np.int64))
    again = runner.invoke(app, args)
    assert again.exit_code == 1 and "refusing to overwrite" in again.output


def test_predict_folder_mode_pairs_by_stem(tmp_path, rng):
    for stem in ("f1", "f2"):
        _inputs(tmp_path / "in", stem, rng)
    Image.fromarray(np.zeros((64, 96, 3), np.uint8)).save(tmp_path / "in" / "lonely.png")
    result = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"), "--zones-dir",
                                 str(tmp_path / "in"), "--out", str(tmp_path / "out"),
                                 "--outputs", "npy", *LITE])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["f1_depth_m.npy",
                                                                    "f2_depth_m.npy"]
    assert "1 file without a partner is left out: ['lonely']" in " ".join(result.output.split())
    # WebP images pair like the others; hidden files (temporaries) are no frames.
    Image.fromarray(np.zeros((64, 96, 3), np.uint8)).save(tmp_path / "in" / "lonely.webp")
    (tmp_path / "in" / ".f1_panel.png.x.tmp.png").write_bytes(b"partial")
    result = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"), "--zones-dir",
                                 str(tmp_path / "in"), "--out", str(tmp_path / "out"),
                                 "--outputs", "npy", "--skip-existing", *LITE])
    assert result.exit_code == 1 and "same stem 'lonely'" in " ".join(result.output.split())
    (tmp_path / "in" / "lonely.png").unlink()
    result = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"), "--zones-dir",
                                 str(tmp_path / "in"), "--out", str(tmp_path / "out"),
                                 "--outputs", "npy", "--skip-existing", *LITE])
    assert result.exit_code == 0 and "without a partner" in result.output
    assert ".f1_panel" not in result.output
    # The outputs may not go into an input folder, where they would replace its files.
    before = sorted(p.name for p in (tmp_path / "in").iterdir())
    for out in (tmp_path / "in", tmp_path / "in" / "sub"):
        result = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"),
                                     "--zones-dir", str(tmp_path / "in"), "--out", str(out),
                                     "--overwrite", *LITE])
        assert result.exit_code == 1 and ("is inside the input" in result.output or
                                          "is the input" in result.output), result.output
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == before


@pytest.mark.parametrize("problem, message", [
    ("truncated_image", "cannot decode colour image"),
    ("nan_zone", "NaN"),
    ("negative_zone", "negative"),
    ("zone_count", "wrong zone count"),
])
def test_predict_bad_inputs_name_file_and_problem(tmp_path, rng, problem, message):
    image, zones = _inputs(tmp_path / "in", "a", rng)
    if problem == "truncated_image":
        data = image.read_bytes()
        image.write_bytes(data[: len(data) // 2])
        culprit = image.name
    else:
        content = json.loads(zones.read_text())
        if problem == "nan_zone":
            content["mean_m"][3] = float("nan")
        elif problem == "negative_zone":
            content["mean_m"][3] = -1.0
        else:
            for key in ("mean_m", "sigma_m", "valid"):
                content[key] = content[key][:36]
            content["zone_count"] = 36
        zones.write_text(json.dumps(content))
        culprit = zones.name
    result = runner.invoke(app, ["predict", "--image", str(image), "--zones", str(zones),
                                 "--out", str(tmp_path / "out"), *LITE])
    assert result.exit_code == 1
    text = " ".join(result.output.split())
    assert message in text and culprit in text


def test_predict_refuses_calibration_for_another_resolution(tmp_path, rng):
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    image, zones = _inputs(tmp_path / "in", "a", rng)
    calib = RigCalibration(CameraIntrinsics(500, 500, 319.5, 239.5, 640, 480),
                           SensorExtrinsics()).save(tmp_path / "calib.json")
    result = runner.invoke(app, ["predict", "--image", str(image), "--zones", str(zones),
                                 "--calib", str(calib), "--out", str(tmp_path / "out"), *LITE])
    assert result.exit_code == 1
    assert "calibrated resolution" in " ".join(result.output.split())


def test_predict_folder_refuses_an_image_of_another_size_before_any_frame(tmp_path, rng):
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    for stem in ("a", "b"):
        _inputs(tmp_path / "in", stem, rng)  # 64 x 96
    Image.fromarray(np.zeros((32, 48, 3), np.uint8)).save(tmp_path / "in" / "b.png")
    calib = RigCalibration(CameraIntrinsics(60, 60, 47.5, 31.5, 96, 64),
                           SensorExtrinsics()).save(tmp_path / "calib.json")
    result = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"), "--zones-dir",
                                 str(tmp_path / "in"), "--calib", str(calib), "--out",
                                 str(tmp_path / "out"), "--outputs", "npy", *LITE])
    assert result.exit_code == 1
    text = " ".join(result.output.split())
    assert f"b.png is 32x48 pixels but --calib {calib} is for the calibrated resolution 64x96" \
        in text
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    # With --keep-going that frame fails alone and the others are written.
    kept = runner.invoke(app, ["predict", "--images", str(tmp_path / "in"), "--zones-dir",
                               str(tmp_path / "in"), "--calib", str(calib), "--out",
                               str(tmp_path / "out"), "--outputs", "npy", "--keep-going", *LITE])
    assert kept.exit_code == 1 and "1 of 2 frames failed" in " ".join(kept.output.split())
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a_depth_m.npy"]


def test_record_replay_wall_test_export_end_to_end(tmp_path):
    for distance in ("1.01", "2.05"):
        result = runner.invoke(app, ["record", str(tmp_path / f"wall{distance}"), "--simulate",
                                     f"wall:{distance}:4:64x96"])
        assert result.exit_code == 0, result.output
        assert "recorded 4 images, 2 zone frames" in result.output
    replayed = runner.invoke(app, ["replay", str(tmp_path / "wall1.01"), "--out",
                                   str(tmp_path / "replay"), *LITE])
    assert replayed.exit_code == 0, replayed.output
    assert len(list((tmp_path / "replay").glob("*_depth_m.npy"))) == 2
    walls = runner.invoke(app, ["wall-test", str(tmp_path / "wall1.01"),
                                str(tmp_path / "wall2.05"), "--out", str(tmp_path / "wall"),
                                *LITE])
    assert walls.exit_code == 0, walls.output
    rows = json.loads((tmp_path / "wall" / "wall_test.json").read_text())["results"]
    assert [round(r["distance_m"], 2) for r in rows] == [1.02, 2.06]
    assert all(abs(r["zones_bias_m"] - 0.01) < 1e-4 for r in rows)
    exported = runner.invoke(app, ["export", "--preset", "deltar-lite", "--out",
                                   str(tmp_path / "lite.onnx"), "--size", "64x96",
                                   "--layout-from", str(tmp_path / "wall1.01")])
    assert exported.exit_code == 0, exported.output
    # A random deltar-lite is designed for 480x640: a 64x96 camera runs at that budget.
    assert "camera 64x96, network 448x672" in exported.output
    onnx_replay = runner.invoke(app, ["replay", str(tmp_path / "wall1.01"), "--out",
                                      str(tmp_path / "onnx"), "--onnx",
                                      str(tmp_path / "lite.onnx"), "--threads", "1"])
    assert onnx_replay.exit_code == 0, onnx_replay.output
    assert len(list((tmp_path / "onnx").glob("*_depth_m.npy"))) == 2


def test_predict_flip_runs_and_onnx_refuses_it(tmp_path, rng):
    image, zones = _inputs(tmp_path / "in", "a", rng)
    out = tmp_path / "out"
    result = runner.invoke(app, ["predict", "--image", str(image), "--zones", str(zones),
                                 "--out", str(out), "--outputs", "npy", "--flip", *LITE])
    assert result.exit_code == 0, result.output
    assert np.isfinite(np.load(out / "a_depth_m.npy")).all()
    fake_onnx = tmp_path / "model.onnx"
    fake_onnx.write_bytes(b"not read")
    refused = runner.invoke(app, ["predict", "--image", str(image), "--zones", str(zones),
                                  "--out", str(tmp_path / "o2"), "--onnx", str(fake_onnx),
                                  "--flip"])
    assert refused.exit_code != 0 and "--flip" in refused.output


def test_predict_onnx_default_runs_the_bundled_export_with_the_pytorch_depth(tmp_path, rng):
    image, zones = _inputs(tmp_path / "in", "a", rng)
    for name, extra in (("torch", []), ("onnx", ["--onnx", "default"])):
        result = runner.invoke(app, ["predict", "--image", str(image), "--zones", str(zones),
                                     "--out", str(tmp_path / name), "--outputs", "npy",
                                     "--threads", "1", *extra])
        assert result.exit_code == 0, result.output
    depths = [np.load(tmp_path / name / "a_depth_m.npy") for name in ("torch", "onnx")]
    assert np.abs(depths[0] - depths[1]).max() <= 1e-4


def test_export_int8_needs_a_calibration_folder(tmp_path):
    out = tmp_path / "int8.onnx"
    alone = runner.invoke(app, ["export", "--preset", "deltar-lite", "--out", str(out),
                                "--size", "64x96", "--int8"])
    assert alone.exit_code != 0 and "--calibration" in alone.output
    missing = runner.invoke(app, ["export", "--preset", "deltar-lite", "--out", str(out),
                                  "--size", "64x96", "--int8", "--calibration",
                                  str(tmp_path / "nowhere")])
    assert missing.exit_code != 0 and "calibration RGB-D folder not found" in missing.output
    assert not out.exists()


@pytest.mark.parametrize("folder_mode", [False, True])
def test_a_raw_driver_dump_is_reoriented_as_asked(tmp_path, rng, folder_mode):
    image, _ = _inputs(tmp_path / "in", "a", rng)
    (tmp_path / "in" / "a.json").unlink()
    # ST's order: the driver's first rows read near (1.0 m), its last rows far (2.4 m).
    rows = np.repeat(np.arange(8), 8)
    (tmp_path / "in" / "a.json").write_text(json.dumps({
        "distance_mm": (1000 + 200 * rows).tolist(), "range_sigma_mm": [20] * 64,
        "target_status": [5] * 64}))
    inputs = (["--images", str(tmp_path / "in"), "--zones-dir", str(tmp_path / "in")]
              if folder_mode else ["--image", str(image), "--zones", str(tmp_path / "in" /
                                                                        "a.json")])
    top_minus_bottom = {}
    for orientation in ("none", "flip_ud"):
        out = tmp_path / orientation
        result = runner.invoke(app, ["predict", *inputs, "--out", str(out), "--outputs", "npy",
                                     "--driver-orientation", orientation, "--preset",
                                     "deltar-select", "--threads", "1"])
        assert result.exit_code == 0, result.output
        depth = np.load(out / "a_depth_m.npy")
        top_minus_bottom[orientation] = depth[:16].mean() - depth[-16:].mean()
    assert top_minus_bottom["none"] < -0.5 and top_minus_bottom["flip_ud"] > 0.5
    bad = runner.invoke(app, ["predict", *inputs, "--out", str(tmp_path / "x"),
                              "--driver-orientation", "upside", "--preset", "deltar-select"])
    assert bad.exit_code == 2 and "--driver-orientation" in bad.output
    assert not (tmp_path / "x").exists()
