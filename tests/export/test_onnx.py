"""ONNX export: parity with PyTorch, dynamic batch, layout guard, estimator backend."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.export.onnx import export_onnx
from deltar.inference.estimator import DepthEstimator
from deltar.inference.loading import load_estimator
from deltar.inference.onnx_runtime import OnnxDepthModel, layout_signature
from deltar.models import create_model
from deltar.sensor.zone_frame import ZoneFrame

DEPTH_TOLERANCE_M = 1e-3


def _torch_outputs(model, inputs):
    with torch.inference_mode():
        out = model(*inputs)
    return {k: v.numpy() for k, v in out.items()}


def _random_inputs(rects: np.ndarray, batch: int, seed: int):
    generator = torch.Generator().manual_seed(seed)
    zones = rects.shape[0]
    image = torch.randn(batch, 3, 64, 96, generator=generator)
    mean = 0.5 + 3 * torch.rand(batch, zones, 1, generator=generator)
    hypotheses = mean + torch.linspace(-0.1, 0.1, 16)
    valid = torch.rand(batch, zones, generator=generator) > 0.1
    hypotheses = hypotheses * valid[..., None]
    return (image, hypotheses, torch.from_numpy(rects)[None].expand(batch, -1, -1).contiguous(),
            valid)


def _plane_select_lite():
    """A seeded deltar-lite plane-select network (descriptor decoder, 64x96) with its
    channel weights spread over 0.5-1.5, in eval mode, torch on one thread."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-lite", head="plane_select", decoder="descriptors",
                         design_size=(64, 96)).eval()
    with torch.no_grad():
        model.decoder.channel_weight.uniform_(0.5, 1.5)
    return model


def _export_and_run(model, path, seed: int, threads: int):
    """Export a 64x96 model, run file and model on random inputs at its example layout.

    Returns:
        (onnx outputs, torch outputs, the layout's (Z, 4) rects, the ONNX runner).
    """
    from deltar.export.onnx import example_inputs

    export_onnx(model, path, 64, 96)
    rects = example_inputs(model, 64, 96)[2][0].numpy()
    inputs = _random_inputs(rects, 2, seed)
    runner = OnnxDepthModel(path, num_threads=threads)
    return runner.run(*(t.numpy() for t in inputs)), _torch_outputs(model, inputs), rects, runner


@pytest.fixture(scope="module")
def lite_export(tmp_path_factory):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    path = export_onnx(model, tmp_path_factory.mktemp("onnx") / "lite.onnx", 64, 96,
                       metadata={"deltar_weights": "test"})
    return model, path


def test_lite_parity_and_dynamic_batch(lite_export):
    # A head without use for the no-target flags: the file has the four inputs only.
    assert not OnnxDepthModel(lite_export[1], num_threads=1).takes_no_target
    model, path = lite_export
    runner = OnnxDepthModel(path, num_threads=1)
    assert runner.input_size == (64, 96) and runner.num_hypotheses == 16 and runner.grid == 8
    assert runner.metadata["deltar_weights"] == "test"
    from deltar.export.onnx import example_inputs

    rects = example_inputs(model, 64, 96)[2][0].numpy()
    for batch, seed in ((1, 0), (3, 1)):
        inputs = _random_inputs(rects, batch, seed)
        expected = _torch_outputs(model, inputs)
        got = runner.run(*(t.numpy() for t in inputs))
        for key in ("depth", "uncertainty", "bin_edges"):
            assert got[key].shape == expected[key].shape
            assert np.abs(got[key] - expected[key]).max() < DEPTH_TOLERANCE_M, key


def test_export_refuses_to_overwrite_and_checks_size(lite_export, tmp_path):
    model, path = lite_export
    with pytest.raises(FileExistsError):
        export_onnx(model, path, 64, 96)
    with pytest.raises(ValueError, match="positive"):
        export_onnx(model, tmp_path / "x.onnx", 0, 96)


