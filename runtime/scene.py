"""A scene you can render at time t through a camera: one notion for every command
(docs/design.md, "Scenes").

==============================  ================================  ==============
SCENE path                      scene                             needs
==============================  ================================  ==============
``*.ply``                       a standard 3DGS PLY (static)      runtime only
``*.onnx``                      an exported ``nehad-onnx/1``      runtime only
a folder with manifest.json     split streaming layers            runtime only
a folder with model.pt          a training run                    an opener
==============================  ================================  ==============

:func:`open_scene` picks the kind from the path. A training run is drawn by its torch model,
which the runtime never imports: the training package offers an *opener* (a function
``opener(path, lod, threads) -> Scene | None``, named as ``"module:function"``) that the caller
passes in `openers` (the command line passes ``nehad.run_scene:open_run``). The openers travel
with each frame task, so a pool or Dask worker opens a run the same way.

`lod` keeps streaming layers 0..lod (docs/streaming.md). :func:`scene_time` is the one time
check and :func:`choose_camera` the one camera choice of every command.
"""

from __future__ import annotations

import hashlib
import importlib
import math
from pathlib import Path

import numpy as np

from .errors import InputProblem


class SceneError(InputProblem):
    """A scene path, time, layer or camera that cannot be used; the message names it."""


class Scene:
    """What every scene offers (subclasses fill it in).

    kind: "ply", "onnx", "layers" or "run"; path: what was opened; dynamic: whether it moves;
    time_range: the trained (lo, hi) (a static PLY says (0, 1) and ignores time);
    default_background, default_camera (or None), aabb ((2, 3) or None), num_gaussians,
    sh_degree, num_layers (streaming layers; 1 without); problems: warnings found while opening
    (a damaged layer chunk)."""

    kind = "scene"
    dynamic = True
    num_layers = 1
    time_range: tuple[float, float] = (0.0, 1.0)
    default_background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    default_camera = None
    aabb = None

    def __init__(self, path):
        self.path = Path(path)
        self.problems: list[str] = []

    def gaussians(self, time: float | None):
        """The activated Gaussians (a GaussianCloud) at `time` (None: the middle of the range)."""
        raise NotImplementedError

    def describe(self) -> str:
        return f"{self.kind} {self.path.name}: {self.num_gaussians} Gaussians, SH degree " \
               f"{self.sh_degree}"

    def digest(self) -> str:
        """sha256 of what defines the scene's content (a moved copy has the same digest)."""
        return file_sha256(self.path)

    def middle_time(self) -> float:
        return 0.5 * (self.time_range[0] + self.time_range[1])

    def cameras(self) -> list:
        """The cameras the scene comes with (a run: its dataset's test split); the first is
        `default_camera`. Empty when it has none."""
        return [self.default_camera] if self.default_camera is not None else []


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class PlyScene(Scene):
    """A static 3DGS PLY: the same Gaussians at every time; black background by default."""

    kind = "ply"
    dynamic = False

    def __init__(self, path, lod: int | None = None):
        super().__init__(path)
        if lod is not None and lod != 0:
            raise SceneError(f"{{lod}} {lod}: {self.path} is a PLY file, which has one layer "
                             f"(0)", "lod")
        from .ply import read_gaussian_ply

        self.cloud = read_gaussian_ply(self.path)  # PlyError names a missing or bad file
        self.num_gaussians = len(self.cloud)
        self.sh_degree = self.cloud.sh_degree
        if len(self.cloud):
            self.aabb = np.stack([self.cloud.means.min(0), self.cloud.means.max(0)])

    def gaussians(self, time=None):
        return self.cloud


