"""Load and run an exported `nehad-onnx/1` model without torch (docs/design.md section 7).

    model = OnnxModel("lego.onnx", threads=4)
    cloud = model.gaussians(0.5)          # GaussianCloud for nehad.runtime.raster.render
    model.time_range, model.background, model.default_camera, model.aabb

The file is validated when opened: the format tag and metadata, the digest of the graph (its
operators and weights) that the export wrote into the metadata (`graph_sha256`, issue 15; a
file exported before it has none and is not checked), the input `time` float32 [1], the
outputs means [N,3], scales [N,3], quats [N,4], opacities [N], sh [N,K,3] (and an optional
`layer` [N]). A foreign, truncated or damaged file, or outputs holding NaN, raise
:class:`OnnxModelError` with a message naming the file. The deformed Gaussians of the last few
times are cached, so several views at one time deform once.

A file exported in parts (metadata `parts`: row bounds 0 = b_0 < ... < b_P = N) has an output
`NAME.partP` with rows b_P .. b_P+1 of each output NAME that changes with time (docs/design.md
section 7). With more than one thread the parts are deformed side by side: each thread runs a
session of its own on the graph cut down to its share of the parts (`graph_for_outputs`:
onnxruntime runs every node of a graph whatever a run asks for), one onnxruntime thread each (a
15k-Gaussian model on 2 cores: 6.3 ms against 8.7-9.0 for the whole on onnxruntime's 2 threads,
docs/performance.md). The outputs without parts are constants, fetched once.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .gaussians import GaussianCloud
from .onnx_proto import (ModelSummary, ProtoError, graph_for_outputs, graph_sha256,
                         inputs_read, summarize)
from .errors import InputProblem
from .threads import usable_cores
from .values import MAX_THREADS, count_problem

FORMAT = "nehad-onnx/1"
OUTPUTS = ("means", "scales", "quats", "opacities", "sh")
REQUIRED_METADATA = ("format", "sh_degree", "num_gaussians", "time_range", "background", "aabb")
#: Metadata key of the SHA-256 of the serialized graph (runtime.onnx_proto.graph_sha256).
DIGEST_KEY = "graph_sha256"
#: Metadata key of the part row bounds; part outputs are named by `part_output_name`.
PARTS_KEY = "parts"
PART_SUFFIX = ".part"


def part_output_name(name: str, part: int) -> str:
    """The output that holds part `part`'s rows of output `name` ("means.part0", ...)."""
    return f"{name}{PART_SUFFIX}{part}"


class OnnxModelError(InputProblem):
    """An .onnx file that is not a usable nehad-onnx/1 model (the message names the file)."""


@dataclass
class ModelInfo:
    """What `nehad info` shows: read from the file alone (no session)."""

    path: Path
    file_size: int
    opset: int
    operators: dict  # op type -> count
    metadata: dict  # raw metadata_props
    summary: ModelSummary
    sh_degree: int
    num_gaussians: int
    time_range: tuple
    background: tuple
    aabb: np.ndarray  # (2, 3)
    default_camera: object  # runtime.cameras.Camera or None
    digest_checked: bool = False  # the graph matched the metadata's graph_sha256

    @property
    def num_layers(self) -> int:
        """Streaming layers in the file (metadata `lod_layers`; 1 without layers)."""
        return max(1, len(self.layer_counts))

    @property
    def layer_counts(self) -> list[int]:
        """Gaussians of each streaming layer (metadata `lod_layers`; [num_gaussians] without
        layers): a list of whole numbers >= 0, else OnnxModelError naming the file."""
        text = self.metadata.get("lod_layers")
        if not text:
            return [int(self.num_gaussians)]
        try:
            counts = json.loads(text)
        except (ValueError, TypeError, RecursionError):
            counts = None
        if not isinstance(counts, list) or not counts or not all(
                isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts):
            raise OnnxModelError(f"{self.path}: metadata lod_layers is not a JSON list of "
                                 f"Gaussian counts: {text[:200]!r}")
        return counts

    @property
    def static_gaussians(self) -> int:
        """Gaussians written pre-deformed (metadata `static_gaussians`, export/static_split.py;
        0 without): a whole number from 0 to `num_gaussians`, else OnnxModelError naming the
        file (checked when the file is read)."""
        text = self.metadata.get("static_gaussians") or "0"
        try:
            n = int(text)
        except ValueError:
            n = -1
        if not 0 <= n <= self.num_gaussians:
            raise OnnxModelError(f"{self.path}: metadata static_gaussians is not a whole number "
                                 f"from 0 to num_gaussians ({self.num_gaussians}): "
                                 f"{text[:200]!r}")
        return n


