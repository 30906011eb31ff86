"""Export a trained NeHaD run to one self-contained `nehad-onnx/1` file (docs/design.md section 7).

    from nehad.export.onnx_export import export_run
    report = export_run("runs/lego", "lego.onnx")

The graph is traced with torch's TorchScript-based exporter (`dynamo=False`, fast and exact for
this fixed-size graph) from :class:`nehad.export.graph.ExportGraph`. Before anything is written,
the graph is checked (standard operators only, opset >= 17, `onnx.checker` full_check) and run
with onnxruntime at a few times including 0 and 1 against the torch model (parity 1e-5, absolute
or relative for values above 1). The file is then written atomically (a temporary file in the
same folder, renamed over the target).
"""

from __future__ import annotations

import io
import json
import math
import time as _time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nehad.model import RunInfo
from nehad.export.checks import FORMAT, MIN_OPSET, check_graph
from nehad.export.graph import (MIN_PART_ROWS, OUTPUT_NAMES, ExportGraph, closed_form_copy,
                                reference_outputs)
from nehad.runtime.images import atomic_write_bytes

PARITY_TOL = 1e-5
#: parts a runtime may deform side by side (fewer when a part would hold under MIN_PART_ROWS
#: moving Gaussians): 4 parts on 2 cores deform a 15k-Gaussian model in 6.5 ms against 8.6 for
#: the whole on onnxruntime's 2 threads (docs/performance.md, "Parts of the deformation").
DEFAULT_PARTS = 4
PARITY_TIMES = (0.0, 0.25, 0.5, 0.8, 1.0)
MAX_OPSET = 20  # the highest opset the TorchScript-based exporter writes


class ExportError(ValueError):
    """The run cannot be exported, or the exported graph failed its own checks."""


@dataclass
class ExportReport:
    path: Path
    num_gaussians: int
    sh_degree: int
    opset: int
    file_size: int
    seconds: float
    operators: dict
    parity: dict = field(default_factory=dict)  # output name -> max error over the check times
    parity_vs_fp32: dict = field(default_factory=dict)  # with fp16 weights: vs the unrounded model
    metadata: dict = field(default_factory=dict)
    num_static: int = 0  # Gaussians written pre-deformed (nehad.export.static_split)
    static_deviation: dict = field(default_factory=dict)  # their largest change over time


def parity_error(got: np.ndarray, ref: np.ndarray) -> float:
    """max |got - ref| / max(1, |ref|): absolute for values up to 1, relative above."""
    got = np.asarray(got, np.float64)
    ref = np.asarray(ref, np.float64)
    if got.shape != ref.shape:
        return math.inf
    if got.size == 0:
        return 0.0
    return float(np.max(np.abs(got - ref) / np.maximum(1.0, np.abs(ref))))


def _default_camera(data_dir: str | None):
    """cam.json dict of the first test (else val, train) camera of the run's dataset, or None."""
    if not data_dir:
        return None
    from nehad.runtime.cameras import camera_to_dict, load_view

    for split in ("test", "val", "train"):
        path = Path(data_dir) / f"transforms_{split}.json"
        if path.is_file():
            try:
                cam = load_view(path, 0)
                return camera_to_dict(cam[0] if isinstance(cam, list) else cam)
            except Exception:  # an unreadable dataset only loses the default camera
                continue
    return None


def build_metadata(model, info: RunInfo, sh_degree: int, cfg=None) -> dict[str, str]:
    from nehad import __version__

    aabb = model.field.aabb if info.aabb is None else info.aabb
    aabb = np.asarray(aabb.detach().cpu().numpy() if torch.is_tensor(aabb) else aabb, np.float64)
    md = {
        "format": FORMAT,
        "sh_degree": str(int(sh_degree)),
        "num_gaussians": str(len(model.gaussians)),
        "time_range": json.dumps([float(v) for v in info.time_range]),
        "background": json.dumps([float(v) for v in info.background]),
        "aabb": json.dumps(aabb.reshape(2, 3).tolist()),
        "extent": repr(float(model.field.extent if info.extent is None else info.extent)),
        "decoder": str(model.field.cfg.decoder),
        "nehad_version": __version__,
    }
    if cfg is not None:
        from nehad.configtools import config_hash

        md["config_hash"] = config_hash(cfg)
    cam = _default_camera(info.data_dir)
    if cam is not None:
        md["default_camera"] = json.dumps(cam)
    return md


