"""What `nehad render` can draw: a scene source chosen from the SCENE path.

A source gives the activated Gaussians at a time and the background its format implies:

==============================  ==============================  ===========================
SCENE                           source                          status
==============================  ==============================  ===========================
``*.ply``                       a standard 3DGS PLY (static)    supported
``*.onnx``                      an exported ``nehad-onnx/1``    supported (no torch)
a directory                     a training run (needs torch)    supported
a directory with manifest.json  streaming layers (no torch)     supported
==============================  ==============================  ===========================

`lod` (``nehad render --lod K``) keeps streaming layers 0..K (SPEC 8): of a run trained with
``--lod-levels``, of an exported model with a ``layer`` output, or of a split layers folder
(whose missing or corrupt chunks are reported in ``problems`` and skipped: the layers before
them are rendered).

Adding a source: a class with ``describe()``, ``default_background``, ``num_gaussians``,
``sh_degree`` and ``gaussians(time)``, and a branch in :func:`open_source`. Heavy imports (onnxruntime, torch) belong inside the class, never
at the top of this module: the CLI imports it for every render.
"""

from __future__ import annotations

from pathlib import Path

from .errors import InputError


class PlySource:
    """A static 3DGS PLY: the same Gaussians at every time; black background by default."""

    kind = "ply"
    dynamic = False
    time_range = (0.0, 1.0)
    default_background = (0.0, 0.0, 0.0)

    def __init__(self, path: Path, lod: int | None = None):
        self.path = Path(path)
        self._cloud = None
        self.problems: list[str] = []
        if lod is not None and lod != 0:
            raise InputError(f"--lod {lod}: {self.path} is a PLY file, which has one layer (0)")

    def load(self):
        """Read the file now (raises PlyError for a missing or malformed file)."""
        if self._cloud is None:
            from nehad.runtime.ply import read_gaussian_ply

            self._cloud = read_gaussian_ply(self.path)
        return self._cloud

    def gaussians(self, time: float | None = None):
        """The Gaussians at `time` (ignored: a PLY is static)."""
        return self.load()

    @property
    def num_gaussians(self) -> int:
        return len(self.load())

    @property
    def sh_degree(self) -> int:
        return self.load().sh_degree

    def describe(self) -> str:
        cloud = self.load()
        return f"{len(cloud)} Gaussians, SH degree {cloud.sh_degree}"


class RunSource:
    """A training run directory (RUN/model.pt): the deformed Gaussians at any time, computed by
    the torch model; the background the run was trained with."""

    kind = "run"
    dynamic = True

    def __init__(self, path: Path, lod: int | None = None):
        from nehad.trainer import load_run  # torch: only for this source

        self.path = Path(path)
        self.model, self.meta = load_run(self.path)
        self.default_background = tuple(float(v) for v in self.meta["background"])
        self.time_range = tuple(float(v) for v in self.meta["time_range"])
        self.sh_degree = int(self.meta["sh_degree"])
        self.problems: list[str] = []
        self.lod = lod
        self._keep = None
        if lod is not None:
            from nehad.lod import run_layers

            layers = run_layers(self.meta, len(self.model.gaussians))
            count = int(layers.max()) + 1 if len(layers) else 1
            if not 0 <= lod < count:
                raise InputError(f"--lod {lod}: run {self.path} has {count} layer(s), "
                                 f"0..{count - 1}")
            self._keep = layers <= lod

    @property
    def num_gaussians(self) -> int:
        return len(self.model.gaussians)

    def gaussians(self, time: float | None = None):
        from nehad.trainer import cloud_at

        cloud = cloud_at(self.model, time, self.sh_degree)
        if self._keep is not None:
            from nehad.runtime.gaussians import GaussianCloud

            k = self._keep
            cloud = GaussianCloud(cloud.means[k], cloud.scales[k], cloud.quats[k],
                                  cloud.opacities[k], cloud.sh[k])
        return cloud

    def describe(self) -> str:
        if self._keep is not None:
            return (f"run {self.path.name}: layers 0..{self.lod}, {int(self._keep.sum())} of "
                    f"{len(self.model.gaussians)} Gaussians, SH degree {self.sh_degree}")
        return f"run {self.path.name}: {len(self.model.gaussians)} Gaussians, SH degree {self.sh_degree}"