def _json(md: dict, key: str, source: str):
    try:
        return json.loads(md[key])
    except (ValueError, TypeError, RecursionError):
        raise OnnxModelError(f"{source}: metadata {key!r} is not valid JSON: {md[key]!r}") from None


def _floats(value, n: int, key: str, source: str) -> list[float]:
    try:
        out = [float(v) for v in np.asarray(value, np.float64).reshape(-1)]
    except (ValueError, TypeError):
        out = None
    if out is None or len(out) != n or not all(math.isfinite(v) for v in out):
        raise OnnxModelError(f"{source}: metadata {key!r} must hold {n} finite numbers, got "
                             f"{value!r}")
    return out


def read_model_info(path) -> ModelInfo:
    """Read and validate the file's summary and metadata (no onnxruntime session)."""
    return _read_model(path)[0]


def _read_model(path) -> tuple[ModelInfo, bytes]:
    """`read_model_info` and the bytes it checked (a file in parts is opened from them)."""
    path = Path(path)
    source = str(path)
    if path.exists() and not path.is_dir() and not path.is_file():
        # /dev/zero would be read forever, a FIFO waits for a writer (issue 26)
        raise OnnxModelError(f"{source}: not a regular file (a device, FIFO or socket)")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise OnnxModelError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise OnnxModelError(f"{source}: is a folder, not an .onnx file") from None
    except OSError as e:
        raise OnnxModelError(f"{source}: cannot read ({e.strerror or e})") from None
    try:
        s = summarize(data)
    except ProtoError as e:
        raise OnnxModelError(f"{source}: not a readable ONNX file (truncated or corrupt: {e})") from None
    if not s.has_graph or not s.opsets:
        raise OnnxModelError(f"{source}: not an ONNX model (no graph or opset)")
    md = s.metadata
    fmt = md.get("format")
    if fmt != FORMAT:
        raise OnnxModelError(f"{source}: not a nehad model (metadata format is {fmt!r}, expected "
                             f"{FORMAT!r}; export one with `nehad export RUN -o model.onnx`)")
    missing = [k for k in REQUIRED_METADATA if k not in md]
    if missing:
        raise OnnxModelError(f"{source}: metadata lacks {', '.join(missing)}")
    digest = md.get(DIGEST_KEY)
    if digest is not None and graph_sha256(data, s.graph_spans) != digest:
        raise OnnxModelError(f"{source}: damaged: its graph (operators and weights) does not match "
                             f"the digest written at export ({DIGEST_KEY}); export the model again "
                             f"or fetch an intact copy")
    try:
        deg, n = int(md["sh_degree"]), int(md["num_gaussians"])
    except ValueError:
        raise OnnxModelError(f"{source}: metadata sh_degree / num_gaussians are not integers") from None
    if not 0 <= deg <= 3 or n < 0:
        raise OnnxModelError(f"{source}: metadata sh_degree {deg} / num_gaussians {n} out of range")
    lo, hi = _floats(_json(md, "time_range", source), 2, "time_range", source)
    if lo > hi:
        raise OnnxModelError(f"{source}: metadata time_range [{lo}, {hi}] is empty")
    bg = _floats(_json(md, "background", source), 3, "background", source)
    if not all(0.0 <= c <= 1.0 for c in bg):
        raise OnnxModelError(f"{source}: metadata 'background' must lie in [0, 1], got "
                             f"{md['background']!r}")
    aabb = np.asarray(_floats(_json(md, "aabb", source), 6, "aabb", source)).reshape(2, 3)
    camera = None
    if "default_camera" in md:
        from .cameras import CameraError, parse_camera

        obj = _json(md, "default_camera", source)
        try:
            camera = parse_camera(obj, source=f"{source} (metadata default_camera)")
        except (CameraError, TypeError, AttributeError) as e:
            raise OnnxModelError(f"{source}: metadata default_camera: {e}") from None
    opset = int(s.opsets.get("", s.opsets.get("ai.onnx", 0)))
    info = ModelInfo(path, len(data), opset, dict(s.operators), dict(md), s, deg, n, (lo, hi),
                     tuple(bg), aabb, camera, digest is not None)
    info.static_gaussians  # its range is checked here, when the file is read
    return info, data


def _dims(arg) -> list:
    return [d if isinstance(d, int) else None for d in (arg.shape or [])]