class OnnxScene(Scene):
    """An exported ``nehad-onnx/1`` model, deformed by onnxruntime; its metadata gives the time
    range, background, box and default camera. The session starts at the first frame."""

    kind = "onnx"

    def __init__(self, path, lod: int | None = None, threads: int | None = None):
        super().__init__(path)
        from .onnx_model import read_model_info
        from .threads import prefer_passive_openmp

        if not self.path.is_file():
            raise SceneError(f"{self.path}: no such file", "scene")
        self.info = read_model_info(self.path)
        self.threads = threads
        prefer_passive_openmp()  # now: the session (and its call) waits for the first frame
        self._model = None
        self.time_range = tuple(float(v) for v in self.info.time_range)
        self.default_background = tuple(float(v) for v in self.info.background)
        self.default_camera = self.info.default_camera
        self.aabb = self.info.aabb
        self.sh_degree = self.info.sh_degree
        counts = self.info.layer_counts
        self.num_layers = len(counts)
        self.lod = lod
        if lod is not None and not 0 <= lod < self.num_layers:
            raise SceneError(f"{{lod}} {lod}: {self.path} has {self.num_layers} layer(s), "
                             f"0..{self.num_layers - 1}", "lod")
        self.num_gaussians = sum(counts[:lod + 1]) if lod is not None else self.info.num_gaussians

    @property
    def model(self):
        if self._model is None:
            from .onnx_model import OnnxModel

            self._model = OnnxModel(self.path, threads=self.threads)
        return self._model

    def gaussians(self, time=None):
        return self.model.gaussians(self.middle_time() if time is None else time,
                                    max_layer=self.lod)

    def describe(self) -> str:
        layers = f"layers 0..{self.lod} of {self.num_layers}, " if self.lod is not None else ""
        return (f"model {self.path.name}: {layers}{self.num_gaussians} Gaussians, SH degree "
                f"{self.sh_degree}")


class LayeredScene(Scene):
    """A folder written by ``nehad export --split-layers``: base.onnx plus the enhancement
    layers' chunks. The longest intact prefix of layers (up to `lod`) is drawn; `problems` says
    which chunk was missing or damaged."""

    kind = "layers"

    def __init__(self, path, lod: int | None = None, threads: int | None = None):
        super().__init__(path)
        from .layers import LayeredModel

        self.model = LayeredModel(self.path, threads=threads, max_layer=lod)
        m = self.model
        if lod is not None and lod >= m.num_layers:
            raise SceneError(f"{{lod}} {lod}: {self.path} has {m.num_layers} layer(s), "
                             f"0..{m.num_layers - 1}", "lod")
        self.time_range = tuple(float(v) for v in m.time_range)
        self.default_background = tuple(float(v) for v in m.background)
        self.default_camera = m.default_camera
        self.aabb = getattr(m.base, "aabb", None)
        self.sh_degree = m.sh_degree
        self.num_gaussians = m.num_gaussians
        self.num_layers = m.num_layers
        self.problems = list(m.problems)

    def gaussians(self, time=None):
        return self.model.gaussians(self.middle_time() if time is None else time)

    def describe(self) -> str:
        m = self.model
        return (f"layers {self.path.name}: layers 0..{m.loaded_layers - 1} of {m.num_layers}, "
                f"{m.num_gaussians} Gaussians, SH degree {self.sh_degree}")

    def digest(self) -> str:
        return file_sha256(self.path / "manifest.json")  # it holds every chunk's sha256


def _load_opener(spec: str):
    module, _, name = spec.partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        if isinstance(e, ImportError) and e.name and e.name.split(".")[0] in ("torch", "onnx"):
            raise  # a runtime-only install: the caller says which extra to install
        raise SceneError(f"scene opener {spec!r} cannot be loaded ({e})") from None


