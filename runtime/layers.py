"""Streaming layers on disk and their torch-free reader (docs/design.md section 7-8; docs/streaming.md).

`nehad export RUN --split-layers DIR` writes

    DIR/manifest.json     what to fetch, in order: per layer its file, byte size, sha256, Gaussians
    DIR/base.onnx         a complete nehad-onnx/1 model: the deformation field + layer 0
    DIR/layer_1.bin ...   one chunk per enhancement layer: that layer's canonical Gaussians

The base model renders on its own (`nehad render DIR/base.onnx`). Its canonical Gaussians are
initializers, and it has optional inputs, one per canonical array, `extra_means` [M,3],
`extra_log_scales` [M,3], `extra_quats` [M,4] (raw wxyz), `extra_opacity_logits` [M],
`extra_sh` [M,K,3], `extra_mu_eq` [M,3], `extra_t_eq` [M,1], `extra_layer` [M] int32, whose
defaults are empty (M = 0) initializers of the same names (ONNX "overridable initializers"). The
graph appends the extra Gaussians to layer 0's and deforms them all with the one field, so the
client sends the concatenated chunks it holds as those inputs and gets the outputs of layers
0..k. The deformation of each Gaussian depends only on its own canonical parameters, so this is
exactly the prefix of the full model (checked at export to 1e-5).

Chunk file (`nehad-layer/1`), little-endian:

    bytes 0..7    magic b"NEHADLYR"
    bytes 8..11   uint32 H, the length of the JSON header
    H bytes       UTF-8 JSON: {"format": "nehad-layer/1", "layer": k, "count": M,
                  "arrays": [{"name", "dtype", "shape", "offset", "nbytes"}, ...]}
                  offsets count from the start of the data section
    data          the arrays' raw bytes (float32 / int32, C order), each 16-byte aligned

`LayeredModel` reads the manifest, checks the base model's size and hash (without a usable base
nothing can be rendered: an error), then loads chunks 1, 2, ... in order, checking each one's
size, sha256 and header; it stops at the first missing or corrupt chunk, records why in
`problems`, and renders the layers before it. `refresh()` re-reads the folder, for chunks that
arrived since.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import numpy as np

from nehad.runtime.images import atomic_write_bytes as atomic_write

from .errors import InputProblem

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "nehad-layers/1"
CHUNK_FORMAT = "nehad-layer/1"
MAGIC = b"NEHADLYR"
BASE_FILE = "base.onnx"
#: Canonical arrays of a chunk, in order, with their trailing shapes (K: SH coefficients).
CHUNK_ARRAYS = ("means", "log_scales", "quats", "opacity_logits", "sh", "mu_eq", "t_eq")
EXTRA_PREFIX = "extra_"
EXTRA_LAYER = "extra_layer"


class LayerError(InputProblem):
    """A layered model folder, manifest or chunk that cannot be used (the message names it)."""


def chunk_file_name(layer: int) -> str:
    return f"layer_{int(layer)}.bin"


def trailing_shapes(sh_coeffs: int) -> dict[str, tuple[int, ...]]:
    return {"means": (3,), "log_scales": (3,), "quats": (4,), "opacity_logits": (),
            "sh": (int(sh_coeffs), 3), "mu_eq": (3,), "t_eq": (1,)}


def sha256_of(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def encode_chunk(layer: int, arrays: dict[str, np.ndarray]) -> bytes:
    """The bytes of a `nehad-layer/1` chunk holding `arrays` (see the module doc)."""
    count = None
    entries, blobs, offset = [], [], 0
    for name in CHUNK_ARRAYS:
        a = np.ascontiguousarray(arrays[name], dtype=np.float32)
        if count is None:
            count = int(a.shape[0])
        elif a.shape[0] != count:
            raise LayerError(f"chunk {layer}: array {name} has {a.shape[0]} rows, expected {count}")
        raw = a.astype("<f4").tobytes()
        pad = (-offset) % 16
        blobs.append(b"\0" * pad)
        offset += pad
        entries.append({"name": name, "dtype": "float32", "shape": list(a.shape),
                        "offset": offset, "nbytes": len(raw)})
        blobs.append(raw)
        offset += len(raw)
    header = json.dumps({"format": CHUNK_FORMAT, "layer": int(layer), "count": int(count or 0),
                         "arrays": entries}, separators=(",", ":")).encode("utf-8")
    return MAGIC + struct.pack("<I", len(header)) + header + b"".join(blobs)


def decode_chunk(data: bytes, source: str = "chunk") -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) of a chunk's bytes; LayerError naming `source` when malformed."""
    if len(data) < 12 or data[:8] != MAGIC:
        raise LayerError(f"{source}: not a nehad layer chunk (bad magic)")
    (h,) = struct.unpack("<I", data[8:12])
    if 12 + h > len(data):
        raise LayerError(f"{source}: truncated header")
    try:
        header = json.loads(data[12:12 + h].decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise LayerError(f"{source}: header is not valid JSON") from None
    if not isinstance(header, dict) or header.get("format") != CHUNK_FORMAT:
        raise LayerError(f"{source}: header format is not {CHUNK_FORMAT!r}")
    body = memoryview(data)[12 + h:]
    arrays = {}
    try:
        for e in header["arrays"]:
            if e["dtype"] != "float32":
                raise LayerError(f"{source}: array {e['name']} has dtype {e['dtype']}")
            start, n = int(e["offset"]), int(e["nbytes"])
            shape = tuple(int(v) for v in e["shape"])
            if start < 0 or start + n > len(body) or n != 4 * int(np.prod(shape)):
                raise LayerError(f"{source}: array {e['name']} lies outside the file")
            arrays[e["name"]] = np.frombuffer(body[start:start + n], "<f4").reshape(shape).astype(
                np.float32)
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, LayerError):
            raise
        raise LayerError(f"{source}: malformed array table ({e})") from None
    missing = [n for n in CHUNK_ARRAYS if n not in arrays]
    if missing:
        raise LayerError(f"{source}: lacks arrays {missing}")
    return header, arrays