def round_to_fp16(params) -> None:
    """Round torch parameters in place to the nearest float16 value (kept as float32), so that
    `_to_fp16_initializers` can store them exactly and the parity check compares like with like."""
    with torch.no_grad():
        for p in params:
            p.copy_(p.to(torch.float16).to(torch.float32))


def _to_fp16_initializers(proto) -> int:
    """Store each float32 initializer whose values are exactly representable in float16 as
    float16 plus a Cast back to float32 (exact). Returns the number converted."""
    import onnx
    from onnx import numpy_helper

    graph = proto.graph
    outputs = {o.name for o in graph.output}
    keep, casts, count = [], [], 0
    for init in graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT or init.name in outputs:
            keep.append(init)
            continue
        arr = numpy_helper.to_array(init)
        half = arr.astype(np.float16)
        if arr.size < 16 or not np.isfinite(half).all() or not np.array_equal(
                half.astype(np.float32), arr):
            keep.append(init)
            continue
        name16 = f"{init.name}__fp16"
        keep.append(numpy_helper.from_array(half, name16))
        casts.append(onnx.helper.make_node("Cast", [name16], [init.name], to=onnx.TensorProto.FLOAT,
                                           name=f"{init.name}__cast"))
        count += 1
    del graph.initializer[:]
    graph.initializer.extend(keep)
    nodes = list(graph.node)
    del graph.node[:]
    graph.node.extend(casts + nodes)
    return count


def _name_outputs(proto, names=OUTPUT_NAMES) -> None:
    """Give the graph outputs the names of docs/design.md section 7. An output the exporter folded into a constant
    (the SH, which do not depend on time) comes out as an initializer with a generated name: it
    is routed through an Identity node to its proper name."""
    import onnx

    for out, name in zip(proto.graph.output, names):
        if out.name != name:
            proto.graph.node.append(onnx.helper.make_node("Identity", [out.name], [name],
                                                          name=f"{name}__output"))
            out.name = name


# -- the export pipeline, shared by the one-file export (`export_model`) and the split-layer
# export (nehad.export.layers): check the request, trace, seal, check parity, write.

def check_opset(opset: int) -> None:
    if not MIN_OPSET <= int(opset) <= MAX_OPSET:
        raise ExportError(f"--opset {opset}: supported opsets are {MIN_OPSET}..{MAX_OPSET}")


def check_finite(arrays: dict) -> None:
    """Refuse a model whose parameters hold NaN or infinite values."""
    for name, value in arrays.items():
        if not torch.isfinite(value).all():
            raise ExportError(f"the model's {name} holds NaN or infinite values")


def traced_proto(graph, inputs: tuple, input_names, output_names, opset: int, *,
                 dynamic_axes=None, fp16: bool = False):
    """`graph` traced by torch.onnx (the TorchScript exporter, constants folded) as an ONNX
    ModelProto with the outputs named `output_names` (`_name_outputs`); with `fp16` the float32
    initializers that float16 holds exactly are stored as float16 (`_to_fp16_initializers`)."""
    import onnx

    buf = io.BytesIO()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(graph, inputs, buf, input_names=list(input_names),
                              output_names=list(output_names), dynamic_axes=dynamic_axes,
                              opset_version=int(opset), dynamo=False,
                              do_constant_folding=True)
    except Exception as e:
        raise ExportError(f"torch.onnx.export failed: {' '.join(str(e).split())[:400]}") from e
    proto = onnx.load_from_string(buf.getvalue())
    _name_outputs(proto, list(output_names))
    if fp16:
        _to_fp16_initializers(proto)
    return proto


