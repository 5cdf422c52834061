"""load_estimator: one call for every model source the CLI offers."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from deltar.inference import load_estimator, resolve_source
from deltar.inference.estimator import DepthEstimator
from deltar.models import create_model
from deltar.models.checkpoint import load_checkpoint, save_checkpoint
from deltar.sensor.zone_frame import ZoneFrame
from deltar.weights import resolve_checkpoint
from tests.inference.fakes import random_frame, random_image


def test_sources_are_told_apart(tmp_path):
    for name in ("model.onnx", "model.pt"):
        (tmp_path / name).write_bytes(b"")
    assert resolve_source() == ("bundled", "default")
    assert resolve_source("default") == ("bundled", "default")
    assert resolve_source(tmp_path / "model.onnx") == ("onnx", str(tmp_path / "model.onnx"))
    assert resolve_source(tmp_path / "model.pt") == ("checkpoint", str(tmp_path / "model.pt"))
    assert resolve_source("deltar-lite") == ("preset", "deltar-lite")
    assert resolve_source("nyu.pt", kind="official") == ("official", "nyu.pt")


@pytest.mark.parametrize(("source", "kind", "error", "message"), [
    ("nothing-here", None, FileNotFoundError, "'nothing-here' is not a bundled model "
     r"\(default\), an existing file or a preset \(.*deltar-lite"),
    ("run/last.ckpt", None, ValueError, "last.ckpt is a Lightning training checkpoint"),
    ("default", "weights", ValueError, "kind must be one of bundled, checkpoint"),
    (None, "onnx", ValueError, "kind='onnx' needs a source"),
    (5, None, TypeError, "source must be a model name or a file path .*got int 5"),
    (b"model.pt", None, TypeError, "source must be a model name or a file path .*bytes"),
    ("", None, ValueError, "source must name a model or a file, got ''"),
    ("  ", "onnx", ValueError, "source must name a model or a file"),
])
def test_bad_sources_name_the_source(source, kind, error, message):
    with pytest.raises(error, match=message):
        resolve_source(source, kind)


def test_bundled_default_and_its_file_as_a_checkpoint():
    bundled = load_estimator()
    assert isinstance(bundled, DepthEstimator) and "default" in bundled.weights
    from_file = load_estimator(resolve_checkpoint("default"), input_size=(64, 96))
    assert from_file.input_size == (64, 96)
    # No fixed size: the size rule gives a 4:3 camera the weights' design size.
    assert bundled.input_size is None
    assert bundled.network_size_for((480, 640)) == bundled.model.network_config.inputs.design_size


def test_the_bundled_models_onnx_export_by_name_where_pytorch_is_installed(rng):
    from deltar.weights import bundled_onnx

    lean = load_estimator("default", kind="onnx", threads=1)
    assert lean.model is None and lean.onnx_model is not None
    assert lean.weights.endswith("(onnxruntime)")
    assert str(lean.onnx_model.path) == str(bundled_onnx("default"))
    image, frame = random_image(rng, 240, 320), random_frame(rng)
    full = load_estimator("default", threads=1)
    assert full.model is not None
    assert np.abs(lean.predict(image, frame).depth_m - full.predict(image, frame).depth_m
                  ).max() <= 1e-4


def test_the_onnx_export_refuses_another_grid_naming_the_frame_and_remedy(rng):
    lean = load_estimator("default", kind="onnx", threads=1)
    image = random_image(rng, 240, 320)
    with pytest.raises(ValueError, match=r"frames\[0\] has 4x4 zones, but the ONNX model "
                       r".*takes 8x8 zone frames; the PyTorch backend .* runs any grid"):
        lean.predict(image, random_frame(rng, grid=4, invalid=1))
    # The PyTorch path of the same weights takes the 4x4 frame.
    depth = load_estimator("default", threads=1).predict(
        image, random_frame(rng, grid=4, invalid=1)).depth_m
    assert depth.shape == (240, 320) and np.isfinite(depth).all()


def test_a_size_the_onnx_export_lacks_is_refused_listing_its_sizes():
    with pytest.raises(ValueError, match=r"input_size \(320, 320\) is not one the ONNX model "
                       r".*deltar_select_default.onnx was exported at: \(256, 320\), .*"
                       r"the PyTorch backend \(without --onnx\) runs any size"):
        load_estimator("default", kind="onnx", input_size=(320, 320))
    assert load_estimator("default", kind="onnx", input_size=(288, 288)).input_size == (288, 288)


def test_a_file_named_like_the_bundled_model_wins_as_onnx(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "default").write_bytes(b"not an ONNX file")
    with pytest.raises(ValueError, match="default"):
        load_estimator("default", kind="onnx")


def test_the_bundled_name_as_onnx_without_its_export_names_it(monkeypatch):
    import deltar.inference.loading as loading

    monkeypatch.setattr(loading, "bundled_onnx", lambda name: None)
    with pytest.raises(FileNotFoundError, match="no ONNX export of the bundled model 'default'"):
        load_estimator("default", kind="onnx")


def test_checkpoint_predicts_like_the_constructor(tmp_path):
    # A model of its own: estimators fold the batch norms of the model they are given.
    torch.manual_seed(0)
    path = tmp_path / "lite.pt"
    save_checkpoint(path, create_model("deltar-lite", design_size=(64, 96)), "deltar-lite")
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(1, 3, (8, 8)), np.full((8, 8), 0.03), np.ones((8, 8), bool))
    loaded = load_estimator(path, kind="checkpoint", flip_average=True)
    direct = DepthEstimator(load_checkpoint(path)[0], flip_average=True)
    np.testing.assert_array_equal(loaded.predict(image, frame).depth_m,
                                  direct.predict(image, frame).depth_m)
    assert loaded.flip_average


def test_preset_warns_and_threads_are_set():
    before = torch.get_num_threads()
    try:
        with pytest.warns(UserWarning, match="random, untrained weights"):
            estimator = load_estimator("deltar-lite", threads=1, input_size=(64, 64))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    assert estimator.weights == "deltar-lite (random weights)"
    assert estimator.input_size == (64, 64)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"precision": "float8"}, "precision must be one of float32, float16, bfloat16"),
    ({"input_size": (60, 64)}, r"input_size must be positive multiples of 32, got \(60, 64\)"),
    ({"threads": 0}, "threads must be between 1 and"),
    ({"device": "gpu"}, "device: unknown device 'gpu'; use cpu, cuda, cuda:N or mps"),
])
def test_bad_arguments_name_the_argument(kwargs, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with pytest.raises(ValueError, match=message):
            load_estimator("deltar-lite", **kwargs)


def test_onnx_refuses_flip_and_official_needs_the_file(tmp_path):
    with pytest.raises(ValueError, match="flip_average needs a PyTorch model"):
        load_estimator(tmp_path / "m.onnx", kind="onnx", flip_average=True)
    with pytest.raises(FileNotFoundError, match="official weights not found"):
        load_estimator(tmp_path / "nyu.pt", kind="official")


def test_checkpoint_round_trip(tmp_path, rng):
    torch.manual_seed(1)
    config = {"design_size": (64, 96), "n_bins": 32}
    model = create_model("deltar-lite", **config).eval()
    path = save_checkpoint(tmp_path / "model.pt", model, "deltar-lite")
    with pytest.raises(FileExistsError):
        save_checkpoint(path, model, "deltar-lite")
    restored, preset, saved_config = load_checkpoint(path)
    assert not restored.training
    assert preset == "deltar-lite" and saved_config == model.config()
    assert saved_config["input"]["design_size"] == (64, 96)
    assert saved_config["head"]["n_bins"] == 32
    image, frame = random_image(rng, 64, 96), random_frame(rng)
    a = DepthEstimator(model, weights="a").predict(image, frame)
    b = load_estimator(path).predict(image, frame)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)


def test_bad_checkpoints_raise(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_estimator(tmp_path / "missing.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"corrupt\.pt"):
        load_estimator(corrupt)
    plain = tmp_path / "plain.pt"
    torch.save({"weights": torch.zeros(1)}, plain)
    with pytest.raises(ValueError, match="not a deltar checkpoint"):
        load_estimator(plain)
    with pytest.raises(FileNotFoundError):
        load_estimator(tmp_path / "nyu.pt", kind="official")


def test_official_weights_load(tmp_path, parity_fixture, rng):
    """The fixture's state dict (release names, float16) saved as a file loads cleanly."""
    fixture = parity_fixture
    weights = tmp_path / "nyu.pt"
    torch.save({k: v.float() for k, v in fixture["state_dict"].items()}, weights)
    # Unfolded, so the stem's weights are the file's own.
    estimator = load_estimator(weights, kind="official", fold_batch_norms=False)
    assert "deltar-official" in estimator.weights
    stem = estimator.model.image_encoder.backbone.conv_stem.weight
    np.testing.assert_array_equal(stem.detach().numpy(),
                                  fixture["state_dict"]["img_encoder.conv0.0.weight"].float())
    pred = estimator.predict(random_image(rng, 64, 96), random_frame(rng))
    assert pred.depth_m.shape == (64, 96) and np.isfinite(pred.depth_m).all()
    broken = tmp_path / "broken.pt"
    torch.save({"img_encoder.conv0.0.weight": torch.zeros(1)}, broken)
    with pytest.raises(ValueError, match=r"broken\.pt"):
        load_estimator(broken, kind="official")


