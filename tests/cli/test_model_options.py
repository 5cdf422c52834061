"""The model option group: one definition, the same options on every model command."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from deltar.cli.main import app
from deltar.cli.model_options import MODEL_OPTIONS, ModelOptions, model_options

ALL = ["--preset", "--checkpoint", "--official", "--onnx", "--device", "--precision",
       "--size", "--threads", "--flip", "--network-only", "--no-inferred-flags",
       "--keep-outlier-zones"]


def _options(command: str) -> dict[str, str]:
    group = typer.main.get_command(app)
    return {p.opts[0]: p.help for p in group.commands[command].params}


def test_predict_replay_and_wall_test_share_the_model_options():
    reference = _options("predict")
    for command in ("predict", "replay", "wall-test"):
        options = _options(command)
        assert [o for o in options if o in ALL] == ALL, command
        assert {o: options[o] for o in ALL} == {o: reference[o] for o in ALL}
    export = _options("export")
    assert {o: export[o] for o in ALL[:3]} == {o: reference[o] for o in ALL[:3]}


def test_the_command_receives_one_model_object():
    seen = []

    @model_options
    def command(out: str = "x", model: ModelOptions = MODEL_OPTIONS, last: int = 1):
        seen.append((out, model, last))

    command(out="o", last=2, **{name.lstrip("-").replace("-", "_"): value for name, value in
                                zip(ALL, [None, "c.pt", None, None, "cpu", "float16", "64x64",
                                           2, True, True, True, True], strict=True)})
    out, model, last = seen[0]
    assert (out, last) == ("o", 2)
    assert model == ModelOptions(checkpoint="c.pt", precision="float16", size="64x64",
                                 threads=2, flip=True, network_only=True,
                                 no_inferred_flags=True, keep_outlier_zones=True)
    assert model.source() == ("c.pt", "checkpoint")
    assert ModelOptions().source() == (None, None)
    with pytest.raises(TypeError, match="has no 'model' parameter"):
        model_options(lambda out="x": None)


@pytest.mark.parametrize(("options", "message"), [
    (ModelOptions(preset="deltar-lite", onnx="m.onnx"), "give only one of --preset"),
    (ModelOptions(onnx="m.onnx", flip=True), "--flip needs a PyTorch model"),
    (ModelOptions(precision="float8"), "must be one of float32, float16, bfloat16"),
    (ModelOptions(size="100x64"), r"--size must be positive multiples of 32, got \(100, 64\)"),
    (ModelOptions(size="big"), "size must look like 480x640, got 'big'"),
])
def test_usage_checks_name_the_option(options, message):
    with pytest.raises(typer.BadParameter, match=message):
        options.check()


def test_two_model_options_on_the_command_line_is_a_usage_error(tmp_path):
    result = CliRunner().invoke(app, ["wall-test", str(tmp_path), "--out", str(tmp_path / "o"),
                                      "--preset", "deltar-lite", "--onnx", "m.onnx"])
    assert result.exit_code == 2
    assert "give only one of --preset, --checkpoint, --official, --onnx" in result.stderr


def test_network_only_turns_the_blend_off():
    """The bundled plane-select model blends by default; --network-only is the network."""
    assert ModelOptions().load().blend is not None
    assert ModelOptions(network_only=True).load().blend is None


def test_no_inferred_flags_turns_the_no_target_rule_off():
    """The bundled model infers flags for frames without them; --no-inferred-flags not."""
    assert ModelOptions().load().no_target_min_neighbour_m is not None
    assert ModelOptions(no_inferred_flags=True).load().no_target_min_neighbour_m is None


def test_keep_outlier_zones_turns_the_outlier_rule_off(tmp_path):
    from deltar.models import create_model
    from deltar.models.checkpoint import save_checkpoint
    from deltar.sensor.zone_outliers import OutlierRule

    model = create_model("deltar-select", design_size=(32, 64))
    model.set_output_contract(zone_outlier_rule=OutlierRule(0.05, min_zones=3).to_dict())
    path = save_checkpoint(tmp_path / "select.pt", model, "deltar-select")
    assert ModelOptions(checkpoint=path).load().zone_outliers == OutlierRule(0.05, min_zones=3)
    assert ModelOptions(checkpoint=path, keep_outlier_zones=True).load().zone_outliers is None