def _seal_and_open(proto, md: dict[str, str], doc: str):
    """Write the metadata `md` (replacing any; `md` gets the graph's digest added), producer and
    `doc` into `proto`, run the docs/design.md section 7 graph checks (full_check) and open the serialized graph
    with onnxruntime for the parity check: (operator types, serialized bytes, session). Shared
    by the single-file and the split-layer exports."""
    import onnxruntime as ort
    from nehad import __version__
    from nehad.runtime.onnx_model import DIGEST_KEY
    from nehad.runtime.onnx_proto import graph_sha256

    md.pop(DIGEST_KEY, None)
    del proto.metadata_props[:]
    for k, v in md.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = k, v
    proto.producer_name, proto.producer_version = "nehad", __version__
    proto.doc_string = doc
    try:
        ops = check_graph(proto, full_check=True)
    except ValueError as e:
        raise ExportError(f"exported graph failed its checks: {e}") from None
    # Integrity (issue 15): the digest of the graph's bytes (operators and weights) goes into
    # the metadata, outside the graph, and every load compares it with the file
    digest = graph_sha256(proto.SerializeToString())
    entry = proto.metadata_props.add()
    entry.key, entry.value = DIGEST_KEY, digest
    data = proto.SerializeToString()
    if graph_sha256(data) != digest:
        raise ExportError("the serialized graph changed when its digest was added (protobuf "
                          "serialization is not stable here); nothing written")
    md[DIGEST_KEY] = digest
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    return ops, data, ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])


def run_layers_of(info: RunInfo, n: int):
    """The [n] layer of each Gaussian when the run was trained with LOD layers (docs/design.md section 8), else
    None (then the file has no `layer` output)."""
    if info.layer is None:
        return None
    from nehad.lod import run_layers

    try:
        return run_layers(info, n)
    except ValueError as e:
        raise ExportError(str(e)) from None


