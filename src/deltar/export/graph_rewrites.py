"""Rewrites of exported ONNX graphs (:mod:`deltar.export.onnx` applies them): same
outputs, less work or fewer bytes.

- :func:`fold_pads_into_convs`: constant zero ``Pad`` nodes merged into their ``Conv``.
- :func:`single_target_branch`: one graph of the exports with and without the
  ``zone_targets`` input, the several-targets work only for batches that need it.
- :func:`merge_equal_constants`, :func:`short_value_names`: each constant once, short
  value names.
- :func:`name_constants_by_contents`, :func:`shared_weights`, :func:`point_to_shared`: the
  weights of exports at several sizes in one shared file.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import onnx

#: Initializers at least this large (bytes) go to the shared weights file of
#: :func:`deltar.export.onnx.export_onnx_sizes`; smaller ones (and every size-dependent
#: constant) stay inline.
SHARED_MIN_BYTES = 1024


def name_constants_by_contents(proto: onnx.ModelProto) -> None:
    """Rename the large initializers the exporter named by a counter (``onnx::...``, e.g.
    folded batch norms) after their contents, in place, references in branches too.

    The counter's numbers depend on how many values the trace made before, which can
    differ between input sizes; names from the contents let exports at several sizes
    share the same tensors (:func:`shared_weights`).
    """
    import hashlib

    from onnx import numpy_helper

    renames = {}
    for tensor in proto.graph.initializer:
        array = numpy_helper.to_array(tensor)
        if tensor.name.startswith("onnx::") and array.nbytes >= SHARED_MIN_BYTES:
            digest = hashlib.sha1(f"{array.dtype}{array.shape}".encode() + array.tobytes())
            renames[tensor.name] = f"constant_{digest.hexdigest()[:16]}"
    if not renames:
        return
    kept, seen = [], set()
    for tensor in proto.graph.initializer:
        tensor.name = renames.get(tensor.name, tensor.name)
        if tensor.name not in seen:  # equal contents: one tensor
            seen.add(tensor.name)
            kept.append(tensor)
    del proto.graph.initializer[:]
    proto.graph.initializer.extend(kept)

    def rename_in(graph: onnx.GraphProto) -> None:
        for node in graph.node:
            node.input[:] = [renames.get(name, name) for name in node.input]
            for attribute in node.attribute:
                if attribute.HasField("g"):
                    rename_in(attribute.g)
                for sub in attribute.graphs:
                    rename_in(sub)

    rename_in(proto.graph)


def merge_equal_constants(proto: onnx.ModelProto) -> int:
    """Replace ``Constant`` nodes that hold the same tensor, in the graph and its ``If``
    branches, by one initializer of the outer graph, in place (a branch reads outer
    values). The trace writes a constant each time the code builds one (an interpolation
    matrix read by several products, or by both branches).

    Returns:
        Number of ``Constant`` nodes removed.
    """
    import hashlib

    from onnx import numpy_helper

    graph = proto.graph
    by_contents: dict[str, str] = {}
    for tensor in graph.initializer:
        array = numpy_helper.to_array(tensor)
        by_contents.setdefault(hashlib.sha1(
            f"{array.dtype}{array.shape}".encode() + array.tobytes()).hexdigest(), tensor.name)
    removed = 0

    def merge(sub: onnx.GraphProto) -> None:
        nonlocal removed
        renames: dict[str, str] = {}
        kept = []
        for node in sub.node:
            value = next((a.t for a in node.attribute if a.name == "value"), None)
            if node.op_type == "Constant" and node.domain in ("", "ai.onnx") and \
                    value is not None and len(node.attribute) == 1:
                array = numpy_helper.to_array(value)
                key = hashlib.sha1(f"{array.dtype}{array.shape}".encode()
                                   + array.tobytes()).hexdigest()
                if key not in by_contents:
                    by_contents[key] = node.output[0]
                    graph.initializer.append(numpy_helper.from_array(array, node.output[0]))
                renames[node.output[0]] = by_contents[key]
                removed += 1
                continue
            kept.append(node)
        del sub.node[:]
        sub.node.extend(kept)
        for node in sub.node:
            node.input[:] = [renames.get(name, name) for name in node.input]
        for value in sub.output:
            if value.name in renames:  # an output must be produced in its graph
                sub.node.append(onnx.helper.make_node("Identity", [renames[value.name]],
                                                      [value.name]))
        for node in sub.node:
            for attribute in node.attribute:
                if attribute.HasField("g"):
                    merge(attribute.g)
                    # The branch may read what this graph renamed.
                    for inner in attribute.g.node:
                        inner.input[:] = [renames.get(name, name) for name in inner.input]

    merge(graph)
    return removed


def short_value_names(proto: onnx.ModelProto) -> None:
    """Name the values the graph's nodes compute with short numbers, in place (branches
    too); graph inputs, outputs, initializers and node names are kept (profiles name the
    nodes; those onnxruntime rewrites take their output's name). The tracer's names
    (module path, operator, output index), repeated at every producer and reader, were
    a third of a graph file's bytes."""
    graph = proto.graph
    kept = {v.name for v in graph.input} | {v.name for v in graph.output}
    renames: dict[str, str] = {}

    def collect(sub: onnx.GraphProto) -> None:
        for node in sub.node:
            for name in node.output:
                if name and name not in kept and name not in renames:
                    renames[name] = f"v{len(renames):x}"
            for attribute in node.attribute:
                if attribute.HasField("g"):
                    collect(attribute.g)

    def apply(sub: onnx.GraphProto) -> None:
        for node in sub.node:
            node.input[:] = [renames.get(name, name) for name in node.input]
            node.output[:] = [renames.get(name, name) for name in node.output]
            for attribute in node.attribute:
                if attribute.HasField("g"):
                    apply(attribute.g)
        for value in [*sub.output, *sub.value_info]:
            value.name = renames.get(value.name, value.name)

    collect(graph)
    apply(graph)


def shared_weights(protos: list[onnx.ModelProto]) -> tuple[bytes, dict[str, tuple[int, int]]]:
    """The large initializers of several exports of one network as one blob.

    Only those equal (same name, same contents) in every export are shared; the others
    (constants that depend on the input size, such as interpolation weights) stay in
    their own graph.

    Returns:
        The blob (each tensor's little-endian bytes, at 64-byte aligned offsets) and
        name -> (offset, length).

    Raises:
        ValueError: the exports' network weights (the module's parameters and buffers)
            differ: not one network's exports.
    """
    from onnx import numpy_helper

    def large(proto: onnx.ModelProto) -> dict[str, bytes]:
        arrays = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
        return {name: np.ascontiguousarray(a).astype(a.dtype.newbyteorder("<")).tobytes()
                for name, a in arrays.items() if a.nbytes >= SHARED_MIN_BYTES}

    tensors = large(protos[0])
    for proto in protos[1:]:
        other = large(proto)
        if any(name.startswith("inner.") and other.get(name) != data
               for name, data in tensors.items()):
            raise ValueError("the exports' weights differ: only one network's exports at "
                             "several sizes can share a weights file")
        tensors = {name: data for name, data in tensors.items() if other.get(name) == data}
    blob, where = bytearray(), {}
    for name, data in tensors.items():
        blob.extend(b"\0" * (-len(blob) % 64))
        where[name] = (len(blob), len(data))
        blob.extend(data)
    return bytes(blob), where


def point_to_shared(proto: onnx.ModelProto, where: dict[str, tuple[int, int]],
                     location: str) -> None:
    """Replace the listed initializers' data by references into the shared file, in place."""
    import onnx
    from onnx.external_data_helper import set_external_data

    for tensor in proto.graph.initializer:
        if tensor.name not in where:
            continue
        offset, length = where[tensor.name]
        if not tensor.HasField("raw_data"):  # set_external_data wants the raw form
            tensor.raw_data = b""
        set_external_data(tensor, location, offset=offset, length=length)
        for field in ("raw_data", "float_data", "int32_data", "int64_data", "double_data",
                      "uint64_data"):
            tensor.ClearField(field)
        tensor.data_location = onnx.TensorProto.EXTERNAL


def structural_keys(graph: onnx.GraphProto) -> dict[str, str]:
    """Each value's structural key: equal keys, the same computation (same graph inputs,
    initializer contents, operators and attributes), whatever the values are named."""
    import hashlib

    from onnx import numpy_helper

    keys = {value.name: "input:" + value.name for value in graph.input}
    for tensor in graph.initializer:
        array = numpy_helper.to_array(tensor)
        keys[tensor.name] = "initializer:" + hashlib.sha1(
            f"{array.dtype}{array.shape}".encode() + array.tobytes()).hexdigest()
    for node in graph.node:
        digest = hashlib.sha1("|".join([node.op_type, node.domain, *(
            keys[name] if name else "" for name in node.input)]).encode())
        for attribute in sorted(node.attribute, key=lambda a: a.name):
            digest.update(attribute.SerializeToString())
        for index, name in enumerate(node.output):
            keys[name] = f"{digest.hexdigest()}:{index}"
    return keys


def single_target_branch(with_targets: onnx.ModelProto, single: onnx.ModelProto
                          ) -> onnx.ModelProto:
    """One graph of both exports: the several-targets work only for frames that need it.

    ``with_targets`` reads ``zone_targets``; ``single`` is the same network exported
    without that input (the primary readings alone), which gives the same outputs when
    no valid zone reports a further target, in less time. The result computes what both
    share once, then an ``If`` runs ``with_targets``' own nodes when some valid zone of
    the batch reports a further target (a distance > 0 in a slot beyond the first) and
    ``single``'s own nodes otherwise. Same inputs and outputs as ``with_targets``.
    """
    import onnx
    from onnx import helper

    graph, other = with_targets.graph, single.graph
    keys, other_keys = structural_keys(graph), structural_keys(other)
    shared = set(keys.values()) & set(other_keys.values())
    by_key = {}
    for name, key in keys.items():
        by_key.setdefault(key, name)
    # What both compute goes to the outer graph, except a Transpose that only branch
    # nodes read: each branch that reads it computes it, so that onnxruntime can still
    # fuse it into the MatMul it feeds (outside a branch it runs as a copy).
    readers: dict[str, list[str]] = {}
    for node, node_keys in [(n, keys) for n in graph.node] + [(n, other_keys) for n in other.node]:
        for name in node.input:
            if name:
                readers.setdefault(node_keys[name], []).append(node_keys[node.output[0]])
    graph_outputs = {keys[v.name] for v in graph.output}
    for node in graph.node:
        key = keys[node.output[0]]
        if node.op_type == "Transpose" and key in shared and key not in graph_outputs and \
                not any(reader in shared for reader in readers.get(key, [])):
            shared = shared - {key}
    outer_nodes = [n for n in graph.node if all(keys[o] in shared for o in n.output)]
    then_nodes = [n for n in graph.node if not all(keys[o] in shared for o in n.output)]
    else_nodes = [n for n in other.node if not all(other_keys[o] in shared for o in n.output)]
    # The single branch's own values get a prefix (names are unique across a model and
    # its branches); what it shares with the outer graph reads the outer graph's names.
    prefix = "single_target/"

    def renamed(name: str) -> str:
        if not name:
            return name
        key = other_keys[name]
        return by_key[key] if key in shared else prefix + name

    branch_initializers = []
    for tensor in other.initializer:
        if other_keys[tensor.name] not in shared:
            copy = onnx.TensorProto()
            copy.CopyFrom(tensor)
            copy.name = prefix + tensor.name
            branch_initializers.append(copy)
    renamed_nodes = []
    for node in else_nodes:
        copy = onnx.NodeProto()
        copy.CopyFrom(node)
        copy.name = prefix + node.name
        copy.input[:] = [renamed(name) for name in node.input]
        copy.output[:] = [prefix + name for name in node.output]
        renamed_nodes.append(copy)

    def branch(name: str, nodes: list, outputs: list[str], initializers: list
               ) -> onnx.GraphProto:
        # Each branch output gets its own name (an Identity), as the If's outputs take
        # the graph outputs' names.
        results = []
        for value, source in zip(graph.output, outputs, strict=True):
            local = f"{name}/output/{value.name}"
            nodes = [*nodes, helper.make_node("Identity", [source], [local],
                                              name=f"{name}/{value.name}/Identity")]
            info = onnx.ValueInfoProto()
            info.CopyFrom(value)
            info.name = local
            results.append(info)
        return helper.make_graph(nodes, name, [], results, initializer=initializers)

    then_graph = branch("several_targets", then_nodes, [v.name for v in graph.output], [])
    else_graph = branch("single_target", renamed_nodes,
                        [renamed(v.name) for v in other.output], branch_initializers)
    # Some valid zone of the batch reports a further target: (B, Z, T - 1) distances > 0.
    from deltar.inference.onnx_runtime import TARGETS_INPUT

    constants = {
        "several_targets/starts": np.array([1, 0], np.int64),
        "several_targets/ends": np.array([np.iinfo(np.int64).max, 1], np.int64),
        "several_targets/axes": np.array([2, 3], np.int64),
        "several_targets/zero": np.array(0.0, np.float32),
    }
    from onnx import numpy_helper

    condition = [
        helper.make_node("Slice", [TARGETS_INPUT, "several_targets/starts",
                                   "several_targets/ends", "several_targets/axes"],
                         ["several_targets/distances"], name="several_targets/Slice"),
        helper.make_node("Greater", ["several_targets/distances", "several_targets/zero"],
                         ["several_targets/reported"], name="several_targets/Greater"),
        helper.make_node("Unsqueeze", ["zone_valid", "several_targets/unsqueeze_axes"],
                         ["several_targets/valid"], name="several_targets/Unsqueeze"),
        helper.make_node("Unsqueeze", ["several_targets/valid", "several_targets/unsqueeze_axes"],
                         ["several_targets/valid4"], name="several_targets/Unsqueeze_1"),
        helper.make_node("And", ["several_targets/reported", "several_targets/valid4"],
                         ["several_targets/present"], name="several_targets/And"),
        helper.make_node("Cast", ["several_targets/present"], ["several_targets/count"],
                         to=onnx.TensorProto.FLOAT, name="several_targets/Cast"),
        helper.make_node("ReduceMax", ["several_targets/count"], ["several_targets/any"],
                         keepdims=0, name="several_targets/ReduceMax"),
        helper.make_node("Greater", ["several_targets/any", "several_targets/zero"],
                         ["several_targets/condition"], name="several_targets/Greater_1"),
        helper.make_node("If", ["several_targets/condition"], [v.name for v in graph.output],
                         then_branch=then_graph, else_branch=else_graph,
                         name="several_targets/If"),
    ]
    constants["several_targets/unsqueeze_axes"] = np.array([-1], np.int64)
    merged = helper.make_graph(
        outer_nodes + condition, graph.name, list(graph.input), list(graph.output),
        initializer=list(graph.initializer) + [numpy_helper.from_array(v, k)
                                               for k, v in constants.items()])
    model = helper.make_model(merged, opset_imports=list(with_targets.opset_import),
                              producer_name=with_targets.producer_name,
                              producer_version=with_targets.producer_version)
    model.ir_version = with_targets.ir_version
    return model


def fold_pads_into_convs(proto: onnx.ModelProto) -> int:
    """Merge constant zero ``Pad`` nodes into the convolutions they feed, in place.

    onnxruntime (1.32) does not fuse a ``Pad`` into the following ``Conv`` by itself,
    while ``Conv`` takes asymmetric padding in its ``pads`` attribute; the pads here
    are constants (:func:`_static_same_padding`), evaluated with onnx's reference
    evaluator at the model's opset. A ``Pad`` of the main graph is merged only when its
    mode is constant with value 0, it pads no batch or channel axis, its output is not a
    graph output and every consumer is a ``Conv`` without ``auto_pad`` that reads it as
    its data input only. The arithmetic is the same: zeros outside the image either way.

    Returns:
        Number of ``Pad`` nodes removed.
    """
    import onnx
    from onnx import helper, numpy_helper
    from onnx.reference import ReferenceEvaluator

    graph = proto.graph
    producers = {out: node for node in graph.node for out in node.output}
    initializers = {init.name: init for init in graph.initializer}
    graph_inputs = {value.name for value in graph.input}
    graph_outputs = {value.name for value in graph.output}
    chains: list = []  # nodes computing the merged pads (removed when unused)

    def constant(name: str) -> np.ndarray | None:
        """The value of a tensor computed from constants only, or None."""
        if name in initializers:
            return numpy_helper.to_array(initializers[name])
        nodes, stack, seen = [], [name], set()
        while stack:
            tensor = stack.pop()
            if tensor in seen or tensor in initializers or not tensor:
                continue
            seen.add(tensor)
            node = producers.get(tensor)
            if node is None or tensor in graph_inputs:
                return None
            nodes.append(node)
            stack.extend(node.input)
        order = [n for n in graph.node if any(n is m for m in nodes)]
        used = [initializers[i] for n in order for i in n.input if i in initializers]
        sub = helper.make_graph(order, "constant", [], [helper.make_tensor_value_info(
            name, onnx.TensorProto.UNDEFINED, None)], initializer=used)
        try:
            value = ReferenceEvaluator(helper.make_model(
                sub, opset_imports=list(proto.opset_import))).run(None, {})[0]
        except Exception:  # an operator the evaluator lacks: leave this Pad alone
            return None
        chains.extend(order)
        return np.asarray(value)

    def pads_of(pad) -> np.ndarray | None:
        mode = next((a.s for a in pad.attribute if a.name == "mode"), b"constant")
        if mode != b"constant" or not 2 <= len(pad.input) <= 3:
            return None
        if len(pad.input) == 3 and pad.input[2]:
            value = constant(pad.input[2])
            if value is None or np.any(value != 0):
                return None
        pads = constant(pad.input[1])
        if pads is None or pads.shape != (8,) or np.any(pads < 0) or np.any(pads[[0, 1, 4, 5]]):
            return None
        return pads

    def plain_conv(node, tensor: str) -> bool:
        auto_pad = next((a.s for a in node.attribute if a.name == "auto_pad"), b"NOTSET")
        return (node.op_type == "Conv" and auto_pad in (b"", b"NOTSET")
                and node.input[0] == tensor and tensor not in node.input[1:])

    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    removed = []
    for pad in [n for n in graph.node if n.op_type == "Pad"]:
        users = consumers.get(pad.output[0], [])
        if not users or pad.output[0] in graph_outputs or \
                not all(plain_conv(user, pad.output[0]) for user in users):
            continue
        pads = pads_of(pad)
        if pads is None:
            continue
        for conv in users:
            attribute = next((a for a in conv.attribute if a.name == "pads"), None)
            current = list(attribute.ints) if attribute is not None else [0, 0, 0, 0]
            merged = [current[0] + int(pads[2]), current[1] + int(pads[3]),
                      current[2] + int(pads[6]), current[3] + int(pads[7])]
            if attribute is not None:
                conv.attribute.remove(attribute)
            conv.attribute.append(helper.make_attribute("pads", merged))
            conv.input[0] = pad.input[0]
        removed.append(pad)
    for pad in removed:
        graph.node.remove(pad)
    # The constant chains that fed only the removed pads (nodes with subgraphs could
    # read them too: then nothing more is removed, onnxruntime drops dead nodes anyway).
    has_subgraphs = any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
                        for node in graph.node for a in node.attribute)
    while chains and not has_subgraphs:
        needed = {name for node in graph.node for name in node.input} | graph_outputs
        dead = [n for n in chains if any(n is m for m in graph.node)
                and not any(out in needed for out in n.output)]
        if not dead:
            break
        for node in dead:
            graph.node.remove(node)
    return len(removed)
