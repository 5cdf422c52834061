"""ONNX graph rewrites: pads folded into convolutions, constants merged, short names."""

from __future__ import annotations

import numpy as np
import torch


class _Padded(torch.nn.Module):
    """One foldable zero pad before a convolution, and pads that must stay: reflect mode,
    a non-zero value, a pad also read by an add, a pad that is a graph output."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 4, 3, stride=2)

    def forward(self, x):
        pad = torch.nn.functional.pad
        folded = self.conv(pad(x, (0, 1, 1, 2)))
        reflect = self.conv(pad(x, (1, 0, 0, 1), mode="reflect"))
        ones = self.conv(pad(x, (1, 1, 0, 0), value=1.0))
        shared = pad(x, (2, 2, 2, 2))
        mixed = self.conv(shared).sum() + shared.sum()
        returned = pad(x, (1, 2, 1, 2))
        return folded, reflect, ones, mixed, returned, self.conv(returned)


def test_constant_zero_pads_fold_into_the_convolutions_they_feed(tmp_path):
    import onnx
    import onnxruntime as ort

    from deltar.export.graph_rewrites import fold_pads_into_convs

    model = _Padded().eval()
    x = torch.randn(1, 3, 12, 17, generator=torch.Generator().manual_seed(1))
    path = tmp_path / "pads.onnx"
    with torch.no_grad():
        expected = [t.numpy() for t in model(x)]
        torch.onnx.export(model, (x,), str(path), input_names=["x"], opset_version=17,
                          dynamo=False)
    proto = onnx.load(str(path))
    pads_before = sum(n.op_type == "Pad" for n in proto.graph.node)
    assert pads_before == 5
    assert fold_pads_into_convs(proto) == 1
    assert sum(n.op_type == "Pad" for n in proto.graph.node) == pads_before - 1
    onnx.checker.check_model(proto)
    folded = [n for n in proto.graph.node if n.op_type == "Conv" and n.input[0] == "x"]
    assert [list(a.ints) for n in folded for a in n.attribute if a.name == "pads"] == \
        [[1, 0, 2, 1]]
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    for got, want in zip(session.run(None, {"x": x.numpy()}), expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_a_pad_of_convolution_weights_is_left_alone():
    import onnx
    from onnx import TensorProto, helper

    from deltar.export.graph_rewrites import fold_pads_into_convs

    pads = helper.make_tensor("pads", TensorProto.INT64, [8], [0, 0, 0, 0, 0, 0, 1, 1])
    weight = helper.make_tensor("w", TensorProto.FLOAT, [1, 1, 2, 2], [1.0] * 4)
    graph = helper.make_graph(
        [helper.make_node("Pad", ["w", "pads"], ["w_padded"]),
         helper.make_node("Conv", ["x", "w_padded"], ["y"])], "weights",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, 5, 5])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 1, 3, 3])],
        initializer=[pads, weight])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    assert fold_pads_into_convs(proto) == 0
    assert [n.op_type for n in proto.graph.node] == ["Pad", "Conv"]
    onnx.checker.check_model(proto)


def test_equal_constants_merge_and_values_get_short_names_with_the_same_outputs():
    """Two equal Constant nodes, one inside an If branch, become one outer initializer;
    computed values get short names, the graph's inputs and outputs keep theirs."""
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from deltar.export.graph_rewrites import merge_equal_constants, short_value_names

    table = np.arange(12, dtype=np.float32).reshape(3, 4)

    def constant(name: str) -> onnx.NodeProto:
        return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(table),
                                name=f"/module/{name}")

    def branch(name: str, op: str) -> onnx.GraphProto:
        return helper.make_graph(
            [constant(f"{name}_table"), helper.make_node(op, ["scaled", f"{name}_table"],
                                                         [f"{name}_out"], name=f"/{name}/Op")],
            name, [], [helper.make_tensor_value_info(f"{name}_out", TensorProto.FLOAT, [3, 4])])

    graph = helper.make_graph(
        [constant("outer_table"),
         helper.make_node("Mul", ["x", "outer_table"], ["scaled"], name="/module/Mul"),
         helper.make_node("If", ["flag"], ["y"], then_branch=branch("then", "Add"),
                          else_branch=branch("else", "Sub"), name="/module/If")],
        "toy", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [3, 4]),
                helper.make_tensor_value_info("flag", TensorProto.BOOL, [])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [3, 4])])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    x = np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4)

    def run(model: onnx.ModelProto, flag: bool) -> np.ndarray:
        session = ort.InferenceSession(model.SerializeToString(),
                                       providers=["CPUExecutionProvider"])
        return session.run(None, {"x": x, "flag": np.array(flag)})[0]

    expected = [run(proto, flag) for flag in (True, False)]
    assert merge_equal_constants(proto) == 3
    short_value_names(proto)
    onnx.checker.check_model(proto)
    assert len(proto.graph.initializer) == 1
    assert not [n for n in proto.graph.node if n.op_type == "Constant"]
    assert [v.name for v in proto.graph.input] == ["x", "flag"]
    assert [v.name for v in proto.graph.output] == ["y"]
    assert [n.name for n in proto.graph.node] == ["/module/Mul", "/module/If"]
    assert all(len(name) <= 3 for name in proto.graph.node[0].output)
    for flag, want in zip((True, False), expected, strict=True):
        np.testing.assert_array_equal(run(proto, flag), want)
