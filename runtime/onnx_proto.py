"""A minimal reader of the ONNX protobuf wire format: what `nehad info` and the model validator
need (opsets, operator types, metadata, producer) without the `onnx` package or torch.

Only the few ModelProto / GraphProto / NodeProto fields listed below are decoded; everything
else (initializer data, attributes) is skipped by length. A truncated or non-protobuf file raises
:class:`ProtoError`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from .errors import InputProblem


class ProtoError(InputProblem):
    """The bytes are not a well-formed protobuf message."""


# ModelProto
_M_IR_VERSION, _M_PRODUCER, _M_PRODUCER_VERSION, _M_GRAPH, _M_OPSET, _M_METADATA = 1, 2, 3, 7, 8, 14
# GraphProto
_G_NODE, _G_INITIALIZER, _G_INPUT, _G_OUTPUT = 1, 5, 11, 12
# NodeProto
_N_OP_TYPE, _N_DOMAIN = 4, 7


def _varint(buf, pos: int, end: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= end:
            raise ProtoError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 70:
            raise ProtoError("varint too long")


def _fields(buf, start: int = 0, end: int | None = None):
    """Yield (field number, wire type, value) where value is an int (varint/fixed) or a
    (start, end) slice for length-delimited fields."""
    end = len(buf) if end is None else end
    pos = start
    while pos < end:
        key, pos = _varint(buf, pos, end)
        num, wt = key >> 3, key & 7
        if num == 0:
            raise ProtoError("field number 0")
        if wt == 0:
            value, pos = _varint(buf, pos, end)
        elif wt == 1:
            if pos + 8 > end:
                raise ProtoError("truncated fixed64")
            value, pos = int.from_bytes(buf[pos:pos + 8], "little"), pos + 8
        elif wt == 5:
            if pos + 4 > end:
                raise ProtoError("truncated fixed32")
            value, pos = int.from_bytes(buf[pos:pos + 4], "little"), pos + 4
        elif wt == 2:
            n, pos = _varint(buf, pos, end)
            if pos + n > end:
                raise ProtoError("truncated length-delimited field")
            value, pos = (pos, pos + n), pos + n
        else:
            raise ProtoError(f"unsupported wire type {wt}")
        yield num, wt, value


def _text(buf, span) -> str:
    try:
        return bytes(buf[span[0]:span[1]]).decode("utf-8")
    except UnicodeDecodeError:
        raise ProtoError("invalid UTF-8 string") from None


@dataclass
class ModelSummary:
    ir_version: int = 0
    producer: str = ""
    producer_version: str = ""
    opsets: dict = field(default_factory=dict)  # domain -> version
    metadata: dict = field(default_factory=dict)
    operators: Counter = field(default_factory=Counter)  # op_type (domain::op_type if custom)
    domains: set = field(default_factory=set)
    num_initializers: int = 0
    inputs: list = field(default_factory=list)
    outputs: list = field(default_factory=list)
    has_graph: bool = False
    graph_spans: list = field(default_factory=list)  # (start, end) of each graph field's bytes


def _name_of_value_info(buf, span) -> str:
    for num, wt, v in _fields(buf, *span):
        if num == 1 and wt == 2:
            return _text(buf, v)
    return ""


def summarize(data: bytes) -> ModelSummary:
    """Decode the summary fields of a serialized ModelProto."""
    buf = memoryview(data)
    s = ModelSummary()
    for num, wt, v in _fields(buf):
        if num == _M_IR_VERSION and wt == 0:
            s.ir_version = v
        elif num == _M_PRODUCER and wt == 2:
            s.producer = _text(buf, v)
        elif num == _M_PRODUCER_VERSION and wt == 2:
            s.producer_version = _text(buf, v)
        elif num == _M_OPSET and wt == 2:
            domain, version = "", 0
            for n2, w2, v2 in _fields(buf, *v):
                if n2 == 1 and w2 == 2:
                    domain = _text(buf, v2)
                elif n2 == 2 and w2 == 0:
                    version = v2
            s.opsets[domain] = version
        elif num == _M_METADATA and wt == 2:
            key = value = ""
            for n2, w2, v2 in _fields(buf, *v):
                if n2 == 1 and w2 == 2:
                    key = _text(buf, v2)
                elif n2 == 2 and w2 == 2:
                    value = _text(buf, v2)
            s.metadata[key] = value
        elif num == _M_GRAPH and wt == 2:
            s.has_graph = True
            s.graph_spans.append(v)
            for n2, w2, v2 in _fields(buf, *v):
                if w2 != 2:
                    continue
                if n2 == _G_NODE:
                    op, domain = "", ""
                    for n3, w3, v3 in _fields(buf, *v2):
                        if n3 == _N_OP_TYPE and w3 == 2:
                            op = _text(buf, v3)
                        elif n3 == _N_DOMAIN and w3 == 2:
                            domain = _text(buf, v3)
                    s.domains.add(domain)
                    s.operators[op if domain in ("", "ai.onnx") else f"{domain}::{op}"] += 1
                elif n2 == _G_INITIALIZER:
                    s.num_initializers += 1
                elif n2 == _G_INPUT:
                    s.inputs.append(_name_of_value_info(buf, v2))
                elif n2 == _G_OUTPUT:
                    s.outputs.append(_name_of_value_info(buf, v2))
    return s


def graph_sha256(data, spans=None) -> str:
    """SHA-256 (hex) of the serialized graph of a ModelProto: its operators, initializers
    (weights) and inputs/outputs, exactly as the bytes in the file. The metadata lives outside
    the graph, so a file can carry this digest of itself (`graph_sha256`, issue 15). `spans`:
    the summary's `graph_spans` when the bytes were summarized already."""
    import hashlib

    buf = memoryview(data)
    if spans is None:
        spans = [v for num, wt, v in _fields(buf) if num == _M_GRAPH and wt == 2]
    h = hashlib.sha256()
    for start, end in spans:
        h.update(buf[start:end])
    return h.hexdigest()