def test_layout_guard_rejects_other_layouts(lite_export):
    _, path = lite_export
    runner = OnnxDepthModel(path)
    image = np.zeros((1, 3, 64, 96), np.float32)
    hypotheses = np.ones((1, 64, 16), np.float32)
    # A grid of 4 x 6 px zones: smaller patches than the exported nominal layout.
    ys, xs = np.meshgrid(np.arange(8) * 4.0, np.arange(8) * 6.0, indexing="ij")
    rects = np.stack([ys, xs, ys + 4, xs + 6], -1).reshape(1, 64, 4).astype(np.float32)
    with pytest.raises(ValueError, match="does not fit"):
        runner.run(image, hypotheses, rects, np.ones((1, 64), bool))
    with pytest.raises(ValueError, match="image must be"):
        runner.run(np.zeros((1, 3, 32, 96), np.float32), hypotheses, rects,
                   np.ones((1, 64), bool))


def test_estimator_onnx_backend_matches_pytorch(lite_export, rng):
    model, path = lite_export
    image = rng.integers(0, 256, size=(64, 96, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(0.5, 3, (8, 8)), rng.uniform(0.01, 0.1, (8, 8)),
                      np.ones((8, 8), bool))
    torch_pred = DepthEstimator(model, weights="t").predict(image, frame)
    onnx_pred = load_estimator(path, kind="onnx", threads=1).predict(image, frame)
    assert np.abs(torch_pred.depth_m - onnx_pred.depth_m).max() < DEPTH_TOLERANCE_M
    with pytest.raises(ValueError, match="float32"):
        load_estimator(path, kind="onnx", precision="float16")


def test_missing_or_foreign_onnx_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        OnnxDepthModel(tmp_path / "missing.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match=r"bad\.onnx"):
        OnnxDepthModel(bad)


def test_official_export_reproduces_the_release_outputs(tmp_path, parity_fixture):
    """deltar-official with the fixture's weights, exported at 480x640, run by onnxruntime,
    matches the release's own outputs on the case's inputs (calibrated rectangles running
    past the image); the two other cases have other layout signatures, which the exported
    model must refuse."""
    from deltar.contract import normalise_image
    from deltar.models import load_official_weights
    from deltar.models.benchmark import EDGE_TOLERANCE_M

    torch.set_num_threads(2)
    model = create_model("deltar-official")
    assert load_official_weights(model, parity_fixture["state_dict"]).ok
    model.eval()
    case = parity_fixture["cases"][0]
    rects = case["zone_rects_yxyx"].float().numpy()
    path = export_onnx(model, tmp_path / "official.onnx", 480, 640, zone_rects=rects)
    image = torch.from_numpy(normalise_image(case["image_rgb_uint8"].numpy()))[None]
    inputs = (image, case["zone_samples_icdf16"][None].float(),
              torch.from_numpy(rects)[None], case["zone_valid"][None].bool())
    runner = OnnxDepthModel(path, num_threads=2)
    got = runner.run(*(t.numpy() for t in inputs))
    depth_error = np.abs(got["depth"][0, 0] - case["expected_depth_half_res"].numpy()).max()
    edge_error = np.abs(got["bin_edges"][0] - case["expected_bin_edges"].numpy()).max()
    assert depth_error < DEPTH_TOLERANCE_M
    assert edge_error < EDGE_TOLERANCE_M
    for other in parity_fixture["cases"][1:]:
        other_rects = other["zone_rects_yxyx"][None].float().numpy()
        assert layout_signature(other_rects, 8) != runner.signature
        with pytest.raises(ValueError, match="does not fit"):
            runner.check_layout(other_rects)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["deltar-paper", "deltar-official"])
def test_other_presets_export_with_parity(preset, tmp_path):
    """The paper preset (mViT head, transformer encoder) and the released one export too."""
    torch.set_num_threads(2)
    torch.manual_seed(0)
    model = create_model(preset, design_size=(64, 96)).eval()
    got, expected, _, _ = _export_and_run(model, tmp_path / f"{preset}.onnx", 3, threads=2)
    assert np.abs(got["depth"] - expected["depth"]).max() < DEPTH_TOLERANCE_M


def test_zone_select_head_exports_with_parity(tmp_path):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-lite", head="zone_select", design_size=(64, 96)).eval()
    with torch.no_grad():
        model.head.query.weight.normal_(0.0, 0.5)
    got, expected, _, _ = _export_and_run(model, tmp_path / "select.onnx", 5, threads=1)
    assert np.abs(got["depth"] - expected["depth"]).max() < DEPTH_TOLERANCE_M


def test_plane_select_network_exports_with_parity(tmp_path):
    # No decoder: encoder descriptors, zone planes (closed-form 2x2 solves) and the
    # stride-4 head resized to the contract's stride 2, all in the graph.
    model = _plane_select_lite()
    got, expected, rects, runner = _export_and_run(model, tmp_path / "plane.onnx", 7, threads=1)
    assert got["depth"].shape == (2, 1, 32, 48)
    assert np.abs(got["depth"] - expected["depth"]).max() < DEPTH_TOLERANCE_M
    assert np.abs(got["uncertainty"] - expected["uncertainty"]).max() < DEPTH_TOLERANCE_M
    # The encoder's TensorFlow-"same" stride-2 convolutions carry their padding in the
    # Conv nodes (no Pad nodes, no shape arithmetic in the encoder), and the model is
    # left as it was.
    import onnx
    from timm.layers import Conv2dSame

    graph = onnx.load(str(tmp_path / "plane.onnx")).graph
    assert not [n for n in graph.node if n.op_type == "Pad" and "image_encoder" in n.name]
    assert not [n for n in graph.node if n.op_type == "Shape" and "image_encoder" in n.name]
    same = [m for m in model.modules() if isinstance(m, Conv2dSame)]
    assert same and not any("forward" in vars(m) for m in same)
    # No zone patches in this graph: any layout of the grid runs (here shrunk and moved,
    # which a fusion network's file refuses), with the same parity.
    moved = _random_inputs(rects * 0.7 + 5.0, 2, 8)
    runner.check_layout(moved[2].numpy())
    got = runner.run(*(t.numpy() for t in moved))
    assert np.abs(got["depth"] - _torch_outputs(model, moved)["depth"]).max() < \
        DEPTH_TOLERANCE_M
    # Its head reads the no-target flags: the file takes them as a fifth input.
    assert runner.takes_no_target
    inputs = _random_inputs(rects, 2, 9)
    no_target = ~inputs[3]
    with torch.inference_mode():
        flagged = model(*inputs, zone_no_target=no_target)["depth"].numpy()
    got = runner.run(*(t.numpy() for t in inputs), no_target.numpy())
    assert np.abs(got["depth"] - flagged).max() < DEPTH_TOLERANCE_M
    assert np.abs(flagged - _torch_outputs(model, inputs)["depth"]).max() > 0.1
    # And several targets per zone, as a sixth input of NETWORK_TARGET_SLOTS slots:
    # the same depth as PyTorch; none given reads as the primary readings alone.
    assert runner.target_slots == 2
    primary = inputs[1].mean(dim=2)
    targets = torch.zeros(*inputs[3].shape, 2, 2)
    targets[..., 0, 0], targets[..., 0, 1] = primary, 0.6
    targets[:, ::3, 1, 0], targets[:, ::3, 1, 1] = primary[:, ::3] * 2.5, 0.4
    targets = targets * inputs[3][..., None, None]
    with torch.inference_mode():
        expected = model(*inputs, zone_no_target=no_target, zone_targets=targets)["depth"]
    got = runner.run(*(t.numpy() for t in inputs), no_target.numpy(), targets.numpy())
    assert np.abs(got["depth"] - expected.numpy()).max() < DEPTH_TOLERANCE_M
    assert np.abs(expected.numpy() - flagged).max() > 0.1
    alone = runner.run(*(t.numpy() for t in inputs), no_target.numpy(), None)
    assert np.abs(alone["depth"] - flagged).max() < DEPTH_TOLERANCE_M


def test_the_targets_work_runs_only_for_frames_that_report_further_targets(tmp_path):
    """One graph, two branches: the network traced without the targets input serves
    batches in which no valid zone reports a further target; both give PyTorch's depth
    and uncertainty."""
    import onnx

    from deltar.export.onnx import example_inputs
    from deltar.inference.onnx_runtime import TARGETS_INPUT

    model = _plane_select_lite()
    path = export_onnx(model, tmp_path / "plane.onnx", 64, 96)
    graph = onnx.load(str(path)).graph
    (branch,) = [n for n in graph.node if n.op_type == "If"]
    several, single = (next(a.g for a in branch.attribute if a.name == name)
                       for name in ("then_branch", "else_branch"))
    # The encoder and descriptors run once, before the choice; the single-target branch
    # never reads the targets and has less to do.
    assert any("image_encoder" in n.name for n in graph.node)
    assert not any("image_encoder" in n.name or "decoder" in n.name
                   for g in (several, single) for n in g.node)
    assert not any(TARGETS_INPUT in n.input for n in single.node)
    assert len(single.node) < len(several.node)
    rects = example_inputs(model, 64, 96)[2][0].numpy()
    inputs = _random_inputs(rects, 2, 11)
    runner = OnnxDepthModel(path, num_threads=1)
    primary = inputs[1].mean(dim=2)
    targets = torch.zeros(*inputs[3].shape, 2, 2)
    targets[..., 0, 0], targets[..., 0, 1] = primary, 0.7
    # Further targets in invalid zones alone: they count for nothing (single branch).
    invalid_only = targets.clone()
    invalid_only[..., 1, 0], invalid_only[..., 1, 1] = 3.0, 0.3
    invalid_only = torch.where(inputs[3][..., None, None], targets, invalid_only)
    # And in every fourth zone, valid or not (several-targets branch).
    several_targets = targets.clone()
    several_targets[:, ::4, 1, 0], several_targets[:, ::4, 1, 1] = primary[:, ::4] * 2.0, 0.3
    with torch.inference_mode():
        plain = model(*inputs)
    for given in (None, targets, invalid_only, several_targets):
        with torch.inference_mode():
            expected = model(*inputs, zone_targets=given) if given is not None else plain
        got = runner.run(*(t.numpy() for t in inputs), None,
                         None if given is None else given.numpy())
        for key in ("depth", "uncertainty"):
            assert np.abs(got[key] - expected[key].numpy()).max() < 1e-4
    with torch.inference_mode():
        moved = model(*inputs, zone_targets=several_targets)["depth"]
    assert np.abs(moved.numpy() - plain["depth"].numpy()).max() > 0.05


@pytest.mark.parametrize("size", [(480, 480), (720, 1280)])
def test_export_runs_at_the_size_rule_like_the_estimator(tmp_path, rng, size):
    """A non-4:3 camera: the file's fixed input is the size the estimator runs the model
    at (aspect kept, design pixel budget, multiples of 32), and both backends agree."""
    from deltar.export.onnx import export_input_size
    from deltar.inference.preprocess import network_input_size

    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    with torch.no_grad():  # a head that is not zero, so the image matters
        model.head.logits_conv.weight.normal_(0.0, 0.5)
    path = export_onnx(model, tmp_path / "odd.onnx", *size)
    assert not model.traceable  # the export leaves the model on its eager path
    expected = network_input_size(*size, design_size=(64, 96))
    runner = OnnxDepthModel(path, num_threads=1)
    assert runner.input_size == export_input_size(model, *size) == expected
    assert runner.metadata["deltar_input_size"] == f"{expected[0]}x{expected[1]}"
    assert runner.metadata["deltar_image_size"] == f"{size[0]}x{size[1]}"
    image = rng.integers(0, 256, size=(*size, 3), dtype=np.uint8)
    frame = ZoneFrame(rng.uniform(0.5, 3, (8, 8)), rng.uniform(0.01, 0.1, (8, 8)),
                      np.ones((8, 8), bool))
    torch_pred = DepthEstimator(model, weights="t", fold_batch_norms=False).predict(image, frame)
    onnx_pred = load_estimator(path, kind="onnx", threads=1).predict(image, frame)
    assert torch_pred.network_size == onnx_pred.network_size == expected
    assert onnx_pred.depth_m.shape == size
    assert np.abs(torch_pred.depth_m - onnx_pred.depth_m).max() < DEPTH_TOLERANCE_M


def test_a_model_prepared_for_inference_exports_with_parity(tmp_path):
    # The estimator's model has its "same" convolutions rewritten
    # (SymmetricSameConv2d); its export is the same graph, with the same outputs.
    import onnx

    from deltar.models.optimize import SymmetricSameConv2d, prepare_for_inference

    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-select", design_size=(64, 96)).eval()
    with torch.no_grad():
        model.decoder.channel_weight.uniform_(0.5, 1.5)
    prepare_for_inference(model)
    assert any(isinstance(m, SymmetricSameConv2d) for m in model.modules())
    got, expected, _, _ = _export_and_run(model, tmp_path / "prepared.onnx", 11, threads=1)
    assert np.abs(got["depth"] - expected["depth"]).max() < DEPTH_TOLERANCE_M
    graph = onnx.load(str(tmp_path / "prepared.onnx")).graph
    assert not [n for n in graph.node if n.op_type == "Pad" and "image_encoder" in n.name]
    assert not any("forward" in vars(m) for m in model.modules()
                   if isinstance(m, SymmetricSameConv2d))


def test_several_sizes_share_one_weights_file_and_run_each_image_at_its_rule_size(
        tmp_path, rng):
    import json

    from deltar.export.onnx import export_onnx_sizes
    from deltar.inference.onnx_runtime import SIZES_KEY

    model = _plane_select_lite()
    # 64x96 and 128x192 give the same network size: one file for both.
    camera_sizes = [(64, 96), (54, 128), (128, 192), (96, 64)]
    written = export_onnx_sizes(model, tmp_path / "net.onnx", camera_sizes)
    names = [p.name for p in written]
    assert names == ["net.onnx", "net.64x128.onnx", "net.96x64.onnx", "net.onnx.data"]
    single = export_onnx(model, tmp_path / "alone.onnx", 54, 128)
    weights = written[-1].stat().st_size
    # The weights are written once: each graph is a small fraction of a whole export.
    assert all(p.stat().st_size < 0.5 * single.stat().st_size for p in written[:-1])
    assert weights > 0.5 * single.stat().st_size
    runner = OnnxDepthModel(written[0], num_threads=1)
    assert runner.input_sizes == ((64, 96), (64, 128), (96, 64))
    assert json.loads(runner.metadata[SIZES_KEY]) == {
        "64x96": "net.onnx", "64x128": "net.64x128.onnx", "96x64": "net.96x64.onnx"}
    with pytest.raises(ValueError, match="no export for 32x32"):
        runner.for_input_size((32, 32))
    # Every image runs at the size rule's size, with the PyTorch path's depth; the
    # wide one by the file written for it, as a file exported alone for it gives.
    estimator = load_estimator(written[0], kind="onnx", threads=1)
    reference = DepthEstimator(model, weights="t", fold_batch_norms=False)
    alone = load_estimator(single, kind="onnx", threads=1)
    frame = ZoneFrame(rng.uniform(0.5, 3, (8, 8)), rng.uniform(0.01, 0.1, (8, 8)),
                      np.ones((8, 8), bool))
    for size in [(64, 96), (54, 128), (96, 64)]:
        image = rng.integers(0, 256, size=(*size, 3), dtype=np.uint8)
        got, expected = estimator.predict(image, frame), reference.predict(image, frame)
        assert got.network_size == expected.network_size
        assert np.abs(got.depth_m - expected.depth_m).max() < DEPTH_TOLERANCE_M
        if size == (54, 128):
            assert got.network_size == (64, 128)
            np.testing.assert_allclose(got.depth_m, alone.predict(image, frame).depth_m,
                                       atol=1e-6)
    with pytest.raises(FileExistsError):
        export_onnx_sizes(model, tmp_path / "net.onnx", camera_sizes)
    # The files go together: one missing is named when the set is loaded.
    written[2].unlink()
    with pytest.raises(ValueError, match=r"96x64 export .*net\.96x64\.onnx.* missing"):
        OnnxDepthModel(written[0])


def test_the_hypotheses_source_travels_with_checkpoint_and_onnx_file(tmp_path):
    """A network trained on histogram hypotheses says so in its checkpoint and its ONNX
    file, and both backends then draw a CNH frame's hypotheses from its histograms."""
    from deltar.models.checkpoint import save_checkpoint
    from deltar.sensor.cnh import zone_frame_from_cnh
    from deltar.sensor.hypotheses import zone_hypotheses_from_histogram

    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96), histogram_hypotheses=True).eval()
    save_checkpoint(tmp_path / "hist.pt", model, "deltar-lite")
    export_onnx(model, tmp_path / "hist.onnx", 64, 96)
    rng = np.random.default_rng(0)
    values = rng.uniform(0, 50, size=(64, 18))
    values[np.arange(64), rng.integers(0, 18, 64)] += 2000.0
    frame = zone_frame_from_cnh(np.full(64, 1500.0), values)
    _, _, valid = frame.flat()
    expected = zone_hypotheses_from_histogram(frame.hist_edges_m,
                                              frame.hist_counts.reshape(64, -1), valid, 16)
    for path, kind in ((tmp_path / "hist.pt", "checkpoint"), (tmp_path / "hist.onnx", "onnx")):
        estimator = load_estimator(path, kind=kind, threads=1)
        assert estimator.histogram_hypotheses
        np.testing.assert_array_equal(estimator.hypotheses_for(frame), expected)


