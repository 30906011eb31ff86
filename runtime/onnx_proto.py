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


__all__ = ["ModelSummary", "ProtoError", "graph_sha256", "summarize"]
