"""Checks of an exported `nehad-onnx/1` graph (docs/design.md section 7): standard operators only, opset, checker.

Only needs the `onnx` package (no torch), so the tests and `nehad export` share it.
"""

from __future__ import annotations

from collections import Counter

FORMAT = "nehad-onnx/1"
MIN_OPSET = 17

#: Standard ai.onnx operators an exported NeHaD graph may use: arithmetic, elementwise math,
#: tensor shuffling, comparisons/selection, reductions, MatMul/Gemm and GridSample (the hex-plane).
#: No control flow, no random ops, nothing from ai.onnx.preview.training (Gradient, Adam, ...),
#: no custom domains.
ALLOWED_OPS = frozenset("""
Abs Acos Add And Asin Atan Cast Ceil Clip Concat Constant ConstantOfShape Cos Div Einsum Equal
Erf Exp Expand Flatten Floor Gather GatherElements Gemm Greater GreaterOrEqual GridSample
Identity IsInf IsNaN Less LessOrEqual Log MatMul Max Min Mod Mul Neg Not Or Pow Range Reciprocal
ReduceL2 ReduceMax ReduceMean ReduceMin ReduceProd ReduceSum ReduceSumSquare Relu Reshape
Shape Sigmoid Sign Sin Size Slice Softplus Split Sqrt Squeeze Sub Sum Tanh Tile Transpose
Unsqueeze Where Xor
""".split())

STANDARD_DOMAINS = ("", "ai.onnx")


class GraphCheckError(ValueError):
    """An exported graph breaks a rule of docs/design.md section 7 (the message says which)."""


def operator_counts(model) -> Counter:
    """Counter of "op_type" (domain-qualified when not ai.onnx) over the main graph's nodes."""
    c = Counter()
    for n in model.graph.node:
        c[n.op_type if n.domain in STANDARD_DOMAINS else f"{n.domain}::{n.op_type}"] += 1
    return c


def opset_of(model) -> int:
    for imp in model.opset_import:
        if imp.domain in STANDARD_DOMAINS:
            return int(imp.version)
    return 0


def check_graph(model, full_check: bool = True) -> Counter:
    """Raise GraphCheckError unless `model` (an onnx.ModelProto) uses only whitelisted standard
    operators, imports only the standard domain at opset >= 17, has no subgraphs, and passes
    `onnx.checker.check_model(full_check=...)`. Returns the operator counts."""
    import onnx

    others = [imp.domain for imp in model.opset_import if imp.domain not in STANDARD_DOMAINS]
    if others:
        raise GraphCheckError(f"graph imports non-standard domains {others}")
    opset = opset_of(model)
    if opset < MIN_OPSET:
        raise GraphCheckError(f"graph opset {opset} < {MIN_OPSET}")
    bad = sorted({f"{n.domain}::{n.op_type}" if n.domain not in STANDARD_DOMAINS else n.op_type
                  for n in model.graph.node
                  if n.domain not in STANDARD_DOMAINS or n.op_type not in ALLOWED_OPS})
    if bad:
        raise GraphCheckError(f"graph uses operators outside the standard whitelist: {bad}")
    for n in model.graph.node:
        if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
               for a in n.attribute):
            raise GraphCheckError(f"node {n.name or n.op_type} holds a subgraph")
    try:
        onnx.checker.check_model(model, full_check=full_check)
    except Exception as e:  # onnx.checker.ValidationError, shape inference errors
        raise GraphCheckError(f"onnx.checker: {' '.join(str(e).split())[:500]}") from None
    return operator_counts(model)


__all__ = ["ALLOWED_OPS", "FORMAT", "GraphCheckError", "MIN_OPSET", "check_graph", "opset_of",
           "operator_counts"]
