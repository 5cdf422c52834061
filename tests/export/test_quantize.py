"""Static int8 quantisation of an exported model (small model, a few real frames)."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from deltar.export.onnx import export_onnx
from deltar.export.quantize import QUANT_KEY, calibration_feeds, export_int8, quantize_onnx
from deltar.inference.loading import load_estimator
from deltar.inference.onnx_runtime import OnnxDepthModel
from deltar.models import create_model

from ..conftest import SHARED_DATA

SIZE = (64, 96)


def _small_model():
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=SIZE).eval()
    # The zone-prior head starts at zero logits (depth = prior, whatever the features);
    # random logits make the output depend on the quantised features.
    torch.nn.init.normal_(model.head.logits_conv.weight, std=0.05)
    return model


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}")
    shared = SHARED_DATA
    folder = tmp_path_factory.mktemp("int8")
    float_path = export_onnx(_small_model(), folder / "float.onnx", *SIZE,
                             metadata={"deltar_weights": "test"})
    estimator = load_estimator(float_path, kind="onnx", threads=1)
    feeds = calibration_feeds(estimator, shared / "icl_livingroom1", frames=3)
    int8_path = quantize_onnx(float_path, folder / "int8.onnx", feeds)
    return float_path, int8_path, feeds, shared


def test_calibration_feeds_are_network_inputs_with_simulated_zones(exported):
    _, _, feeds, _ = exported
    assert len(feeds) == 3
    for feed in feeds:
        assert feed["image"].shape == (1, 3, *SIZE) and feed["image"].dtype == np.float32
        assert feed["hypotheses"].shape == (1, 64, 16)
        assert feed["zone_valid"].dtype == bool and feed["zone_valid"].sum() > 32
        valid = feed["zone_valid"][0]
        # Simulated from real indoor depth: metres within the sensor's 4 m range.
        assert 0.2 < feed["hypotheses"][0, valid].mean() < 4.5
    # Different frames, different readings.
    assert not np.allclose(feeds[0]["hypotheses"], feeds[1]["hypotheses"])


def test_int8_model_is_quantised_runs_and_stays_close(exported):
    float_path, int8_path, feeds, _ = exported
    graph = onnx.load(str(int8_path)).graph
    ops = {node.op_type for node in graph.node}
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    # Quantised convolutions read int8 weights through DequantizeLinear; the head's do not.
    producers = {out: node.op_type for node in graph.node for out in node.output}
    convs = [node for node in graph.node if node.op_type == "Conv"]
    head = [node for node in convs if "/head/" in node.name]
    assert head and all(producers.get(node.input[1]) != "DequantizeLinear" for node in head)
    quantised = [node for node in convs if producers.get(node.input[1]) == "DequantizeLinear"]
    assert len(quantised) > len(convs) // 2
    float_model = OnnxDepthModel(float_path, num_threads=1)
    int8_model = OnnxDepthModel(int8_path, num_threads=1)
    assert int8_model.metadata["deltar_weights"] == "test"
    assert "int8" in int8_model.metadata[QUANT_KEY]
    for feed in feeds:
        reference = float_model.run(**feed)["depth"]
        quantised = int8_model.run(**feed)["depth"]
        relative = np.abs(quantised - reference) / reference
        assert np.isfinite(quantised).all()
        assert 0 < relative.max() and relative.mean() < 0.03
    # The estimator runs it like any export.
    estimator = load_estimator(int8_path, kind="onnx", threads=1)
    image = np.full((*SIZE, 3), 128, np.uint8)
    from deltar.sensor.zone_frame import ZoneFrame

    frame = ZoneFrame(np.full((8, 8), 1.5), np.full((8, 8), 0.02), np.ones((8, 8), bool))
    depth = estimator.predict(image, frame).depth_m
    assert depth.shape == SIZE and np.isfinite(depth).all()


def test_quantize_rejects_bad_input(exported, tmp_path):
    float_path, int8_path, feeds, shared = exported
    with pytest.raises(FileNotFoundError):
        quantize_onnx(tmp_path / "missing.onnx", tmp_path / "out.onnx", feeds)
    with pytest.raises(ValueError, match="at least one"):
        quantize_onnx(float_path, tmp_path / "out.onnx", [])
    with pytest.raises(ValueError, match="must differ"):
        quantize_onnx(float_path, float_path, feeds, overwrite=True)
    with pytest.raises(ValueError, match="already quantised"):
        quantize_onnx(int8_path, tmp_path / "twice.onnx", feeds)
    with pytest.raises(FileExistsError):
        quantize_onnx(float_path, int8_path, feeds)
    with pytest.raises(ValueError, match="frames"):
        calibration_feeds(load_estimator(float_path, kind="onnx"), shared / "icl_livingroom1", 0)
    with pytest.raises(FileNotFoundError, match="calibration"):
        export_int8(_small_model(), tmp_path / "x.onnx", *SIZE, tmp_path / "no_such_folder")


def test_weights_trained_on_histograms_calibrate_on_histogram_hypotheses(exported):
    """Their feeds carry the hypotheses of ST's example CNH bins, as a CH part's
    frames give them at run time, not the Gaussian ones of the other feeds."""
    from deltar.data.rgbd import open_rgbd
    from deltar.sensor.cnh import CNHConfig, simulate_cnh
    from deltar.sensor.hypotheses import zone_hypotheses_from_histogram
    from deltar.sensor.zone_frame import ZoneFrame

    float_path, _, gaussian, shared = exported
    estimator = load_estimator(float_path, kind="onnx", threads=1, histogram_hypotheses=True)
    feeds = calibration_feeds(estimator, shared / "icl_livingroom1", frames=3)
    reader = open_rgbd(shared / "icl_livingroom1")
    frame = reader[0]  # the first of the evenly spread picks
    layout = ZoneFrame(np.ones((8, 8)), np.zeros((8, 8)), np.ones((8, 8), bool))
    rects = estimator.zone_rects_for(layout, frame.image.shape[:2])
    expected = zone_hypotheses_from_histogram(
        CNHConfig().edges_m(), simulate_cnh(frame.depth_m, rects, CNHConfig()),
        feeds[0]["zone_valid"][0], 16)
    np.testing.assert_allclose(feeds[0]["hypotheses"][0], expected, atol=1e-5)
    assert not np.allclose(feeds[0]["hypotheses"], gaussian[0]["hypotheses"], atol=1e-3)


def test_a_file_that_takes_the_no_target_flags_quantises_with_them(tmp_path):
    # The plane-select network (the bundled model's) takes a fifth input, and several
    # targets per zone as a sixth; the real office frames have zones beyond 4 m, so the
    # feeds carry flags that are set (and targets simulated, as the file reads them).
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=SIZE).eval()
    float_path = export_onnx(model, tmp_path / "select.onnx", *SIZE)
    estimator = load_estimator(float_path, kind="onnx", threads=1)
    assert estimator.onnx_model.takes_no_target
    feeds = calibration_feeds(estimator, SHARED_DATA / "realsense_office", frames=2)
    assert estimator.onnx_model.target_slots == 2
    assert all(set(feed) == {"image", "hypotheses", "zone_rects", "zone_valid",
                             "zone_no_target", "zone_targets"} for feed in feeds)
    assert any(feed["zone_no_target"].any() for feed in feeds)
    assert all(feed["zone_targets"].shape == (1, 64, 2, 2) for feed in feeds)
    int8_path = quantize_onnx(float_path, tmp_path / "select-int8.onnx", feeds)
    runner = OnnxDepthModel(int8_path, num_threads=1)
    assert runner.takes_no_target
    out = runner.run(*(feeds[0][k] for k in ("image", "hypotheses", "zone_rects",
                                               "zone_valid", "zone_no_target",
                                               "zone_targets")))
    assert np.all(np.isfinite(out["depth"])) and out["depth"].shape == (1, 1, 32, 48)


def test_a_folder_that_is_not_rgbd_fails_before_the_float_export(tmp_path, monkeypatch):
    import deltar.export.onnx

    def no_export(*args, **kwargs):
        raise AssertionError("exported before checking the calibration folder")

    monkeypatch.setattr(deltar.export.onnx, "export_onnx", no_export)
    (tmp_path / "plain").mkdir()
    with pytest.raises(ValueError, match="cannot tell the layout of"):
        export_int8(_small_model(), tmp_path / "x.onnx", *SIZE, tmp_path / "plain")
    assert not (tmp_path / "x.onnx").exists()