__all__ = ["ModelSummary", "ProtoError", "graph_for_outputs", "graph_sha256", "inputs_read",
           "summarize"]


# -- one edit: initializers as graph inputs ----------------------------------------------------

# TensorProto
_T_DIMS, _T_DATA_TYPE, _T_NAME = 1, 2, 8


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        b = value & 0x7F
        value >>= 7
        if value:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _field(num: int, payload: bytes) -> bytes:
    """A length-delimited field."""
    return _encode_varint(num << 3 | 2) + _encode_varint(len(payload)) + payload


def _tensor_header(buf, span) -> tuple[str, int, list[int]]:
    """(name, data type, dims) of a TensorProto."""
    name, dtype, dims = "", 0, []
    for num, wt, v in _fields(buf, *span):
        if num == _T_NAME and wt == 2:
            name = _text(buf, v)
        elif num == _T_DATA_TYPE and wt == 0:
            dtype = v
        elif num == _T_DIMS and wt == 0:
            dims.append(v)
        elif num == _T_DIMS and wt == 2:  # packed
            pos = v[0]
            while pos < v[1]:
                d, pos = _varint(buf, pos, v[1])
                dims.append(d)
    return name, dtype, dims


def _input_value_info(name: str, dtype: int, dims: list[int], first_dim: str) -> bytes:
    """ValueInfoProto of a tensor input whose first axis is named `first_dim` (any length)."""
    shape = b"".join(_field(1, _field(2, first_dim.encode()) if i == 0
                            else _encode_varint(1 << 3) + _encode_varint(d))
                     for i, d in enumerate(dims))
    tensor_type = _encode_varint(1 << 3) + _encode_varint(dtype) + _field(2, shape)
    return _field(1, name.encode()) + _field(2, _field(1, tensor_type))


def initializers_as_inputs(data: bytes, names, first_dim: str = "extra") -> bytes:
    """The model `data` with the initializers named in `names` turned into plain graph inputs
    (onnxruntime-web feeds graph inputs only, not overridable initializers): each initializer is
    dropped, and where the graph does not list it as an input already, an input of its type and
    shape is added, its first axis of any length. Every other byte of the model is kept."""
    names = set(names)
    buf = memoryview(data)
    rest, graph_fields = bytearray(), []
    for num, wt, v in _fields(buf):
        if num == _M_GRAPH and wt == 2:
            graph_fields.append(v)
        else:
            rest += _raw_field(buf, num, wt, v)
    out, found = bytearray(), set()
    for span in graph_fields:
        listed = {_name_of_value_info(buf, gv) for gnum, gwt, gv in _fields(buf, *span)
                  if gnum == _G_INPUT and gwt == 2}
        graph, inputs = bytearray(), []
        for gnum, gwt, gv in _fields(buf, *span):
            if gnum == _G_INITIALIZER and gwt == 2:
                name, dtype, dims = _tensor_header(buf, gv)
                if name in names:
                    found.add(name)
                    if name not in listed:
                        inputs.append(_field(_G_INPUT, _input_value_info(name, dtype, dims,
                                                                         first_dim)))
                    continue
            graph += _raw_field(buf, gnum, gwt, gv)
        out += _field(_M_GRAPH, bytes(graph) + b"".join(inputs))
    missing = names - found
    if missing:
        raise ProtoError(f"the model has no initializers {sorted(missing)}")
    return bytes(rest + out)