class OnnxModel:
    """An exported NeHaD model with an onnxruntime session (see the module doc).

    Args:
        path: the .onnx file.
        threads: threads of the deformation (None or 0: onnxruntime's default, or for a file in
            parts one per usable core): a file in parts runs its parts on up to this many
            threads side by side, the rest as intra-op threads of the session.
        cache_size: how many times' deformed Gaussians to keep (0: no cache).
    """

    def __init__(self, path, threads: int | None = None, cache_size: int = 4):
        self.path = Path(path)
        self.source = str(self.path)
        self.info, data = _read_model(self.path)
        self.metadata = self.info.metadata
        self.sh_degree = self.info.sh_degree
        self.num_gaussians = self.info.num_gaussians
        self.time_range = self.info.time_range
        self.background = self.info.background
        self.aabb = self.info.aabb
        self.default_camera = self.info.default_camera
        self.cache_size = max(0, int(cache_size))
        self._cache: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._extra_feeds: dict = {}  # optional inputs (streaming layers, runtime/layers.py)
        self.runs = 0  # session runs so far (the cache saves the others)
        why = count_problem(threads, 0, MAX_THREADS)
        if why:
            raise OnnxModelError(f"{{threads}} {threads}: {why} (0: as many as there are cores)",
                                 input="threads")
        self.part_bounds = self._read_part_bounds()
        parts = len(self.part_bounds) - 1
        total = int(threads or 0) or usable_cores()
        #: parts deformed side by side (1: one run for the whole)
        self.workers = min(parts, total) if parts > 1 else 1
        intra = max(1, total // self.workers) if parts > 1 else int(threads or 0)
        self._pool = None
        self._pool_pid = None
        self._constants: dict | None = None
        self._part_sessions: list = []
        self.session = None  # the whole graph's session (a file without parts)
        #: optional inputs of the graph (overridable initializers: runtime/layers.py)
        self.overridable_inputs: dict = {}
        import onnxruntime as ort

        from .threads import prefer_passive_openmp

        prefer_passive_openmp()  # the rasterizer's idle workers leave onnxruntime the cores
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        opts.intra_op_num_threads = intra
        opts.inter_op_num_threads = 1
        # onnxruntime's pool threads spin after each run by default, taking the cores from the
        # Numba rasterizer that runs next: 17.5 FPS instead of 41.2 for a 12k-Gaussian model at
        # 400x400 on 2 cores (bench/render.py).
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if parts > 1:
            self._open_parts(ort, opts, data)
            return
        del data
        self.session = self._session(ort, self.source, opts, "the model")
        self._check_inputs(self.session)
        self.overridable_inputs = {i.name: i
                                   for i in self.session.get_overridable_initializers()}
        outs = {o.name: o for o in self.session.get_outputs()}
        missing = [name for name in OUTPUTS if name not in outs]
        if missing:
            raise OnnxModelError(f"{self.source}: the model lacks outputs {missing} "
                                 f"(has {sorted(outs)})")
        self._check_outputs(outs.values(), {})
        self.output_names = list(outs)

    def _session(self, ort, model, opts, what: str):
        try:
            return ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        except Exception as e:
            raise OnnxModelError(f"{self.source}: onnxruntime cannot load {what}: "
                                 f"{' '.join(str(e).split())[:300]}") from None

    def _open_parts(self, ort, opts, data: bytes) -> None:
        """One session per share of the parts (module doc), each on the graph cut down to its
        part outputs, from the bytes whose digest was checked; no session of the whole graph.
        With one share (one thread) its session holds every part without the whole outputs'
        concatenation, as fast on one thread as a file without parts (docs/performance.md).
        The outputs without part outputs must be constants (read no input)."""
        src, names = self.source, self.info.summary.outputs
        missing = [name for name in OUTPUTS if name not in names]
        if missing:
            raise OnnxModelError(f"{src}: the model lacks outputs {missing} (has {sorted(names)})")
        parts = self._part_outputs(names)
        extra = sorted(set(names) - set(OUTPUTS) - {"layer"} - set(parts))
        if extra:
            raise OnnxModelError(f"{src}: unexpected outputs {extra}")
        self.parted = sorted({name for name, _ in parts.values()}, key=OUTPUTS.index)
        self.output_names = [name for name in names if name not in parts]
        self._constant_names = [name for name in self.output_names if name not in self.parted]
        moving = [name for name in OUTPUTS[:4] if name not in self.parted]
        if moving:
            raise OnnxModelError(f"{src}: outputs {moving} have no part outputs, as a file in "
                                 f"parts must")
        try:
            read = inputs_read(data, self._constant_names) if self._constant_names else set()
        except ProtoError as e:
            raise OnnxModelError(f"{src}: not a readable ONNX file ({e})") from None
        if read:
            raise OnnxModelError(f"{src}: outputs {self._constant_names} have no part outputs "
                                 f"but read the inputs {sorted(read)} (they change with time)")
        groups = np.array_split(np.arange(len(self.part_bounds) - 1), self.workers)
        self._fetches = [[part_output_name(name, p) for p in group for name in self.parted]
                         for group in groups]
        for i, fetch in enumerate(self._fetches):
            wanted = fetch + (self._constant_names if i == 0 else [])
            try:
                cut = graph_for_outputs(data, wanted)
            except ProtoError as e:
                raise OnnxModelError(f"{src}: cannot cut the model into its parts ({e})") from None
            session = self._session(ort, cut, opts, f"the model's parts {wanted[:1]}...")
            del cut
            self._check_inputs(session)
            self._check_outputs(session.get_outputs(), parts)
            self._part_sessions.append(session)

    def _read_part_bounds(self) -> list[int]:
        """The metadata's part row bounds ([0, N] for a file without parts)."""
        n, text = self.num_gaussians, self.metadata.get(PARTS_KEY)
        if text is None:
            return [0, n]
        bounds = _json(self.metadata, PARTS_KEY, self.source)
        if not (isinstance(bounds, list) and len(bounds) >= 2
                and all(isinstance(b, int) and not isinstance(b, bool) for b in bounds)):
            raise OnnxModelError(f"{self.source}: metadata {PARTS_KEY!r} must be a list of row "
                                 f"numbers, got {text!r}")
        if bounds[0] != 0 or bounds[-1] != n or any(a >= b for a, b in zip(bounds[:-1], bounds[1:])):
            raise OnnxModelError(f"{self.source}: metadata {PARTS_KEY!r} must increase from 0 to "
                                 f"num_gaussians {n}, got {text!r}")
        return bounds

    def _part_outputs(self, names) -> dict[str, tuple[str, int]]:
        """{NAME.partP: (NAME, rows)} for the outputs in parts, checked present as a whole set
        per output; `names` are the file's outputs."""
        bounds, parts = self.part_bounds, len(self.part_bounds) - 1
        found = {}
        for name in OUTPUTS:
            have = [part_output_name(name, p) in names for p in range(parts)]
            if any(have):
                if not all(have):
                    raise OnnxModelError(f"{self.source}: output {name!r} has some of its "
                                         f"{parts} part outputs, not all")
                for p in range(parts):
                    found[part_output_name(name, p)] = (name, bounds[p + 1] - bounds[p])
        if not found:
            raise OnnxModelError(f"{self.source}: metadata {PARTS_KEY!r} names {parts} parts "
                                 f"but the model has no part outputs")
        return found

    def _check_inputs(self, session) -> None:
        inputs = session.get_inputs()
        if len(inputs) != 1 or inputs[0].name != "time" or inputs[0].type != "tensor(float)" \
                or _dims(inputs[0]) not in ([1], [None]):
            got = [(i.name, i.type, i.shape) for i in inputs]
            raise OnnxModelError(f"{self.source}: expected one input 'time' float32 [1], got {got}")

    def _check_outputs(self, outputs, parts: dict) -> None:
        """Each output's type and shape (N = num_gaussians; a part output: its rows)."""
        src, n, k = self.source, self.num_gaussians, (self.sh_degree + 1) ** 2
        expected = {"means": [n, 3], "scales": [n, 3], "quats": [n, 4], "opacities": [n],
                    "sh": [n, k, 3], "layer": [n]}
        for part, (name, rows) in parts.items():
            expected[part] = [rows] + expected[name][1:]
        outputs = list(outputs)
        extra = sorted({o.name for o in outputs} - set(expected))
        if extra:
            raise OnnxModelError(f"{src}: unexpected outputs {extra}")
        for o in outputs:
            want = "tensor(int32)" if o.name == "layer" else "tensor(float)"
            dims = _dims(o)
            shape_ok = len(dims) == len(expected[o.name]) and all(
                d is None or d == e for d, e in zip(dims, expected[o.name]))
            if o.type != want or not shape_ok:
                raise OnnxModelError(f"{src}: output {o.name!r} is {o.type} {o.shape}; expected "
                                     f"{want} {expected[o.name]} (N = num_gaussians {n}, K = {k})")

    # ------------------------------------------------------------------ running
    def outputs(self, time: float) -> dict[str, np.ndarray]:
        """All outputs at `time` (cached per float32 time)."""
        try:
            t = float(time)
        except (TypeError, ValueError):
            raise OnnxModelError(f"{self.source}: time {time!r} is not a number") from None
        if not math.isfinite(t):
            raise OnnxModelError(f"{self.source}: time {t} is not a finite number")
        key = float(np.float32(t))
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        feeds = {"time": np.array([key], np.float32), **self._extra_feeds}
        if self._part_sessions:
            out = self._run_parts(feeds)
        else:
            values = self.session.run(self.output_names, feeds)
            out = dict(zip(self.output_names, values))
        for name, arr in out.items():
            bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
            if bad:
                raise OnnxModelError(f"{self.source}: output {name!r} at time {t:g} holds {bad} "
                                     f"NaN or infinite values")
        with self._lock:
            self.runs += 1
            if self.cache_size:
                self._cache[key] = out
                while len(self._cache) > self.cache_size:
                    self._cache.popitem(last=False)
        return out

    def _run_parts(self, feeds: dict) -> dict[str, np.ndarray]:
        """The outputs from the parts, deformed side by side (module doc): the first share in
        this thread, the others on a pool (made anew in a forked process)."""
        if self.workers > 1 and (self._pool is None or self._pool_pid != os.getpid()):
            from concurrent.futures import ThreadPoolExecutor

            with self._lock:
                if self._pool is None or self._pool_pid != os.getpid():
                    self._pool = ThreadPoolExecutor(self.workers - 1,
                                                    thread_name_prefix="nehad-parts")
                    self._pool_pid = os.getpid()
        first, *others = self._part_sessions
        futures = [self._pool.submit(session.run, fetch, feeds)
                   for session, fetch in zip(others, self._fetches[1:])]
        fetch = self._fetches[0]
        if self._constants is None:  # the outputs without parts do not change with time
            got = first.run(fetch + self._constant_names, feeds)
            self._constants = dict(zip(self._constant_names, got[len(fetch):]))
            shares = [got[:len(fetch)]]
        else:
            shares = [first.run(fetch, feeds)]
        shares += [f.result() for f in futures]
        values = [v for share in shares for v in share]
        parted = len(self.parted)
        out = {name: np.concatenate(values[i::parted], 0) for i, name in enumerate(self.parted)}
        out.update(self._constants)
        return {name: out[name] for name in self.output_names}

    def gaussians(self, time: float, max_layer: int | None = None) -> GaussianCloud:
        """The deformed, activated Gaussians at `time` for the shared rasterizer; with
        `max_layer` K, only those of streaming layers 0..K (docs/design.md section 8: the `layer` output)."""
        o = self.outputs(time)
        if max_layer is not None:
            if not 0 <= int(max_layer) < self.num_layers:
                raise OnnxModelError(f"{self.source}: {{lod}} {max_layer}: the model has "
                                     f"{self.num_layers} layer(s), 0..{self.num_layers - 1}")
            if "layer" in o:
                keep = o["layer"] <= int(max_layer)
                return GaussianCloud(o["means"][keep], o["scales"][keep], o["quats"][keep],
                                     o["opacities"][keep], o["sh"][keep])
        return GaussianCloud(o["means"], o["scales"], o["quats"], o["opacities"], o["sh"])

    @property
    def num_layers(self) -> int:
        """Streaming layers in the file (`ModelInfo.num_layers`)."""
        return self.info.num_layers

    def set_extra_inputs(self, feeds: dict) -> None:
        """Feed these optional inputs (overridable initializers, e.g. the extra_* Gaussians of
        streaming layers) with every run from now on; clears the cache."""
        known = set(self.overridable_inputs)
        unknown = sorted(set(feeds) - known)
        if unknown:
            raise OnnxModelError(f"{self.source}: the model has no optional inputs {unknown}")
        with self._lock:
            self._extra_feeds = dict(feeds)
            self._cache.clear()

    def clear_cache(self) -> None:
        with self._lock:
            self._cache.clear()

    def __len__(self) -> int:
        return self.num_gaussians


def open_model(path, threads: int | None = None) -> OnnxModel:
    """`OnnxModel(path, threads)`; the thread count defaults to $NEHAD_THREADS when set."""
    if threads is None and os.environ.get("NEHAD_THREADS"):
        try:
            threads = int(os.environ["NEHAD_THREADS"])
        except ValueError:
            raise OnnxModelError(f"NEHAD_THREADS={os.environ['NEHAD_THREADS']!r}: not an "
                                 f"integer") from None
    return OnnxModel(path, threads=threads)


__all__ = ["DIGEST_KEY", "FORMAT", "ModelInfo", "OnnxModel", "OnnxModelError", "open_model",
           "read_model_info"]