def test_one_estimator_shared_by_threads_gives_each_call_its_own_result(rng):
    from concurrent.futures import ThreadPoolExecutor

    estimator = load_estimator("default", kind="onnx", threads=1)
    inputs = [(random_image(rng, *size), random_frame(rng))
              for size in [(240, 320), (120, 160), (240, 320), (180, 320), (120, 160), (240, 240)]]
    alone = [estimator.predict(image, frame) for image, frame in inputs]
    with ThreadPoolExecutor(max_workers=3) as pool:
        together = list(pool.map(lambda pair: estimator.predict(*pair), inputs * 2))
    for index, result in enumerate(together):
        reference = alone[index % len(inputs)]
        assert np.abs(result.depth_m - reference.depth_m).max() <= 1e-5
        assert np.abs(result.uncertainty_m - reference.uncertainty_m).max() <= 1e-5


def test_a_gpu_the_machine_lacks_is_named_before_any_weights_load(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"^device 'cuda:0': no CUDA GPU is available on "
                       r"this machine \(use device='cpu'\)$"):
        load_estimator("default", device="cuda:0")
    assert load_estimator("default", device=torch.device("cpu")).device.type == "cpu"


def test_an_onnx_session_takes_no_more_threads_than_the_machine_can_use():
    from deltar.inference.onnx_runtime import OnnxDepthModel
    from deltar.weights import bundled_onnx

    with pytest.raises(ValueError, match=r"^num_threads must be between 1 and \d+ "):
        OnnxDepthModel(bundled_onnx("default"), num_threads=10**6)
