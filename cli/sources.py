"""What `nehad render` can draw: a scene source chosen from the SCENE path.

A source gives the activated Gaussians at a time and the background its format implies:

==============================  ==============================  ===========================
SCENE                           source                          status
==============================  ==============================  ===========================
``*.ply``                       a standard 3DGS PLY (static)    supported
``*.onnx``                      an exported ``nehad-onnx/1``    supported (no torch)
a directory                     a training run (needs torch)    supported
==============================  ==============================  ===========================

Adding a source: a class with ``describe()``, ``default_background`` and ``gaussians(time)``, and
a branch in :func:`open_source`. Heavy imports (onnxruntime, torch) belong inside the class, never
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

    def __init__(self, path: Path):
        self.path = Path(path)
        self._cloud = None

    def load(self):
        """Read the file now (raises PlyError for a missing or malformed file)."""
        if self._cloud is None:
            from nehad.runtime.ply import read_gaussian_ply

            self._cloud = read_gaussian_ply(self.path)
        return self._cloud

    def gaussians(self, time: float | None = None):
        """The Gaussians at `time` (ignored: a PLY is static)."""
        return self.load()

    def describe(self) -> str:
        cloud = self.load()
        return f"{len(cloud)} Gaussians, SH degree {cloud.sh_degree}"


class RunSource:
    """A training run directory (RUN/model.pt): the deformed Gaussians at any time, computed by
    the torch model; the background the run was trained with."""

    kind = "run"
    dynamic = True

    def __init__(self, path: Path):
        from nehad.trainer import load_run  # torch: only for this source

        self.path = Path(path)
        self.model, self.meta = load_run(self.path)
        self.default_background = tuple(float(v) for v in self.meta["background"])
        self.time_range = tuple(float(v) for v in self.meta["time_range"])
        self.sh_degree = int(self.meta["sh_degree"])

    def gaussians(self, time: float | None = None):
        from nehad.trainer import cloud_at

        return cloud_at(self.model, time, self.sh_degree)

    def describe(self) -> str:
        return f"run {self.path.name}: {len(self.model.gaussians)} Gaussians, SH degree {self.sh_degree}"


class OnnxSource:
    """An exported ``nehad-onnx/1`` model: the deformed Gaussians at any time, computed by
    onnxruntime (no torch); time range and background from the file's metadata."""

    kind = "onnx"
    dynamic = True

    def __init__(self, path: Path, threads: int | None = None):
        from nehad.runtime.onnx_model import open_model  # onnxruntime: only for this source

        self.path = Path(path)
        self.model = open_model(self.path, threads=threads)
        self.default_background = tuple(float(v) for v in self.model.background)
        self.time_range = tuple(float(v) for v in self.model.time_range)
        self.sh_degree = self.model.sh_degree
        self.default_camera = self.model.default_camera

    def gaussians(self, time: float | None = None):
        """The Gaussians at `time` (the middle of the time range when None)."""
        if time is None:
            time = 0.5 * (self.time_range[0] + self.time_range[1])
        return self.model.gaussians(time)

    def describe(self) -> str:
        return (f"model {self.path.name}: {self.model.num_gaussians} Gaussians, "
                f"SH degree {self.sh_degree}")


def open_source(path):
    """The scene source for a SCENE argument, dispatched on the path (see the module doc)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if p.is_dir():
        if not (p / "model.pt").exists():
            raise InputError(f"{p}: not a finished training run (no model.pt)")
        return RunSource(p)
    if suffix == ".ply":
        return PlySource(p)  # a missing file is reported by the PLY reader
    if suffix == ".onnx":
        if not p.exists():
            raise InputError(f"{p}: no such file")
        return OnnxSource(p)
    if not p.exists():
        raise InputError(f"{p}: no such file or directory")
    raise InputError(f"{p}: unknown scene type {suffix or '(no extension)'!r} "
                     f"(expected a 3DGS .ply file, an exported .onnx model "
                     f"or a training run folder)")
