"""`nehad export RUN --split-layers DIR`: a layered run (docs/design.md section 8, nehad.lod) as a base model plus
one chunk per enhancement layer and a manifest, for streaming (format: nehad.runtime.layers and
docs/streaming.md).

The base graph (`SplitBaseGraph`) holds the field and layer 0's canonical Gaussians as
initializers and takes the enhancement layers' canonical Gaussians as optional inputs whose
defaults are empty; it appends them to layer 0's and deforms all of them with
`nehad.export.deform_graph.FastDeform` (the function of `NeHaDModel.gaussians_at` arranged for
onnxruntime; the means are graph inputs here, so the spatial planes are sampled in every run).
Before anything is written, the graph passes the docs/design.md section 7 checks and is run with onnxruntime with
no extra inputs and with every prefix of layers, against the torch model's outputs for the same
Gaussians (1e-5).
"""

from __future__ import annotations

import json
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nehad.model import RunInfo
from nehad.export.checks import MIN_OPSET
from nehad.export.deform_graph import FastDeform
from nehad.export.graph import LAYER_OUTPUT, OUTPUT_NAMES, closed_form_copy
from nehad.export.onnx_export import (PARITY_TIMES, PARITY_TOL, ExportError, _seal_and_open,
                                      build_metadata, check_finite, check_opset, parity_error,
                                      round_to_fp16, run_layers_of, traced_proto)
from nehad.runtime.layers import (BASE_FILE, CHUNK_ARRAYS, EXTRA_LAYER, EXTRA_PREFIX, MANIFEST,
                                  MANIFEST_FORMAT, atomic_write, chunk_file_name, encode_chunk,
                                  sha256_of)

INPUT_NAMES = ("time",) + tuple(EXTRA_PREFIX + n for n in CHUNK_ARRAYS) + (EXTRA_LAYER,)


def canonical_arrays(model, sh_coeffs: int, rows=slice(None)) -> dict[str, torch.Tensor]:
    """The canonical Gaussians' raw arrays (chunk layout) of `model`'s rows `rows`."""
    g = model.gaussians
    sh = torch.cat([g.sh_dc, g.sh_rest], 1)[:, :sh_coeffs]
    return {"means": g.means[rows], "log_scales": g.log_scales[rows], "quats": g.quats[rows],
            "opacity_logits": g.opacity_logits[rows].reshape(-1), "sh": sh[rows],
            "mu_eq": g.mu_eq[rows], "t_eq": g.t_eq[rows].reshape(-1, 1)}


class SplitBaseGraph(nn.Module):
    """forward(time [1], extra_means [M,3], ..., extra_layer [M]) -> the docs/design.md section 7 outputs and
    `layer` for layer 0's Gaussians followed by the M extra ones."""

    def __init__(self, model, sh_degree: int, n0: int):
        super().__init__()
        g = model.gaussians
        if g.drift_window > 0:
            raise ExportError("the split-layer export does not carry a drift window "
                              "(train.drift_window > 0: every Gaussian drifts); export the run as "
                              "one file instead")
        self.model = model
        self.deform = FastDeform(model, sh_degree, constant_means=False)
        self.k = (int(sh_degree) + 1) ** 2
        with torch.no_grad():
            base = canonical_arrays(model, self.k, slice(0, n0))
            # carving's finite lives and velocities (nehad.carve_pass) belong to layer 0: its
            # passes never run in a layer above the base, so a chunk's Gaussians live at every
            # time and stand still after the field (life rate 0, velocity 0)
            if bool((g.life_rate[n0:] != 0).any()):
                raise ExportError("the split-layer export carries finite lives in layer 0 only; "
                                  "an enhancement layer has Gaussians with one")
            self.mortal = g.has_life()
        for name, value in base.items():
            self.register_buffer(f"base_{name}", value.detach().clone())
        if self.mortal:
            self.register_buffer("base_life_rate", g.life_rate[:n0].detach().reshape(-1, 1).clone())
            self.register_buffer("base_velocity", g.drift_velocity()[:n0].detach().clone())
        self.register_buffer("base_layer", torch.zeros(n0, dtype=torch.int32))

    def forward(self, time, means, log_scales, quats, opacity_logits, sh, mu_eq, t_eq, layer):
        extra = dict(zip(CHUNK_ARRAYS, (means, log_scales, quats, opacity_logits, sh, mu_eq,
                                        t_eq)))
        arrays = {n: torch.cat([getattr(self, f"base_{n}"), extra[n]], 0) for n in CHUNK_ARRAYS}
        drift = ()
        if self.mortal:  # the chunks' rows: life rate 0 (every time), velocity 0
            still = torch.zeros_like(means)
            drift = (torch.cat([self.base_life_rate, still[:, :1]], 0),
                     torch.cat([self.base_velocity, still], 0))
        out = self.deform(*(arrays[n] for n in CHUNK_ARRAYS), time, *drift)
        return out + (torch.cat([self.base_layer, layer]),)