def test_an_onnx_file_from_before_the_key_reads_mean_and_sigma(lite_export, tmp_path):
    """Files exported before ``histogram_hypotheses`` existed (their config has no such
    key) are read as weights trained without histograms."""
    import json

    import onnx

    _, path = lite_export
    graph = onnx.load(path)
    for prop in graph.metadata_props:
        if prop.key == "deltar_config":
            config = json.loads(prop.value)
            del config["input"]["histogram_hypotheses"]
            prop.value = json.dumps(config)
    onnx.save(graph, tmp_path / "old.onnx")
    estimator = load_estimator(tmp_path / "old.onnx", kind="onnx", threads=1)
    assert "histogram_hypotheses" not in estimator.onnx_model.contract
    assert estimator.histogram_hypotheses is False


def test_export_leaves_the_callers_model_as_it_was_and_names_bad_arguments(tmp_path):
    model = create_model("deltar-lite").train().to(torch.bfloat16)
    export_onnx(model, tmp_path / "m.onnx", 48, 64)
    assert model.training and next(model.parameters()).dtype == torch.bfloat16
    for kwargs, message in (({"model": None}, "model must be a DeltarNet"),
                            ({"height": float("nan")}, "height and width must be positive"),
                            ({"zone_rects": np.zeros((3, 3))}, r"zone_rects must be \(Z, 4\)")):
        arguments = {"model": model, "height": 48, "zone_rects": None, **kwargs}
        with pytest.raises(ValueError, match=message):
            export_onnx(arguments["model"], tmp_path / "n.onnx", arguments["height"], 64,
                        zone_rects=arguments["zone_rects"])
    assert not (tmp_path / "n.onnx").exists()


