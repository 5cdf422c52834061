"""The bundled model's ONNX export, which the base install (no PyTorch) runs.

It must stay what exporting the bundled checkpoint gives now, and give the PyTorch
path's depth, so that the two files cannot drift apart.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from deltar.data.procedural import render_scene
from deltar.data.sources import open_source
from deltar.inference.loading import load_estimator
from deltar.models.checkpoint import load_checkpoint
from deltar.sensor.geometry import zone_rects
from deltar.sensor.simulate_frame import simulate_zone_frame
from deltar.weights import (
    BUNDLED_ONNX_EXPORT_SIZE,
    BUNDLED_ONNX_EXPORT_SIZES,
    bundled_onnx,
    resolve_checkpoint,
)


@pytest.fixture(scope="module")
def real_frame(request):
    """A real RGB-D frame of the shared data with zones simulated from its depth."""
    from tests.conftest import SHARED_DATA

    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}")
    frame = open_source(str(SHARED_DATA / "7scenes_redkitchen"))[40]
    zones = simulate_zone_frame(frame.depth_m, zone_rects(frame.intrinsics, 8))
    return frame.image, zones


def test_shipped_onnx_equals_a_fresh_export_of_the_shipped_checkpoint(tmp_path, real_frame):
    from deltar.export.onnx import export_input_size, export_onnx

    shipped = bundled_onnx("default")
    assert shipped is not None
    # One file per exported size, the weights in one shared file: small all together.
    files = list(shipped.parent.glob("deltar_select_default.*onnx*"))
    assert len(files) == len(BUNDLED_ONNX_EXPORT_SIZES) + 1
    assert sum(f.stat().st_size for f in files) < 8 * 1024 * 1024
    model, _, config = load_checkpoint(resolve_checkpoint("default"))
    fresh = export_onnx(model, tmp_path / "fresh.onnx", *BUNDLED_ONNX_EXPORT_SIZE)
    image, zones = real_frame
    ours, theirs = (load_estimator(path, threads=2) for path in (shipped, fresh))
    # The config travels as metadata: the blend, the sigma calibration, the design size.
    assert ours.onnx_model.contract == theirs.onnx_model.contract
    stored = json.loads(json.dumps(config, default=list))
    assert json.loads(theirs.onnx_model.metadata["deltar_config"]) == stored
    assert json.loads(ours.onnx_model.metadata["deltar_config"]) == stored
    assert ours.onnx_model.input_size == (256, 320)  # every 4:3 camera's network size
    assert ours.onnx_model.input_sizes == tuple(
        export_input_size(model, *size) for size in BUNDLED_ONNX_EXPORT_SIZES)
    a, b = ours.predict(image, zones), theirs.predict(image, zones)
    assert np.abs(a.depth_m - b.depth_m).max() <= 1e-4
    assert np.abs(a.uncertainty_m - b.uncertainty_m).max() <= 1e-4


def test_onnx_path_gives_the_pytorch_depth_on_a_real_frame(real_frame):
    image, zones = real_frame
    lean = load_estimator(bundled_onnx("default"), threads=2)
    full = load_estimator("default", threads=2)
    assert full.model is not None and lean.onnx_model is not None
    assert lean.blend == full.blend and lean.uncertainty == full.uncertainty
    assert lean.no_target_min_neighbour_m == full.no_target_min_neighbour_m is not None
    assert lean.zone_outliers == full.zone_outliers
    assert lean.no_target_depth_m == full.no_target_depth_m is not None
    a, b = lean.predict(image, zones), full.predict(image, zones)
    assert a.network_size == b.network_size == (256, 320)
    assert np.abs(a.network_depth_m - b.network_depth_m).max() <= 1e-4
    assert np.abs(a.depth_m - b.depth_m).max() <= 1e-4


@pytest.mark.parametrize(("torch_installed", "remedy"), [
    (False, r"pip install \"deltar\[torch\]\" for that"),
    (True, r"use the PyTorch backend \(without --onnx\) for that")])
def test_an_aspect_not_exported_is_stretched_with_a_warning_naming_the_remedy(
        monkeypatch, torch_installed, remedy):
    import deltar.inference.onnx_runtime as onnx_runtime

    monkeypatch.setattr(onnx_runtime, "torch_available", lambda: torch_installed)
    # 2:1: the size rule gives 192x416, not exported; the nearest aspect exported is 16:9.
    frame = render_scene(3, 240, 480)
    zones = simulate_zone_frame(frame.depth_m, zone_rects(frame.intrinsics, 8))
    lean = load_estimator(bundled_onnx("default"), threads=2)
    with pytest.warns(UserWarning, match=r"stretched .* 224x384 .*192x416; " + remedy):
        result = lean.predict(frame.image, zones)
    assert result.network_size == (224, 384) and result.depth_m.shape == (240, 480)
    # The caller's filters decide: a frame predicted under "ignore" does not use it up.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lean.predict(frame.image, zones)
    with pytest.warns(UserWarning, match=r"stretched .* 224x384"):
        lean.predict(frame.image, zones)


@pytest.fixture(scope="module")
def both_backends():
    """The bundled model through onnxruntime (the shipped file) and through PyTorch."""
    lean = load_estimator(bundled_onnx("default"), threads=2)
    full = load_estimator("default", threads=2)
    assert lean.onnx_model is not None and full.model is not None
    return lean, full


@pytest.mark.parametrize("size", [(120, 160), (240, 320), (480, 640)])
def test_blended_depth_agrees_across_backends_on_every_pixel(both_backends, size):
    # Generated rooms with simulated zones (far walls give no-target zones, whose single
    # dominant hypothesis made the spread pure float32 rounding before it was computed
    # from the deviations; seed 2022 is the demo's first room).
    lean, full = both_backends
    for seed in (2022, 7, 11):
        frame = render_scene(seed, *size)
        zones = simulate_zone_frame(frame.depth_m, zone_rects(frame.intrinsics, 8))
        a, b = lean.predict(frame.image, zones), full.predict(frame.image, zones)
        assert a.network_depth_m is not None and b.network_depth_m is not None  # blended
        assert np.abs(a.network_depth_m - b.network_depth_m).max() <= 1e-4, seed
        assert np.abs(a.depth_m - b.depth_m).max() <= 1e-4, seed
        assert np.abs(a.uncertainty_m - b.uncertainty_m).max() <= 1e-4, seed


@pytest.mark.parametrize("size", [(720, 1280), (480, 480), (640, 480)])
def test_other_aspects_run_at_the_pytorch_size_with_the_pytorch_depth(both_backends, size):
    # 16:9, 1:1 and portrait 3:4 cameras: each at its own exported size, no stretching.
    import warnings

    lean, full = both_backends
    frame = render_scene(5, *size)
    zones = simulate_zone_frame(frame.depth_m, zone_rects(frame.intrinsics, 8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = lean.predict(frame.image, zones)
    b = full.predict(frame.image, zones)
    assert a.network_size == b.network_size != (256, 320)
    assert np.abs(a.network_depth_m - b.network_depth_m).max() <= 1e-4
    assert np.abs(a.depth_m - b.depth_m).max() <= 1e-4
    assert np.abs(a.uncertainty_m - b.uncertainty_m).max() <= 1e-4


def test_more_further_targets_than_the_head_weighs_agree_across_backends(both_backends):
    # Every zone reports a second target (more than SECONDARY_HYPOTHESES of them) with
    # equal signals: the left half's shares tie, and both backends must keep the same
    # ones (before: torch.topk kept an arbitrary subset, 0.26 m from onnxruntime's).
    from deltar.sensor.zone_frame import ZoneFrame

    lean, full = both_backends
    frame = render_scene(2022, 240, 320)
    mean = np.where(np.arange(8) < 4, 1.0, 3.0).astype(np.float32)[None].repeat(8, 0)
    sigma, valid = np.full((8, 8), 0.02, np.float32), np.ones((8, 8), bool)
    zones = ZoneFrame(mean, sigma, valid, target_mean_m=np.stack([mean, mean + 0.5], -1),
                      target_sigma_m=np.stack([sigma, sigma], -1),
                      target_valid=np.ones((8, 8, 2), bool),
                      target_signal=np.ones((8, 8, 2), np.float32))
    a, b = lean.predict(frame.image, zones), full.predict(frame.image, zones)
    assert np.abs(a.network_depth_m - b.network_depth_m).max() <= 1e-4
    assert np.abs(a.depth_m - b.depth_m).max() <= 1e-4