@dataclass
class SplitReport:
    folder: Path
    manifest: dict
    parity: dict = field(default_factory=dict)  # output -> worst error over times and prefixes
    seconds: float = 0.0


def _empty_initializers(proto, shapes: dict) -> None:
    """Give each extra_* input an empty default of its own name (an overridable initializer).
    An input the field does not read (mu_eq and t_eq without BED or carving) was dropped by the
    exporter; it is declared again, unused, so every base graph takes the same chunk feeds
    (runtime/layers.py)."""
    from onnx import helper, numpy_helper

    inputs = {x.name for x in proto.graph.input}
    for name, (tail, dtype) in shapes.items():
        if name not in inputs:
            proto.graph.input.append(helper.make_tensor_value_info(
                name, helper.np_dtype_to_tensor_dtype(np.dtype(dtype)), ["extra_rows", *tail]))
        proto.graph.initializer.append(numpy_helper.from_array(np.zeros((0, *tail), dtype), name))


def export_split_layers(run_dir, out_dir, *, opset: int = MIN_OPSET, fp16_field: bool = False,
                        times=PARITY_TIMES, tol: float = PARITY_TOL) -> SplitReport:
    """Write base.onnx, layer_1.bin, ... and manifest.json for the layered RUN into `out_dir`
    (created; existing files of those names are replaced). Raises ExportError, writing nothing,
    when the run has no layers or a check fails."""
    from nehad.model import load_run

    run = Path(run_dir)
    if not (run / "model.pt").is_file():
        raise ExportError(f"{run}: not a finished training run (no model.pt)")
    model, info = load_run(run)
    if info.layer is None:
        raise ExportError(f"{run}: the run has no streaming layers (train it with --lod-levels L)")
    return export_split_model(model, info, out_dir, cfg=info.config, opset=opset, fp16_field=fp16_field,
                              times=times, tol=tol)


def export_split_model(model, info: RunInfo, out_dir, *, cfg=None, opset: int = MIN_OPSET,
                       fp16_field: bool = False, times=PARITY_TIMES,
                       tol: float = PARITY_TOL) -> SplitReport:
    """`export_split_layers` for a loaded model and what its run records (`info.layer`:
    the [N] layer of each Gaussian, nondecreasing).

    `fp16_field`: store the deformation field's weights (hex-plane and networks) as float16 in
    base.onnx, halving the part of the first download that does not shrink with the layers; the
    Gaussians (layer 0 and the chunks) stay float32. The parity check then compares against the
    model with its field rounded the same way."""
    start = _time.perf_counter()
    out_dir = Path(out_dir)
    check_opset(opset)
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"--split-layers {out_dir}: exists and is not a folder")
    if not out_dir.parent.is_dir():
        raise ExportError(f"--split-layers {out_dir}: parent folder {out_dir.parent} does not exist")
    n = len(model.gaussians)
    layer = run_layers_of(info, n)
    if layer is None:
        raise ExportError("the model has no streaming layers (train it with --lod-levels L)")
    if np.any(np.diff(layer) < 0):
        raise ExportError("the model's streaming layers are not stored in order (layer 0 "
                          "first, then 1, ...); a run trained with --lod-levels stores them so")
    sizes = np.bincount(layer, minlength=int(layer.max()) + 1).tolist()
    sh_degree = info.degree_for(model)
    k = (sh_degree + 1) ** 2
    work = closed_form_copy(model)
    if fp16_field:
        round_to_fp16(work.field.parameters())
    graph = SplitBaseGraph(work, sh_degree, sizes[0]).eval()
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    with torch.no_grad():
        full = canonical_arrays(work, k)
    check_finite(full)
    chunk_arrays = [{nm: full[nm][offsets[j]:offsets[j + 1]].detach() for nm in CHUNK_ARRAYS}
                    for j in range(len(sizes))]

    # trace with the enhancement layers as the example inputs (or one row of layer 0's)
    example = ({nm: torch.cat([c[nm] for c in chunk_arrays[1:]], 0) for nm in CHUNK_ARRAYS}
               if len(sizes) > 1 and sum(sizes[1:]) > 0
               else {nm: full[nm][:1].detach() for nm in CHUNK_ARRAYS})
    m = example["means"].shape[0]
    ex_inputs = (torch.tensor([0.5], dtype=torch.float32), *(example[nm] for nm in CHUNK_ARRAYS),
                 torch.ones(m, dtype=torch.int32))
    out_names = list(OUTPUT_NAMES) + [LAYER_OUTPUT]
    dyn = {nm: {0: "extra"} for nm in INPUT_NAMES[1:]}
    dyn.update({nm: {0: "gaussians"} for nm in out_names})
    # with fp16_field only the rounded field is exactly representable: the Gaussians stay float32
    proto = traced_proto(graph, ex_inputs, INPUT_NAMES, out_names, opset, dynamic_axes=dyn,
                         fp16=fp16_field)
    tails = {"means": (3,), "log_scales": (3,), "quats": (4,), "opacity_logits": (),
             "sh": (k, 3), "mu_eq": (3,), "t_eq": (1,)}
    _empty_initializers(proto, {**{EXTRA_PREFIX + nm: (tails[nm], np.float32)
                                   for nm in CHUNK_ARRAYS}, EXTRA_LAYER: ((), np.int32)})
    md = build_metadata(model, info, sh_degree, cfg)
    md["num_gaussians"] = str(sizes[0])
    md["fp16_weights"] = "field" if fp16_field else "0"
    md["lod_layers"] = json.dumps(sizes)
    md["lod_split"] = "1"
    # parity: every prefix of layers, at every check time, against the full torch model
    _, data, sess = _seal_and_open(
        proto, md, "NeHaD dynamic 3D Gaussians (nehad-onnx/1), streaming base: field + layer 0; "
        "optional inputs extra_* append enhancement layers")
    parity = _split_parity(sess, work, chunk_arrays, layer, sizes, out_names, k, times)
    worst = max(parity.values())
    if not worst <= tol:
        raise ExportError(f"base graph does not match the torch model: max error {worst:.3g} > "
                          f"{tol:g} ({parity})")
    manifest = _write_split(out_dir, data, chunk_arrays, sizes, sh_degree, md, info)
    return SplitReport(out_dir, manifest, parity, _time.perf_counter() - start)


