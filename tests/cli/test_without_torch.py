"""The base install: the command line without PyTorch (nor matplotlib).

Each command runs in a subprocess in which importing torch, timm, lightning, einops or
matplotlib raises ``ModuleNotFoundError`` (a meta-path finder installed before
``deltar`` is imported), as in a virtualenv made by ``pip install deltar`` (no extras).
The depth it writes is compared with the PyTorch path in this process.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from deltar.extras import EXTRA_OF_MODULE

#: The modules the base install does not have.
BLOCKED = ("torch", "timm", "lightning", "einops", "pytorch_lightning", "lightning_fabric",
           "torchvision", "torchmetrics", "matplotlib")

RUNNER = textwrap.dedent(f"""
    import sys

    BLOCKED = {BLOCKED!r}


    class NoTorch:
        # A meta-path finder that refuses the PyTorch stack, as if it were not installed.
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None


    sys.meta_path.insert(0, NoTorch())
    from deltar.cli.main import main

    try:
        main(sys.argv[1:])
    finally:
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not loaded, loaded
""")


def run_without_torch(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """``deltar ARGS`` in a subprocess where the PyTorch stack cannot be imported."""
    runner = tmp_path / "no_torch_runner.py"
    if not runner.exists():
        runner.write_text(RUNNER)
    return subprocess.run([sys.executable, str(runner), *args], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)


def test_the_blocker_blocks(tmp_path):
    result = subprocess.run([sys.executable, "-c", RUNNER.replace(
        "from deltar.cli.main import main", "import torch")], capture_output=True, text=True)
    assert result.returncode != 0 and "No module named 'torch'" in result.stderr


@pytest.fixture(scope="module")
def demo_without_torch(tmp_path_factory) -> Path:
    """``deltar demo`` (one small scene) then ``deltar predict`` on its sample, no torch."""
    tmp_path = tmp_path_factory.mktemp("no_torch")
    demo = run_without_torch(tmp_path, "demo", str(tmp_path / "demo"), "--frames", "1",
                             "--size", "120x160")
    assert demo.returncode == 0, demo.stderr
    sample = tmp_path / "demo" / "sample"
    predict = run_without_torch(tmp_path, "predict", "--image", str(sample / "image.png"),
                                "--zones", str(sample / "zones.json"), "--calib",
                                str(sample / "calib.json"), "--out", str(tmp_path / "pred"),
                                "--outputs", "npy")
    assert predict.returncode == 0, predict.stderr
    network = run_without_torch(tmp_path, "predict", "--image", str(sample / "image.png"),
                                "--zones", str(sample / "zones.json"), "--calib",
                                str(sample / "calib.json"), "--out", str(tmp_path / "net"),
                                "--outputs", "npy", "--network-only")
    assert network.returncode == 0, network.stderr
    return tmp_path


def test_demo_and_predict_without_torch_match_the_pytorch_path(demo_without_torch):
    import json

    from deltar.calibration.rig import RigCalibration
    from deltar.data.rgbd_files import read_color
    from deltar.inference.loading import load_estimator
    from deltar.io.zone_file import load_zone_frame

    metrics = json.loads((demo_without_torch / "demo" / "metrics.json").read_text())
    assert "model:default" in metrics and 0 < metrics["model:default"]["rmse"] < 5
    sample = demo_without_torch / "demo" / "sample"
    inputs = (read_color(sample / "image.png"), load_zone_frame(sample / "zones.json"),
              RigCalibration.load(sample / "calib.json"))
    # The network's depth (--network-only): the same within 1e-4 m.
    estimator = load_estimator("default", blend=None)  # PyTorch is here
    assert estimator.model is not None
    lean = np.load(demo_without_torch / "net" / "image_depth_m.npy")
    reference = estimator.predict(*inputs).depth_m
    assert lean.shape == reference.shape == (120, 160)
    assert np.abs(lean - reference).max() <= 1e-4
    # With the confidence blend: the same within 1e-4 m on every pixel too.
    lean = np.load(demo_without_torch / "pred" / "image_depth_m.npy")
    assert np.abs(lean - load_estimator("default").predict(*inputs).depth_m).max() <= 1e-4


def test_record_replay_bags_and_viewer_without_torch(tmp_path):
    pytest.importorskip("rosbags")
    pytest.importorskip("rerun")
    record = run_without_torch(tmp_path, "record", "rec", "--bag", "--simulate",
                               "procedural:2")
    assert record.returncode == 0, record.stderr
    replay = run_without_torch(tmp_path, "replay", "--bag", "rec", "--out-bag", "depth",
                               "--rerun-save", "view.rrd")
    assert replay.returncode == 0, replay.stderr
    assert "wrote 1 frames of depth to the bag depth" in replay.stdout
    assert (tmp_path / "view.rrd").stat().st_size > 0


def _one_error_line(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 1, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "Traceback" not in result.stderr
    return lines[0]


def test_torch_only_commands_name_the_extra(tmp_path, demo_without_torch):
    sample = demo_without_torch / "demo" / "sample"
    inputs = ["--image", str(sample / "image.png"), "--zones", str(sample / "zones.json")]
    line = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "a",
                                             "--official", str(sample / "calib.json")))
    assert line.endswith('pip install "deltar[torch]"') and "torch" in line
    line = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "b",
                                             "--flip"))
    assert "flip averaging" in line and line.endswith('pip install "deltar[torch]"')
    line = _one_error_line(run_without_torch(tmp_path, "train", "--config", "x.yaml"))
    assert line.endswith('pip install "deltar[train]"')
    line = _one_error_line(run_without_torch(tmp_path, "export", "--out", "x.onnx"))
    assert line.endswith('pip install "deltar[export]"')
    # A file that is not there is said first: the extra would not help.
    line = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "c",
                                             "--checkpoint", "missing.pt", "--threads", "1"))
    assert "'missing.pt' is neither a bundled model" in line and "torch" not in line
    line = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "d",
                                             "--official", "missing.pt"))
    assert "not found: missing.pt" in line and "torch" not in line
    (tmp_path / "weights").mkdir()
    line = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "e",
                                             "--checkpoint", "weights"))
    assert "folder" in line and "torch" not in line
    # simulate runs without PyTorch, but its degraded readings and histograms need it.
    line = _one_error_line(run_without_torch(tmp_path, "simulate", "procedural:1", "sim1",
                                             "--drop-fraction", "0.2"))
    assert "--drop-fraction" in line and line.endswith('pip install "deltar[torch]"')
    line = _one_error_line(run_without_torch(tmp_path, "simulate", "procedural:1", "sim2",
                                             "--cnh"))
    assert "--cnh" in line and line.endswith('pip install "deltar[torch]"')
    assert not (tmp_path / "sim1").exists() and not (tmp_path / "sim2").exists()
    assert EXTRA_OF_MODULE["torch"] == "torch"


def test_devices_and_zone_grids_without_torch_say_what_is_wrong(tmp_path, demo_without_torch):
    sample = demo_without_torch / "demo" / "sample"
    inputs = ["--image", str(sample / "image.png"), "--zones", str(sample / "zones.json")]
    typo = run_without_torch(tmp_path, "predict", *inputs, "--out", "a", "--device", "bogus")
    assert typo.returncode == 2 and "unknown device 'bogus'" in typo.stderr
    assert "pip install" not in typo.stderr
    gpu = run_without_torch(tmp_path, "predict", *inputs, "--out", "b", "--device", "cuda")
    assert gpu.returncode == 2 and 'pip install "deltar[torch]"' in " ".join(gpu.stderr.split())
    preset = _one_error_line(run_without_torch(tmp_path, "predict", *inputs, "--out", "e",
                                               "--preset", "delta-lite"))
    assert "unknown model preset 'delta-lite'; known presets: deltar-lite" in preset
    assert "pip install" not in preset
    size = run_without_torch(tmp_path, "predict", *inputs, "--out", "d", "--size", "320x320")
    text = " ".join(size.stderr.split())
    assert size.returncode == 2 and "Invalid value for --size: (320, 320) is not one" in text
    assert 'pip install "deltar[torch]"' in text
    # The bundled ONNX export takes 8x8 zones: a 4x4 recording is refused by name.
    record = run_without_torch(tmp_path, "record", "r4", "--simulate", "wall:1.2:2:48x64",
                               "--grid", "4")
    assert record.returncode == 0, record.stderr
    line = _one_error_line(run_without_torch(tmp_path, "replay", "r4", "--out", "c"))
    assert "the recording r4 has 4x4 zones, but the ONNX model" in line
    assert 'pip install "deltar[torch]"' in line
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_evaluate_a_histogram_set_without_torch(tmp_path):
    # THDR3K's zones carry CNH histograms: their sigma is read in numpy, not PyTorch.
    from tests.data.thdr3k_set import write_set

    split = write_set(tmp_path / "thdr", train=1, test=2)
    result = run_without_torch(tmp_path, "evaluate", "--method", "nearest", "--data",
                               str(split))
    assert result.returncode == 0, result.stderr
    assert "nearest" in result.stdout and "2 frames" in result.stdout


def test_calibration_plots_without_matplotlib_are_refused_before_the_work(tmp_path):
    # Before: the calibration ran and was written, then the pictures failed (exit 1).
    from scipy.spatial.transform import Rotation

    from deltar.calibration.rig import RigCalibration
    from deltar.calibration.synthetic import synthetic_rig_frames, write_synthetic_recording
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    camera = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    true = SensorExtrinsics(Rotation.from_euler("zyx", [92.0, -1.0, 1.5], degrees=True)
                            .as_matrix(), np.array([0.03, 0.01, -0.01]))
    frames = synthetic_rig_frames(true, camera, frames_per_plane=2, mean_noise_m=0.01, seed=5)
    write_synthetic_recording(tmp_path / "rec", frames, camera)
    RigCalibration(camera, true).save(tmp_path / "calib.json")
    line = _one_error_line(run_without_torch(
        tmp_path, "calibrate", "rec", "--out", "new.json", "--nominal-roll-deg", "90",
        "--plot", "plots"))
    assert "--plot" in line and line.endswith('pip install "deltar[plots]"')
    assert not (tmp_path / "new.json").exists()
    result = run_without_torch(tmp_path, "check-calibration", "rec", "--calib", "calib.json",
                               "--plot", "check.png")
    line = _one_error_line(result)
    assert "--plot" in line and line.endswith('pip install "deltar[plots]"')
    assert result.stdout == ""  # nothing scored


def test_map_with_the_map_extra_alone(tmp_path):
    # The 'map' extra is Open3D: the TSDF update must not need PyTorch either.
    from deltar.mapping.tsdf import require_open3d

    try:
        require_open3d()
    except ImportError:
        pytest.skip("the 'map' extra is not installed")
    from tests.mapping.conftest import write_wall_recording

    write_wall_recording(tmp_path / "rec", frames=3)
    result = run_without_torch(tmp_path, "map", "rec", "--out", "map", "--method", "recorded",
                               "--voxel", "0.04", "--truncation", "3")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "map" / "mesh.ply").stat().st_size > 0
