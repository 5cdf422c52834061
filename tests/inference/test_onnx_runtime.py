"""``OnnxDepthModel`` on files whose deltar metadata or weights were damaged after export:
one ``ValueError`` naming the file, never a traceback of another type."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from deltar.export.onnx import export_onnx, export_onnx_sizes
from deltar.inference.onnx_runtime import OnnxDepthModel
from deltar.models import create_model

onnx = pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    return export_onnx(model, tmp_path_factory.mktemp("onnx") / "lite.onnx", 64, 96)


def _edited(source, target, key, value=None):
    """A copy of ``source`` with metadata ``key`` set to ``value`` (removed when None)."""
    proto = onnx.load(str(source))
    kept = [(e.key, e.value) for e in proto.metadata_props if e.key != key]
    if value is not None:
        kept.append((key, value))
    del proto.metadata_props[:]
    for k, v in kept:
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(proto, str(target))
    return target


@pytest.mark.parametrize(("key", "value", "what"), [
    ("deltar_grid", None, "no deltar_grid metadata"),
    ("deltar_grid", "abc", "deltar_grid must be a positive whole number, got 'abc'"),
    ("deltar_grid", "0", "deltar_grid must be a positive whole number, got '0'"),
    ("deltar_layout_signature", "{not json", "deltar_layout_signature is not JSON"),
    ("deltar_layout_signature", "5", "deltar_layout_signature must be a JSON list"),
    ("deltar_layout_signature", "[1]", "deltar_layout_signature must list"),
    ("deltar_config", "[1, 2]", "deltar_config must be a JSON object"),
    ("deltar_input_sizes", "[1]", "deltar_input_sizes must be a JSON object"),
    ("deltar_input_sizes", '{"abc": "x.onnx"}', "deltar_input_sizes must be a positive"),
])
def test_corrupt_metadata_is_one_error_naming_the_file(exported, tmp_path, key, value, what):
    path = _edited(exported, tmp_path / "bad.onnx", key, value)
    with pytest.raises(ValueError, match=r"^\S*bad\.onnx: cannot read its deltar metadata: ") \
            as caught:
        OnnxDepthModel(path)
    assert what in str(caught.value)


def test_a_symbolic_image_height_is_named(exported, tmp_path):
    proto = onnx.load(str(exported))
    proto.graph.input[0].type.tensor_type.shape.dim[2].dim_param = "h"
    onnx.save(proto, str(tmp_path / "dyn.onnx"))
    with pytest.raises(ValueError, match=r"dyn\.onnx: cannot read its deltar metadata: "
                       r"input 'image' has shape .*axis 2 must be fixed"):
        OnnxDepthModel(tmp_path / "dyn.onnx")


def test_truncated_external_weights_give_deltars_error_alone(tmp_path):
    torch.manual_seed(0)
    model = create_model("deltar-lite", design_size=(64, 96)).eval()
    export_onnx_sizes(model, tmp_path / "m.onnx", [(64, 96)])  # weights in m.onnx.data
    data = tmp_path / "m.onnx.data"
    data.write_bytes(data.read_bytes()[:data.stat().st_size // 2])
    # In a fresh process: onnxruntime's logger writes to the C++ stderr.
    code = ("from deltar.inference.onnx_runtime import OnnxDepthModel\n"
            "try:\n    OnnxDepthModel('m.onnx')\n"
            "except ValueError as err:\n    print(err)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.stdout.startswith("m.onnx: cannot load ONNX model")
    # onnxruntime's own (coloured) log line is not printed before deltar's message.
    assert "[E:onnxruntime" not in done.stderr