def export_model(model, info: RunInfo, out_path, *, opset: int = MIN_OPSET, fp16_weights: bool = False,
                 cfg=None, sh_degree: int | None = None, times=PARITY_TIMES,
                 tol: float = PARITY_TOL, static: bool = True,
                 parts: int = DEFAULT_PARTS, min_part_rows: int = MIN_PART_ROWS) -> ExportReport:
    """Export `model` (a NeHaDModel) with what its run records
    (`info`, as returned by load_run) to
    `out_path`. Raises ExportError (nothing written) when a check fails. `static`: Gaussians that
    do not move are written pre-deformed and skip the field (nehad.export.static_split); the
    parity check holds the graph to the model with those rows frozen, and the report's
    `static_deviation` says how far the frozen rows are from the model at any sampled time.
    `parts`: the rows cut into up to this many parts that a runtime deforms side by side
    (`nehad.export.graph.part_bounds`; metadata `parts`, docs/design.md section 7)."""
    start = _time.perf_counter()
    out_path = Path(out_path)
    check_opset(opset)
    if not out_path.parent.is_dir():
        raise ExportError(f"{out_path}: output folder {out_path.parent} does not exist")
    from nehad.runtime.tempfiles import remove_stale_temps

    remove_stale_temps(out_path.parent, out_path.name)  # what a killed export left (issue 15)
    if sh_degree is None:
        sh_degree = info.degree_for(model)
    work = closed_form_copy(model)
    if fp16_weights:
        round_to_fp16(work.parameters())
    layer = run_layers_of(info, len(model.gaussians))
    split = None
    if static:
        from nehad.export.static_split import find_static

        canonical = float(getattr(getattr(cfg, "train", None), "canonical_time", 0.5))
        split = find_static(work, sh_degree, canonical_time=canonical)
    graph = ExportGraph(work, sh_degree, layer, static=split, parts=parts,
                        min_part_rows=min_part_rows).eval()
    names_out = graph.output_names
    check_finite({name: getattr(work.gaussians, name) for name in
                  ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")})
    proto = traced_proto(graph, (torch.tensor([0.5], dtype=torch.float32),), ["time"], names_out,
                         opset, fp16=fp16_weights)
    md = build_metadata(model, info, sh_degree, cfg)
    md["fp16_weights"] = "1" if fp16_weights else "0"
    if split is not None and split.num_static:
        md["static_gaussians"] = str(split.num_static)
    if graph.parts > 1:  # docs/design.md section 7: the row bounds of the part outputs
        md["parts"] = json.dumps(graph.bounds)
    if layer is not None:  # docs/design.md section 8: Gaussians per layer, layer 0 first
        md["lod_layers"] = json.dumps(np.bincount(layer, minlength=int(layer.max()) + 1
                                                  if len(layer) else 1).tolist())
    # Parity against the torch model before writing.
    ops, data, sess = _seal_and_open(
        proto, md, "NeHaD dynamic 3D Gaussians (nehad-onnx/1): time [1] -> activated Gaussians")
    names = [o.name for o in sess.get_outputs()]
    if names != list(names_out):
        raise ExportError(f"exported graph outputs {names}, expected {list(names_out)}")
    original = closed_form_copy(model) if fp16_weights else None
    parity = {n: 0.0 for n in names_out}
    vs32 = {n: 0.0 for n in names_out}
    def reference(m, t):
        ref = reference_outputs(m, t, sh_degree, layer)
        return ref if split is None else split.apply(ref[:5]) + ref[5:]

    own = len(graph.part_names)
    whole = len(names_out) - (graph.parts * own if graph.parts > 1 else 0)
    for t in times:
        got = sess.run(None, {"time": np.array([t], np.float32)})
        for j in range(whole, len(got)):  # each part output: rows of its whole output
            p, i = divmod(j - whole, own)
            a, b = graph.bounds[p], graph.bounds[p + 1]
            if not np.array_equal(got[j], got[i][a:b]):
                raise ExportError(f"exported graph: output {names_out[j]} is not rows {a}:{b} "
                                  f"of {names_out[i]}")
        for n, a, b in zip(names_out, got, reference(work, t)):
            if not np.isfinite(a).all():
                raise ExportError(f"exported graph: output {n} at time {t} holds NaN/inf")
            parity[n] = max(parity[n], parity_error(a, b))
        if original is not None:
            for n, a, b in zip(names_out, got, reference(original, t)):
                vs32[n] = max(vs32[n], parity_error(a, b))
    worst = max(parity.values())
    if not worst <= tol:
        raise ExportError(f"exported graph does not match the torch model: max error "
                          f"{worst:.3g} > {tol:g} ({parity})")

    atomic_write_bytes(out_path, data, ExportError)
    return ExportReport(out_path, len(model.gaussians), int(sh_degree), int(opset), len(data),
                        _time.perf_counter() - start, dict(ops), parity,
                        vs32 if fp16_weights else {}, md,
                        0 if split is None else split.num_static,
                        {} if split is None else split.deviation)


def export_run(run_dir, out_path, *, opset: int = MIN_OPSET, fp16_weights: bool = False,
               **kw) -> ExportReport:
    """Export RUN/model.pt (see :func:`export_model`)."""
    from nehad.model import load_run

    run = Path(run_dir)
    if not (run / "model.pt").is_file():
        raise ExportError(f"{run}: not a finished training run (no model.pt)")
    model, info = load_run(run)
    return export_model(model, info, out_path, opset=opset, fp16_weights=fp16_weights,
                        cfg=info.config,
                        **kw)


__all__ = ["ExportError", "ExportReport", "MAX_OPSET", "PARITY_TOL", "export_model", "export_run",
           "parity_error"]