def test_a_failed_multi_size_export_leaves_no_file_under_the_final_names(tmp_path,
                                                                        monkeypatch):
    import deltar.io.atomic
    from deltar.export.onnx import export_onnx_sizes, sized_export_paths

    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    sizes = [(64, 96), (96, 96)]
    out = tmp_path / "m.onnx"
    files = list(sized_export_paths(model, out, sizes).values())
    assert [f.name for f in files] == ["m.onnx", "m.64x64.onnx"]
    # A folder under one of the names: refused naming it, before anything is written.
    files[1].mkdir()
    with pytest.raises(ValueError, match=rf"^{files[1]} is a folder, not a file"):
        export_onnx_sizes(model, out, sizes, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == [files[1].name]
    files[1].rmdir()
    # A failure while moving the files into place (the disk, a folder made meanwhile):
    # the ones moved before are removed again, and the error names the final path.
    moves = []
    move = deltar.io.atomic.move_into_place

    def fails_on_the_last(tmp, final, overwrite):
        moves.append(final)
        if len(moves) == 3:
            raise IsADirectoryError(21, "Is a directory", str(tmp), None, str(final))
        move(tmp, final, overwrite)

    monkeypatch.setattr(deltar.io.atomic, "move_into_place", fails_on_the_last)
    with pytest.raises(IsADirectoryError) as caught:
        export_onnx_sizes(model, out, sizes)
    assert caught.value.filename == str(moves[-1])
    assert list(tmp_path.iterdir()) == []  # no final name, no temporary left

    # With overwrite, the files a failed move would have replaced are put back as they
    # were, also those already replaced when the last one fails.
    old = {f: f"old {f.name}".encode() for f in (*files, out.with_name("m.onnx.data"))}
    for f, content in old.items():
        f.write_bytes(content)
    finals = []

    def fails_on_the_last_final_name(tmp, final, overwrite):
        if final in old:  # not the exports into the staging folder
            finals.append(final)
            if len(finals) == len(old):
                raise IsADirectoryError(21, "Is a directory", str(tmp), None, str(final))
        move(tmp, final, overwrite)

    monkeypatch.setattr(deltar.io.atomic, "move_into_place", fails_on_the_last_final_name)
    with pytest.raises(IsADirectoryError):
        export_onnx_sizes(model, out, sizes, overwrite=True)
    assert sorted(finals) == sorted(old)
    assert {f: f.read_bytes() for f in old} == old
    assert sorted(tmp_path.iterdir()) == sorted(old)  # no backup or temporary left
