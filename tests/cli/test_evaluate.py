"""``deltar evaluate`` on tiny ZJU-L5-layout sets written to tmp_path: baselines and
learned models (``--checkpoint``, ``--official``, ``--flip``, ``--network``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.data.zju_l5 import write_zju_l5
from deltar.evaluation.baselines import BASELINES
from deltar.evaluation.metrics import METRIC_KEYS
from deltar.models import create_model
from deltar.models.checkpoint import save_checkpoint
from tests.evaluation.samples import make_sample
from tests.evaluation.test_model_methods import untrained_prior_checkpoint

# A wide terminal keeps rich from wrapping the table title.
runner = CliRunner(env={"COLUMNS": "200"})


@pytest.fixture
def data_json(tmp_path: Path, tiny_samples) -> Path:
    return write_zju_l5(tmp_path / "set", tiny_samples)


def test_all_methods_table_and_json(data_json: Path, tmp_path: Path) -> None:
    out = tmp_path / "out" / "metrics.json"
    result = runner.invoke(app, ["evaluate", "--method", "all", "--data", str(data_json),
                                 "--json", str(out)])
    assert result.exit_code == 0, result.output
    for name in BASELINES:
        assert name in result.output
    assert "RMSE" in result.output and "3 frames" in result.output
    metrics = json.loads(out.read_text())
    assert list(metrics) == list(BASELINES)
    for values in metrics.values():
        assert set(values) == set(METRIC_KEYS)
    # The test frames are constant per zone, so painting zone means is exact.
    assert metrics["nearest"]["d1"] == 1.0
    assert metrics["nearest"]["rmse"] == pytest.approx(0.0, abs=1e-6)
    assert metrics["median"]["rmse"] > 0.1


def test_limit_and_visualisations(data_json: Path, tmp_path: Path) -> None:
    vis = tmp_path / "vis"
    result = runner.invoke(app, ["evaluate", "-m", "bilinear,nearest", "--data",
                                 str(data_json), "--limit", "2", "--save-vis", str(vis)])
    assert result.exit_code == 0, result.output
    assert "2 frames" in result.output
    pngs = sorted(p.relative_to(vis).as_posix() for p in vis.rglob("*.png"))
    assert pngs == ["bilinear/scene_a__0001.png", "bilinear/scene_a__0002.png",
                    "nearest/scene_a__0001.png", "nearest/scene_a__0002.png"]
    assert (vis / pngs[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(vis.rglob("*.tmp*"))


def test_frames_without_ground_truth_are_skipped(tmp_path: Path) -> None:
    data = write_zju_l5(tmp_path / "set", [make_sample("a", 0),
                                          make_sample("b", 1, empty_gt=True)])
    with pytest.warns(RuntimeWarning, match="skipping frame 'b'"):
        result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data)])
    assert result.exit_code == 0, result.output
    assert "1 frames" in result.output and "1 without valid ground truth" in result.output


def test_keep_going_scores_the_other_frames_and_exits_1(tmp_path: Path) -> None:
    import dataclasses

    far = make_sample("far", 1)
    far = dataclasses.replace(far, zone_mean_sigma=far.zone_mean_sigma.copy())
    far.zone_mean_sigma[3, 0] = 4.5  # beyond the L5's 4 m range: not a real reading
    data = write_zju_l5(tmp_path / "set", [make_sample("a", 0), far, make_sample("c", 2)])
    out = tmp_path / "metrics.json"
    args = ["evaluate", "-m", "nearest", "--data", str(data), "--json", str(out)]
    stopped = runner.invoke(app, args)
    assert stopped.exit_code == 1 and "frame 'far'" in stopped.output and not out.exists()
    with pytest.warns(RuntimeWarning, match="leaving out frame 'far'"):
        result = runner.invoke(app, [*args, "--keep-going"])
    assert result.exit_code == 1, result.output
    assert "2 frames (1 left out, --keep-going)" in result.output
    assert "1 of 3 frames left out (first: frame 'far'" in result.output
    assert json.loads(out.read_text())["nearest"]["d1"] == 1.0  # the two good frames


def test_unknown_method_lists_valid_names(data_json: Path) -> None:
    result = runner.invoke(app, ["evaluate", "-m", "nearest,magic", "--data", str(data_json)])
    assert result.exit_code == 2
    assert "magic" in result.output and "bilinear" in result.output


def test_missing_data_json_names_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "data.json"
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(missing)])
    assert result.exit_code == 2
    assert "not found" in result.output and "nowhere" in result.output


def test_refuses_to_overwrite_the_input(data_json: Path) -> None:
    before = data_json.read_text()
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data_json),
                                 "--json", str(data_json), "--overwrite"])
    assert result.exit_code == 1
    assert f"--json {data_json} is the input {data_json}" in result.stderr
    assert data_json.read_text() == before


def test_corrupt_frame_file_is_named(data_json: Path) -> None:
    frame = data_json.parent / "scene_a" / "0002.h5"
    frame.write_bytes(b"not an hdf5 file")
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data_json)])
    assert result.exit_code == 1
    assert "0002.h5" in result.output


def test_thdr3k_layout_is_detected_rotated_and_masked(tmp_path: Path) -> None:
    """A THDR3K file list evaluates like ZJU-L5: the nearest baseline is exact only if
    the ToF grid is rotated to the image and the no-target zone is masked."""
    from tests.data.thdr3k_set import write_set

    list_path = write_set(tmp_path / "thdr", train=1, test=2)
    out = tmp_path / "m.json"
    result = runner.invoke(app, ["evaluate", "-m", "nearest,median", "--data", str(list_path),
                                 "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "2 frames" in result.output
    metrics = json.loads(out.read_text())
    assert metrics["nearest"]["d1"] == 1.0
    assert metrics["nearest"]["rmse"] == pytest.approx(0.0, abs=1e-5)
    assert metrics["median"]["rmse"] > 0.3
    refused = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(list_path),
                                  "--json", str(list_path)])
    assert refused.exit_code != 0
    assert f"--json {list_path} is the input {list_path}" in refused.output


def _evaluate_checkpoint(tmp_path: Path, data: Path, checkpoint: Path, *options: str) -> dict:
    """``deltar evaluate --checkpoint CHECKPOINT OPTIONS``; the metrics it wrote."""
    out = tmp_path / "metrics.json"
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(checkpoint), *options,
                                 "--data", str(data), "--json", str(out)])
    assert result.exit_code == 0, result.output
    return json.loads(out.read_text())


def test_checkpoint_is_evaluated_beside_the_baselines(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    checkpoint = untrained_prior_checkpoint(tmp_path / "prior.pt")
    out = tmp_path / "metrics.json"
    result = runner.invoke(app, ["evaluate", "-m", "median,nearest", "--checkpoint",
                                 str(checkpoint), "--data", str(data), "--json", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    key = f"model:{checkpoint}"
    assert list(metrics) == ["median", "nearest", key]
    # Zone-following depth: far better than one constant, not as exact as painting zones.
    assert metrics[key]["rmse"] < 0.6 * metrics["median"]["rmse"]
    assert metrics[key]["d1"] > metrics["median"]["d1"]


def test_missing_checkpoint_and_official_files_are_named(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    missing = tmp_path / "nope.pt"
    for option in ("--checkpoint", "--official"):
        result = runner.invoke(app, ["evaluate", option, str(missing), "--data", str(data)])
        # Checked as an option value before any work (docs/errors.md): a usage error.
        assert result.exit_code == 2, result.output
        assert f"error: Invalid value for {option}: " in result.output
        assert "nope.pt" in result.output


def test_a_methods_unreadable_model_is_named_as_method(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    result = runner.invoke(app, ["evaluate", "--method", f"nearest,onnx:{bad}",
                                 "--data", str(data)])
    assert result.exit_code == 2, result.output
    assert "error: Invalid value for --method: " in result.output and "bad.onnx" in result.output


@pytest.mark.parametrize(("method", "files"), [
    ("onnx:{}/m.onnx", ["m.onnx", "m.onnx.data"]),
    ("onnx:{}/m.onnx+network", ["m.onnx", "m.onnx.data"]),
    ("model:{}/c.pt", ["c.pt"]),
    ("official:{}/o.pt+flip", ["o.pt"]),
])
def test_no_output_replaces_a_methods_model_file(tmp_path: Path, tiny_samples, method,
                                                files) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    for name in files:
        (tmp_path / name).write_bytes(b"weights")
    for name in files:
        result = runner.invoke(app, ["evaluate", "--method", method.format(tmp_path),
                                     "--data", str(data), "--json", str(tmp_path / name),
                                     "--overwrite"])
        assert result.exit_code == 1, result.output
        assert f"is the input {tmp_path / name}" in result.output
        assert (tmp_path / name).read_bytes() == b"weights"


def test_a_missing_frame_file_is_found_before_any_model(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    frame = data.parent / "scene_b" / "0001.h5"
    frame.unlink()
    # The missing checkpoint would fail when the methods are built: the frame is named first.
    result = runner.invoke(app, ["evaluate", "--method", "nearest,model:missing.pt",
                                 "--data", str(data)])
    assert result.exit_code == 2, result.output
    assert f"frame file not found: {frame}" in result.output
    assert "missing.pt" not in result.output
    # Frames past --limit are not read, so they need not exist.
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data),
                                 "--limit", "2"])
    assert result.exit_code == 0, result.output


def test_no_method_at_all_is_an_error(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    result = runner.invoke(app, ["evaluate", "--data", str(data)])
    assert result.exit_code == 2, result.output
    assert "error:" in result.output and "--checkpoint" in result.output


def test_flip_adds_a_flip_averaged_entry(tmp_path: Path, tiny_samples) -> None:
    data = write_zju_l5(tmp_path / "set", tiny_samples)
    checkpoint = untrained_prior_checkpoint(tmp_path / "prior.pt")
    metrics = _evaluate_checkpoint(tmp_path, data, checkpoint, "--flip")
    key = f"model:{checkpoint}"
    assert list(metrics) == [key, f"{key}+flip"]
    # The untrained prior is mirror-symmetric in the zones: flipping must not change it.
    for name in ("rmse", "rel", "d1"):
        assert abs(metrics[f"{key}+flip"][name] - metrics[key][name]) < 1e-4


def test_network_adds_the_network_alone_for_a_plane_select_model(tmp_path: Path,
                                                                 tiny_samples) -> None:
    """A plane-select checkpoint is scored with the estimator's blend; ``--network`` adds
    its depth without it, which differs (the untrained network is unsure)."""
    from deltar.evaluation.model_methods import checkpoint_predictor

    data = write_zju_l5(tmp_path / "set", tiny_samples)
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(32, 64))
    checkpoint = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    metrics = _evaluate_checkpoint(tmp_path, data, checkpoint, "--network")
    key = f"model:{checkpoint}"
    assert list(metrics) == [key, f"{key}+network"]
    assert metrics[key]["rmse"] != metrics[f"{key}+network"]["rmse"]
    assert checkpoint_predictor(str(checkpoint)).estimator.blend is not None
    assert checkpoint_predictor(f"{checkpoint}+network").estimator.blend is None


def test_a_missing_thdr3k_file_is_found_before_any_model(tmp_path: Path) -> None:
    from tests.data.thdr3k_set import write_set

    list_path = write_set(tmp_path / "thdr", train=1, test=2)
    last = json.loads(list_path.read_text())["test"][-1]["filename"]
    depth = list_path.parent / f"{last}_depth.png"
    depth.unlink()
    result = runner.invoke(app, ["evaluate", "--method", "nearest,model:missing.pt",
                                 "--data", str(list_path)])
    assert result.exit_code == 2, result.output
    assert f"frame file not found: {depth}" in result.output


def test_a_json_path_no_file_can_be_made_in_fails_before_evaluating(
        data_json: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import deltar.evaluation.runner as runner_module

    def never(*args, **kwargs):
        raise AssertionError("evaluated before the --json check")

    monkeypatch.setattr(runner_module, "evaluate_methods", never)
    # /proc passes the permission bits for root, yet no file can be created in it.
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data_json),
                                 "--json", "/proc/x.json"])
    assert result.exit_code == 1, result.output
    assert "--json /proc/x.json: cannot write in /proc" in result.output
    assert ".tmp" not in result.output
    # A folder that can be written in keeps no trace of the check.
    monkeypatch.undo()
    out = tmp_path / "new" / "metrics.json"
    result = runner.invoke(app, ["evaluate", "-m", "nearest", "--data", str(data_json),
                                 "--json", str(out), "--limit", "1"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new", "set"]
    assert list((tmp_path / "new").iterdir()) == [out]


@pytest.mark.parametrize(("calibration", "message"), [
    ("640", "is 48x64 pixels but --calib {calib} is for the calibrated resolution 480x640"),
    ("grid4", "--calib {calib} is for a 4x4 zone grid, the recording {rec} has 8x8"),
])
def test_wall_test_refuses_a_calibration_of_another_rig_before_the_model(
        tmp_path: Path, calibration, message) -> None:
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    rec = tmp_path / "rec"
    assert runner.invoke(app, ["record", str(rec), "--simulate", "wall:1.5:2:48x64"]
                         ).exit_code == 0
    camera = CameraIntrinsics(500, 500, 319.5, 239.5, 640, 480) if calibration == "640" \
        else CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    calib = RigCalibration(camera, SensorExtrinsics(), grid=4 if calibration == "grid4" else 8
                           ).save(tmp_path / "calib.json")
    result = runner.invoke(app, ["wall-test", str(rec), "--out", str(tmp_path / "o"), "--calib",
                                 str(calib), "--preset", "deltar-lite", "--threads", "1"])
    assert result.exit_code == 1
    assert message.format(calib=calib, rec=rec) in " ".join(result.output.split())
    # Before the model is built (it warns of its random weights), as replay does.
    assert "random, untrained weights" not in result.output
    assert not (tmp_path / "o").exists()