def _raw_field(buf, num: int, wt: int, value) -> bytes:
    """A decoded field written back as it was."""
    key = _encode_varint(num << 3 | wt)
    if wt == 0:
        return key + _encode_varint(value)
    if wt == 1:
        return key + value.to_bytes(8, "little")
    if wt == 5:
        return key + value.to_bytes(4, "little")
    return key + _encode_varint(value[1] - value[0]) + bytes(buf[value[0]:value[1]])


# -- one edit: the graph that computes some of the outputs ---------------------------------------

# NodeProto and AttributeProto
_N_INPUT, _N_OUTPUT, _N_ATTRIBUTE = 1, 2, 5
_A_GRAPH, _A_GRAPHS = 6, 11


def _node_io(buf, span) -> tuple[list[str], list[str]]:
    """(inputs, outputs) of a NodeProto; a node that holds a subgraph raises ProtoError (its
    outer-scope inputs are not listed among its inputs)."""
    inputs, outputs = [], []
    for num, wt, v in _fields(buf, *span):
        if num == _N_INPUT and wt == 2:
            inputs.append(_text(buf, v))
        elif num == _N_OUTPUT and wt == 2:
            outputs.append(_text(buf, v))
        elif num == _N_ATTRIBUTE and wt == 2:
            if any(n in (_A_GRAPH, _A_GRAPHS) for n, _, _ in _fields(buf, *v)):
                raise ProtoError("a node holds a subgraph")
    return inputs, outputs


def _graph_of(data: bytes):
    """(the model's other fields as bytes, the graph's fields, {value: (node index, inputs)})."""
    buf = memoryview(data)
    rest, graph = bytearray(), []
    for num, wt, v in _fields(buf):
        if num == _M_GRAPH and wt == 2:
            graph += [(gnum, gwt, gv) for gnum, gwt, gv in _fields(buf, *v)]
        else:
            rest += _raw_field(buf, num, wt, v)
    producer = {}
    for i, (gnum, gwt, gv) in enumerate(graph):
        if gnum == _G_NODE and gwt == 2:
            ins, outs = _node_io(buf, gv)
            producer.update((out, (i, ins)) for out in outs)
    return buf, rest, graph, producer


def _reach(buf, graph, producer, names) -> tuple[set, set]:
    """(indices of the nodes the values `names` depend on, every value name they read)."""
    outputs = {_name_of_value_info(buf, gv) for gnum, gwt, gv in graph
               if gnum == _G_OUTPUT and gwt == 2}
    missing = sorted(set(names) - outputs)
    if missing:
        raise ProtoError(f"the model has no outputs {missing}")
    keep, used, stack = set(), set(names), list(names)
    while stack:
        hit = producer.get(stack.pop())
        if hit is None or hit[0] in keep:
            continue
        keep.add(hit[0])
        for name in hit[1]:
            if name and name not in used:
                used.add(name)
                stack.append(name)
    return keep, used


def inputs_read(data: bytes, names) -> set[str]:
    """The graph inputs that the outputs `names` depend on (an output read from initializers
    only reads none: a constant)."""
    buf, _, graph, producer = _graph_of(data)
    _, used = _reach(buf, graph, producer, list(names))
    inputs = {_name_of_value_info(buf, gv) for gnum, gwt, gv in graph
              if gnum == _G_INPUT and gwt == 2}
    inits = {_tensor_header(buf, gv)[0] for gnum, gwt, gv in graph
             if gnum == _G_INITIALIZER and gwt == 2}
    return (inputs - inits) & used


def graph_for_outputs(data: bytes, names) -> bytes:
    """The model `data` with only the outputs `names` and what computes them: the nodes they
    depend on, the initializers those read and the graph inputs still read (onnxruntime runs
    every node of a graph, whatever outputs a run asks for). Every kept field keeps its bytes."""
    names = list(names)
    buf, rest, graph, producer = _graph_of(data)
    keep, used = _reach(buf, graph, producer, names)
    inits = {_tensor_header(buf, gv)[0] for gnum, gwt, gv in graph
             if gnum == _G_INITIALIZER and gwt == 2}
    parts = [bytes(rest)]
    for i, (gnum, gwt, gv) in enumerate(graph):
        if gwt == 2 and (
                (gnum == _G_NODE and i not in keep)
                or (gnum == _G_OUTPUT and _name_of_value_info(buf, gv) not in names)
                or (gnum == _G_INITIALIZER and _tensor_header(buf, gv)[0] not in used)
                or (gnum == _G_INPUT and _name_of_value_info(buf, gv) in inits - used)):
            continue
        parts.append(_raw_field(buf, gnum, gwt, gv))
    body = parts[1:]
    return b"".join([parts[0], _encode_varint(_M_GRAPH << 3 | 2),
                     _encode_varint(sum(len(b) for b in body))] + body)