def read_manifest(folder) -> dict:
    folder = Path(folder)
    path = folder / MANIFEST
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise LayerError(f"{folder}: no {MANIFEST} (not a layered model folder; write one with "
                         f"`nehad export RUN --split-layers {folder}`)") from None
    except (ValueError, UnicodeDecodeError):
        raise LayerError(f"{path}: not valid JSON") from None
    except RecursionError:
        raise LayerError(f"{path}: not valid JSON (nested too deeply)") from None
    except OSError as e:  # a folder named manifest.json, no permission
        raise LayerError(f"{path}: cannot read ({e.strerror or e})") from None
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise LayerError(f"{path}: format is not {MANIFEST_FORMAT!r}")
    layers = doc.get("layers")
    if not isinstance(layers, list) or not layers:
        raise LayerError(f"{path}: 'layers' must be a non-empty list")
    for k, e in enumerate(layers):
        if not isinstance(e, dict) or any(key not in e for key in
                                          ("layer", "file", "bytes", "sha256", "gaussians")):
            raise LayerError(f"{path}: layers[{k}] needs layer, file, bytes, sha256, gaussians")
        _check_entry(path, k, e)
    return doc


def _whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_entry(path: Path, k: int, e: dict) -> None:
    """The types of manifest entry `k` (a string layer number, a file name that is a number or
    '..', were tracebacks of int() and Path() further on)."""
    if not _whole(e["layer"]) or e["layer"] != k:
        raise LayerError(f"{path}: layers[{k}].layer is {e['layer']!r}; layers must be 0, 1, ... "
                         f"in order")
    f = e["file"]
    if not isinstance(f, str) or f in ("", ".", "..") or Path(f).name != f:
        raise LayerError(f"{path}: layers[{k}].file {f!r} must be a plain file name")
    for key in ("bytes", "gaussians"):
        if not _whole(e[key]) or e[key] < 0:
            raise LayerError(f"{path}: layers[{k}].{key}: expected a whole number >= 0, got "
                             f"{e[key]!r}")
    if not isinstance(e["sha256"], str):
        raise LayerError(f"{path}: layers[{k}].sha256: expected a hex digest, got "
                         f"{e['sha256']!r}")


def _check_file(folder: Path, entry: dict) -> bytes:
    """The bytes of a manifest entry's file after the size and hash checks (LayerError else)."""
    path = folder / entry["file"]
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise LayerError(f"layer {entry['layer']}: {path} is missing") from None
    except OSError as e:
        raise LayerError(f"layer {entry['layer']}: {path}: {e.strerror or e}") from None
    if len(data) != int(entry["bytes"]):
        raise LayerError(f"layer {entry['layer']}: {path} has {len(data)} bytes, the manifest "
                         f"says {entry['bytes']} (incomplete or corrupt)")
    if sha256_of(data) != entry["sha256"]:
        raise LayerError(f"layer {entry['layer']}: {path} does not match its sha256 (corrupt)")
    return data