def _split_parity(sess, work, chunk_arrays, layer, sizes, out_names, k: int, times) -> dict:
    """The largest parity error of each output: every prefix of layers, at every check time,
    against the full torch model."""
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    parity = {nm: 0.0 for nm in out_names}
    layer_np = layer.astype(np.int32)
    for t in times:
        with torch.no_grad():
            ref = [o.detach().numpy() for o in work.gaussians_at(torch.tensor([t]))]
        ref[4] = ref[4][:, :k]
        ref.append(layer_np)
        for j in range(len(sizes)):
            feeds = {"time": np.array([t], np.float32)}
            if j > 0:
                for nm in CHUNK_ARRAYS:
                    feeds[EXTRA_PREFIX + nm] = np.concatenate(
                        [c[nm].numpy() for c in chunk_arrays[1:j + 1]], 0)
                feeds[EXTRA_LAYER] = layer_np[sizes[0]:offsets[j + 1]]
            got = sess.run(None, feeds)
            end = offsets[j + 1]
            for nm, a, b in zip(out_names, got, ref):
                if not np.isfinite(a).all():
                    raise ExportError(f"base graph: output {nm} at time {t} holds NaN/inf")
                parity[nm] = max(parity[nm], parity_error(a, b[:end]))
    return parity


def _write_split(out_dir: Path, data: bytes, chunk_arrays, sizes, sh_degree: int, md: dict,
                 info: RunInfo) -> dict:
    """Write the chunks first, then the base, then the manifest (a reader never sees a manifest
    whose files are not all there yet); stale chunks of an earlier export go. Returns the
    manifest."""
    k = (sh_degree + 1) ** 2
    out_dir.mkdir(exist_ok=True)
    blobs = [(BASE_FILE, data)] + [
        (chunk_file_name(j), encode_chunk(j, {nm: c[nm].numpy() for nm in CHUNK_ARRAYS}))
        for j, c in enumerate(chunk_arrays) if j > 0]
    per_gaussian = 4 * (3 + 3 + 4 + 1 + 3 * k + 3 + 1)
    entries, cum_b, cum_n = [], 0, 0
    for j, (name, blob) in enumerate(blobs):
        cum_b += len(blob)
        cum_n += sizes[j]
        entries.append({"layer": j, "file": name, "bytes": len(blob), "sha256": sha256_of(blob),
                        "gaussians": int(sizes[j]), "cumulative_bytes": cum_b,
                        "cumulative_gaussians": cum_n})
    manifest = {
        "format": MANIFEST_FORMAT, "base": BASE_FILE, "sh_degree": sh_degree,
        "time_range": json.loads(md["time_range"]), "background": json.loads(md["background"]),
        "bytes_per_gaussian": per_gaussian,
        "field_bytes": len(data) - sizes[0] * per_gaussian,
        "train_downscales": list(info.lod.get("downscales", [])),
        "layers": entries,
    }
    for name, blob in blobs:
        atomic_write(out_dir / name, blob)
    for stale in sorted(out_dir.glob("layer_*.bin")):
        if stale.name not in {b[0] for b in blobs}:
            stale.unlink()
    atomic_write(out_dir / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
    return manifest


__all__ = ["INPUT_NAMES", "SplitBaseGraph", "SplitReport", "canonical_arrays",
           "export_split_layers", "export_split_model"]