def open_scene(path, lod: int | None = None, threads: int | None = None,
               openers: tuple[str, ...] = ()) -> Scene:
    """The scene at `path` (module doc). `threads`: onnxruntime's intra-op threads;
    `openers`: ``"module:function"`` names of openers for folders the runtime cannot read
    itself (a training run)."""
    p = Path(path)
    if lod is not None and lod < 0:
        raise SceneError(f"{{lod}} {lod}: must be >= 0", "lod")
    from .values import MAX_THREADS, count_problem

    why = count_problem(threads, 0, MAX_THREADS)
    if why:  # checked here, not at the model's first draw (`nehad view` opens it on a request)
        raise SceneError(f"{{threads}} {threads}: {why}", "threads")
    if p.is_dir():
        if (p / "manifest.json").is_file():
            return LayeredScene(p, lod=lod, threads=threads)
        for spec in openers:
            scene = _load_opener(spec)(p, lod, threads)
            if scene is not None:
                return scene
        if (p / "model.pt").is_file():
            raise SceneError(f"{p}: a training run, which needs the training package to draw; "
                             f"export it (nehad export) and use the .onnx", "scene")
        raise SceneError(f"{p}: not a finished training run (no model.pt) and not a split "
                         f"layers folder (no manifest.json)", "scene")
    suffix = p.suffix.lower()
    if p.exists() and not p.is_file():
        # a FIFO would block the open until someone writes to it, /dev/zero never ends
        raise SceneError(f"{p}: not a regular file (a device, FIFO or socket)", "scene")
    if suffix == ".ply":
        return PlyScene(p, lod=lod)
    if suffix == ".onnx":
        return OnnxScene(p, lod=lod, threads=threads)
    if not p.exists():
        raise SceneError(f"{p}: no such file or directory", "scene")
    raise SceneError(f"{p}: unknown scene type {suffix or '(no extension)'!r} (expected a 3DGS "
                     f".ply file, an exported .onnx model, a split layers folder or a training "
                     f"run folder)", "scene")


#: The largest time a model takes (its time input is float32; beyond, it would be infinite).
FLOAT32_MAX = 3.4028234663852886e38


def check_time(scene, t: float, extrapolate: bool = False, what: str | None = None) -> float:
    """`t` as a float, or SceneError when it is not finite or lies outside the trained time
    range of `scene` (a Scene, or anything with a `time_range`, or a (lo, hi) pair) unless
    `extrapolate`. The one time check of every command; `what` names the input in the message
    (default: ``{time} T``)."""
    lo, hi = getattr(scene, "time_range", scene)
    if what is None:
        what = f"{{time}} {t:g}" if isinstance(t, (int, float)) else f"{{time}} {t}"
    if t is None or not math.isfinite(t):
        raise SceneError(f"{what}: not a finite number", "time")
    if abs(t) > FLOAT32_MAX:
        raise SceneError(f"{what}: beyond the float32 range of a model's time input "
                         f"(|t| <= {FLOAT32_MAX:.4g})", "time")
    if not extrapolate and not (lo - 1e-9 <= t <= hi + 1e-9):
        raise SceneError(f"{what}: time {t:g} is outside the trained time range [{lo:g}, "
                         f"{hi:g}] (allow it with {{extrapolate}})", "time")
    return float(t)


def scene_time(scene: Scene, camera, time: float | None, extrapolate: bool = False):
    """The time to draw `scene` at: `time`, else the camera's own (a D-NeRF frame's), checked
    by :func:`check_time`; None for a static scene."""
    if not scene.dynamic:
        return None
    t = time if time is not None else getattr(camera, "time", None)
    if t is None:
        raise SceneError(f"{scene.path}: a dynamic scene needs a {{time}} (the camera has none)",
                         "time")
    return check_time(scene, t, extrapolate)


def choose_camera(scene: Scene | None, view: str | None = None, size=None):
    """The one camera of a still: `view` (a camera file, FILE:K, or "default"), else the
    scene's default camera (an exported model's metadata, a run's first test camera); resized
    to `size` (W, H) with the same field of view."""
    from .cameras import load_view

    if view is not None and view != "default":
        cam = load_view(view)  # a CameraError names the file and the field
        if isinstance(cam, list):
            if len(cam) != 1:
                raise SceneError(f"{{view}} {view}: the file holds {len(cam)} cameras; pick one "
                                 f"with a frame index, e.g. {view}:0", "view")
            cam = cam[0]
    else:
        cam = getattr(scene, "default_camera", None)
        if cam is None:
            where = scene.path if scene is not None else "the scene"
            raise SceneError(f"{where}: no default camera; give a camera ({{view}})", "view")
    return cam.with_size(*size) if size is not None else cam


__all__ = ["Scene", "SceneError", "PlyScene", "OnnxScene", "LayeredScene", "open_scene",
           "check_time", "scene_time", "choose_camera"]