class LayeredModel:
    """A split layered model folder (see the module doc): renders layers 0..k for the longest
    prefix of intact chunks (up to `max_layer` when given).

    Attributes: `base` (the OnnxModel of base.onnx), `manifest`, `num_layers` (in the manifest),
    `loaded_layers` (how many render now), `problems` (one line per chunk that could not be used),
    and the OnnxModel-like `gaussians(time)`, `time_range`, `background`, `sh_degree`."""

    def __init__(self, folder, threads: int | None = None, max_layer: int | None = None):
        from .onnx_model import OnnxModel

        self.folder = Path(folder)
        self.manifest = read_manifest(self.folder)
        self.entries = self.manifest["layers"]
        self.num_layers = len(self.entries)
        if max_layer is not None and not 0 <= int(max_layer):
            raise LayerError(f"{{lod}} {max_layer}: must be >= 0", "lod")
        self.max_layer = None if max_layer is None else int(max_layer)
        _check_file(self.folder, self.entries[0])
        self.base = OnnxModel(self.folder / self.entries[0]["file"], threads=threads)
        self.overridable = dict(self.base.overridable_inputs)
        missing = [f"{EXTRA_PREFIX}{n}" for n in CHUNK_ARRAYS
                   if f"{EXTRA_PREFIX}{n}" not in self.overridable]
        if self.num_layers > 1 and (missing or EXTRA_LAYER not in self.overridable):
            raise LayerError(f"{self.base.source}: the base model has no inputs for enhancement "
                             f"layers (lacks {missing or [EXTRA_LAYER]})")
        self.time_range = self.base.time_range
        self.background = self.base.background
        self.sh_degree = self.base.sh_degree
        self.default_camera = self.base.default_camera
        self.problems: list[str] = []
        self.loaded_layers = 1
        self.refresh()

    @property
    def wanted_layers(self) -> int:
        n = self.num_layers
        return n if self.max_layer is None else min(n, self.max_layer + 1)

    def refresh(self) -> int:
        """(Re)load the chunks present in the folder; returns the number of layers that render."""
        k = (self.base.sh_degree + 1) ** 2
        shapes = trailing_shapes(k)
        parts: list[dict[str, np.ndarray]] = []
        problems = []
        for entry in self.entries[1:self.wanted_layers]:
            layer = int(entry["layer"])
            try:
                data = _check_file(self.folder, entry)
                header, arrays = decode_chunk(data, str(self.folder / entry["file"]))
                n = int(entry["gaussians"])
                if header.get("layer", -1) != layer or header.get("count", -1) != n:
                    raise LayerError(f"layer {layer}: chunk header says layer "
                                     f"{header.get('layer')} with {header.get('count')} "
                                     f"Gaussians, the manifest layer {layer} with {n}")
                for name, tail in shapes.items():
                    if arrays[name].shape != (n, *tail):
                        raise LayerError(f"layer {layer}: array {name} has shape "
                                         f"{arrays[name].shape}, expected {(n, *tail)}")
                    if not np.isfinite(arrays[name]).all():
                        raise LayerError(f"layer {layer}: array {name} holds NaN or infinite "
                                         f"values")
            except LayerError as e:
                problems.append(f"{e}; rendering layers 0..{layer - 1}")
                break
            arrays["layer"] = np.full(n, layer, np.int32)
            parts.append(arrays)
        self.problems = problems
        self.loaded_layers = 1 + len(parts)
        feeds = {}
        if self.num_layers > 1:
            for name, tail in shapes.items():
                feeds[EXTRA_PREFIX + name] = (np.concatenate([p[name] for p in parts], 0)
                                              if parts else np.zeros((0, *tail), np.float32))
            feeds[EXTRA_LAYER] = (np.concatenate([p["layer"] for p in parts]) if parts
                                  else np.zeros(0, np.int32))
        self.base.set_extra_inputs(feeds)
        return self.loaded_layers

    @property
    def num_gaussians(self) -> int:
        return sum(int(e["gaussians"]) for e in self.entries[:self.loaded_layers])

    def __len__(self) -> int:
        return self.num_gaussians

    def gaussians(self, time: float):
        """The deformed Gaussians of the loaded layers at `time` (a GaussianCloud)."""
        return self.base.gaussians(time)

    def outputs(self, time: float) -> dict:
        return self.base.outputs(time)


def open_layered(folder, threads: int | None = None, max_layer: int | None = None) -> LayeredModel:
    return LayeredModel(folder, threads=threads, max_layer=max_layer)


__all__ = ["BASE_FILE", "CHUNK_ARRAYS", "CHUNK_FORMAT", "EXTRA_LAYER", "EXTRA_PREFIX",
           "LayerError", "LayeredModel", "MANIFEST", "MANIFEST_FORMAT", "atomic_write",
           "chunk_file_name", "decode_chunk", "encode_chunk", "open_layered", "read_manifest",
           "sha256_of", "trailing_shapes"]
