"""Reduced-precision variants of an exported field graph (fp16 and dynamic int8) for devices.

* :func:`make_fp16_variant` — ``onnxruntime.transformers.float16`` (onnxconverter-common is not installed; onnx has no
  float16 converter of its own) with float32 inputs/outputs. The nodes that turn points into hash-grid rows and
  trilinear weights stay float32 (a float16 position, 11-bit mantissa, cannot address the cells of a 1024–2048
  level), and so do exponentials, logs, powers and square roots; the table (> 95 % of the file), the weighted sum,
  the MLPs and the shading run in float16. Three repairs of the converter's output are applied: duplicate Cast
  nodes (one per blocked consumer, same output name), float32 → float16 → float32 round trips in front of blocked
  nodes (they would round the points to 11 bits) and node order.
* :func:`make_int8_variant` — ``onnxruntime.quantization.quantize_dynamic`` (QInt8 weights, activations quantised
  at run time). Its dynamic mode handles ``MatMul`` but not ``Gemm``, which the TorchScript exporter emits for
  ``nn.Linear``: Gemm nodes with constant weights are first rewritten as MatMul + Add. ``gather=True`` also
  quantises the hash table (per-tensor int8 rows, dequantised after the ``Gather``), the only way to shrink the file.

On an x86 CPU neither variant is faster (ONNX Runtime has few float16 CPU kernels and the graph is gather-bound,
not MatMul-bound): they are for size and for accelerators; ``bench/bench_onnx.py`` measures both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit._checks import DarsError

__all__ = ["make_fp16_variant", "make_int8_variant"]


def _gemm_to_matmul(model):
    """Rewrite ``Gemm(A, B, C)`` with constant B as ``MatMul(A, B') + C`` so dynamic int8 quantisation (which
    handles MatMul, not Gemm) applies to the MLP layers."""
    import onnx
    from onnx import helper, numpy_helper

    inits = {i.name: i for i in model.graph.initializer}
    nodes = []
    for node in model.graph.node:
        if node.op_type != "Gemm" or node.input[1] not in inits:
            nodes.append(node)
            continue
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        if attrs.get("transA", 0) or attrs.get("alpha", 1.0) != 1.0 or attrs.get("beta", 1.0) != 1.0:
            nodes.append(node)
            continue
        w = numpy_helper.to_array(inits[node.input[1]])
        if attrs.get("transB", 0):
            w = w.T
        wname = node.input[1] + "_mm"
        model.graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(w), wname))
        mm_out = node.output[0] + ("_mm" if len(node.input) > 2 else "")
        nodes.append(helper.make_node("MatMul", [node.input[0], wname], [mm_out], name=(node.name or "gemm") + "_mm"))
        if len(node.input) > 2 and node.input[2]:
            nodes.append(helper.make_node("Add", [mm_out, node.input[2]], [node.output[0]],
                                          name=(node.name or "gemm") + "_add"))
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {i for n in model.graph.node for i in n.input}
    keep = [i for i in model.graph.initializer if i.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)
    onnx.checker.check_model(model)
    return model


def _encoding_nodes(model) -> list[str]:
    """Names of the nodes that turn the points into hash-grid rows and trilinear weights (the upstream cones of
    the table ``Gather``'s indices and of the weights multiplied with its rows). They stay float32 in the fp16
    variant: a float16 position (11-bit mantissa) cannot address the cells of a 1024-2048 level. The table
    itself, the weighted sum and everything after it become float16."""
    producers = {o: n for n in model.graph.node for o in n.output}
    consumers: dict[str, list] = {}
    for n in model.graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    inits = {t.name: t for t in model.graph.initializer}
    if not inits:
        return []
    table = max(inits.values(), key=lambda t: int(np.prod(t.dims)) if t.dims else 0).name
    roots = []
    for g in (n for n in model.graph.node if n.op_type == "Gather" and n.input[0] == table):
        roots.append(g.input[1])
        value, hops = g.output[0], 0
        while hops < 6:  # follow Reshape/Unsqueeze to the Mul with the weights
            nxt = consumers.get(value, [])
            if not nxt:
                break
            node = nxt[0]
            if node.op_type == "Mul":
                roots.extend(i for i in node.input if i != value)
                break
            value, hops = node.output[0], hops + 1
    keep: set[str] = set()
    stack, seen = list(roots), set()
    while stack:
        name = stack.pop()
        if name in seen or name not in producers:
            continue
        seen.add(name)
        node = producers[name]
        keep.add(node.name)
        stack.extend(node.input)
    return sorted(keep)


def _dedupe_nodes(graph) -> None:
    """Drop nodes whose outputs an identical earlier node (same op, inputs and attributes) already produces."""
    seen: dict[tuple, str] = {}
    keep = []
    produced: set[str] = set()
    for n in graph.node:
        key = (n.op_type, tuple(n.input), tuple(n.output), tuple(a.SerializeToString() for a in n.attribute))
        if any(o in produced for o in n.output):
            if key in seen:
                continue
            raise DarsError(f"graph is not in SSA form: {list(n.output)} produced twice by different nodes")
        seen[key] = n.name
        produced.update(n.output)
        keep.append(n)
    del graph.node[:]
    graph.node.extend(keep)


def _bypass_roundtrip_casts(graph) -> None:
    """Replace ``Cast(to=float32)(Cast(to=float16)(x))`` by ``x`` (x is float32 there: a graph input or a blocked
    node's output), so float32 consumers see the unrounded value; drops casts left without consumers."""
    from onnx import TensorProto, helper

    producers = {o: n for n in graph.node for o in n.output}

    def cast_to(n):
        return next((helper.get_attribute_value(a) for a in n.attribute if a.name == "to"), None)

    alias = {}
    for n in graph.node:
        if n.op_type == "Cast" and cast_to(n) == TensorProto.FLOAT:
            src = producers.get(n.input[0])
            if src is not None and src.op_type == "Cast" and cast_to(src) == TensorProto.FLOAT16:
                alias[n.output[0]] = src.input[0]
    outputs = {o.name for o in graph.output}
    for n in graph.node:
        for i, name in enumerate(n.input):
            if name in alias:
                n.input[i] = alias[name]
    while True:  # remove nodes whose outputs nobody uses any more
        used = {i for n in graph.node for i in n.input} | outputs
        dead = [n for n in graph.node if n.op_type == "Cast" and not any(o in used for o in n.output)]
        if not dead:
            break
        for n in dead:
            graph.node.remove(n)


def _toposort(graph) -> None:
    """Reorder ``graph.node`` topologically in place (stable: keeps the original order where it is valid)."""
    have = {i.name for i in graph.input} | {i.name for i in graph.initializer} | {""}
    pending = list(graph.node)
    ordered = []
    while pending:
        rest = []
        for n in pending:
            if all(i in have for i in n.input):
                ordered.append(n)
                have.update(n.output)
            else:
                rest.append(n)
        if len(rest) == len(pending):
            raise DarsError(f"graph has a cycle or undefined inputs at {[n.name for n in rest[:3]]}")
        pending = rest
    del graph.node[:]
    graph.node.extend(ordered)


def make_fp16_variant(src: Path, dst: Path) -> dict:
    """fp16 field: weights and MLP/shading math in float16, hash-grid addressing and interpolation in float32,
    float32 inputs/outputs (``onnxruntime.transformers.float16``). Returns notes."""
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = onnx.load(str(src))
    for i, n in enumerate(model.graph.node):
        if not n.name:
            n.name = f"node_{i}"
    block = sorted(set(_encoding_nodes(model)) | {n.name for n in model.graph.node if "points" in n.input})
    # numerically fragile ops stay float32: exponentials, norms and the softplus of the density
    op_block = ["Softplus", "Exp", "Log", "Pow", "Sqrt", "ReduceL2", "Acos", "Atan", "Range", "Mod"]
    m16 = convert_float_to_float16(model, keep_io_types=True, node_block_list=block, op_block_list=op_block)
    _dedupe_nodes(m16.graph)  # the converter emits one identical Cast per blocked consumer, with one output name
    _bypass_roundtrip_casts(m16.graph)  # it also feeds blocked nodes float32 -> float16 -> float32
    _toposort(m16.graph)  # ... and appends its input casts out of order
    onnx.checker.check_model(m16)
    onnx.save(m16, str(dst))
    return {"kept_float32_nodes": len(block), "kept_float32_ops": op_block}


def make_int8_variant(src: Path, dst: Path, gather: bool = False) -> dict:
    """Dynamic int8 (``onnxruntime.quantization.quantize_dynamic``): MLP weights int8 (Gemm rewritten as MatMul),
    activations quantised on the fly; the hash table too when ``gather``. Returns notes."""
    import onnx
    import tempfile

    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = _gemm_to_matmul(onnx.load(str(src)))
    ops = ["MatMul"] + (["Gather"] if gather else [])
    import logging

    root = logging.getLogger()
    level = root.level
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td) / "mm.onnx"
        onnx.save(model, str(tmp))
        root.setLevel(logging.ERROR)  # the quantiser warns about pre-processing meant for CNNs
        try:
            # reduce_range: 7-bit weights. ONNX Runtime's u8s8 MatMul on AVX2 / AVX-512 CPUs without VNNI sums
            # pairs of u8 x s8 products in int16 (VPMADDUBSW), which saturates with 8-bit weights: on such a CPU
            # (an AMD EPYC with AVX2 only, 2026-11-28) the variant fell to 34.8 dB against fp32 on the sample's
            # field. 7 bits cannot saturate; VNNI CPUs lose one bit of weight precision.
            quantize_dynamic(str(tmp), str(dst), weight_type=QuantType.QInt8, op_types_to_quantize=ops,
                             per_channel=False, reduce_range=True, extra_options={"MatMulConstBOnly": True})
        finally:
            root.setLevel(level)
    onnx.checker.check_model(onnx.load(str(dst)))
    return {"quantised_ops": ops}