class OnnxSource:
    """An exported ``nehad-onnx/1`` model: the deformed Gaussians at any time, computed by
    onnxruntime (no torch); time range and background from the file's metadata."""

    kind = "onnx"
    dynamic = True

    def __init__(self, path: Path, threads: int | None = None, lod: int | None = None):
        from nehad.runtime.onnx_model import open_model  # onnxruntime: only for this source

        self.path = Path(path)
        self.model = open_model(self.path, threads=threads)
        self.default_background = tuple(float(v) for v in self.model.background)
        self.time_range = tuple(float(v) for v in self.model.time_range)
        self.sh_degree = self.model.sh_degree
        self.num_gaussians = self.model.num_gaussians
        self.default_camera = self.model.default_camera
        self.problems: list[str] = []
        self.lod = lod
        if lod is not None and not 0 <= lod < self.model.num_layers:
            raise InputError(f"--lod {lod}: {self.path} has {self.model.num_layers} layer(s), "
                             f"0..{self.model.num_layers - 1}")

    def gaussians(self, time: float | None = None):
        """The Gaussians at `time` (the middle of the time range when None)."""
        if time is None:
            time = 0.5 * (self.time_range[0] + self.time_range[1])
        return self.model.gaussians(time, max_layer=self.lod)

    def describe(self) -> str:
        n = self.model.num_gaussians
        layers = ""
        if self.lod is not None:
            import json

            counts = json.loads(self.model.metadata.get("lod_layers") or f"[{n}]")
            layers = f"layers 0..{self.lod} of {self.model.num_layers}, "
            n = sum(counts[:self.lod + 1])
        return f"model {self.path.name}: {layers}{n} Gaussians, SH degree {self.sh_degree}"


class LayeredSource:
    """A folder written by ``nehad export --split-layers``: base.onnx plus the chunks of the
    enhancement layers (no torch). Renders the longest intact prefix of layers (up to `lod`);
    `problems` says which chunk was missing or corrupt."""

    kind = "layers"
    dynamic = True

    def __init__(self, path: Path, threads: int | None = None, lod: int | None = None):
        from nehad.runtime.layers import LayeredModel

        self.path = Path(path)
        self.model = LayeredModel(self.path, threads=threads, max_layer=lod)
        if lod is not None and lod >= self.model.num_layers:
            raise InputError(f"--lod {lod}: {self.path} has {self.model.num_layers} layer(s), "
                             f"0..{self.model.num_layers - 1}")
        self.default_background = tuple(float(v) for v in self.model.background)
        self.time_range = tuple(float(v) for v in self.model.time_range)
        self.sh_degree = self.model.sh_degree
        self.num_gaussians = self.model.num_gaussians
        self.default_camera = self.model.default_camera
        self.problems = list(self.model.problems)

    def gaussians(self, time: float | None = None):
        if time is None:
            time = 0.5 * (self.time_range[0] + self.time_range[1])
        return self.model.gaussians(time)

    def describe(self) -> str:
        m = self.model
        return (f"layers {self.path.name}: layers 0..{m.loaded_layers - 1} of {m.num_layers}, "
                f"{m.num_gaussians} Gaussians, SH degree {self.sh_degree}")


def open_source(path, lod: int | None = None):
    """The scene source for a SCENE argument, dispatched on the path (see the module doc);
    `lod` keeps streaming layers 0..lod."""
    p = Path(path)
    suffix = p.suffix.lower()
    if p.is_dir():
        if (p / "manifest.json").exists():
            return LayeredSource(p, lod=lod)
        if not (p / "model.pt").exists():
            raise InputError(f"{p}: not a finished training run (no model.pt)")
        return RunSource(p, lod=lod)
    if suffix == ".ply":
        return PlySource(p, lod=lod)  # a missing file is reported by the PLY reader
    if suffix == ".onnx":
        if not p.exists():
            raise InputError(f"{p}: no such file")
        return OnnxSource(p, lod=lod)
    if not p.exists():
        raise InputError(f"{p}: no such file or directory")
    raise InputError(f"{p}: unknown scene type {suffix or '(no extension)'!r} "
                     f"(expected a 3DGS .ply file, an exported .onnx model "
                     f"or a training run folder)")
