"""Camera paths and time schedules for videos (issue 5; conventions of docs/design.md sections 3 and 3.1).

A video is a list of frames, each a :class:`~nehad.runtime.cameras.Camera` at a time t. Two small
text syntaxes describe it (the CLI's ``--path`` and ``--time``, the keys ``path`` and ``time`` of
a jobs.yaml):

``--path`` (:func:`parse_path_spec`):

=============================  ===================================================================
``orbit[:k=v,...]``            a circle around the scene, looking at its centre. Centre, radius,
                               elevation and up direction are derived from reference cameras: the
                               model's default camera, or ``from=DATA`` (a dataset folder: its
                               train cameras) / ``from=cams.json`` (any camera file). Keys override
                               them: ``centre=[x,y,z]``, ``radius=R``, ``elevation=DEG``,
                               ``up=[x,y,z]`` (or ``z``, ``-y``, ...), ``turns=1``,
                               ``start=DEG`` (azimuth of frame 0), ``fov=DEG`` (horizontal).
``spiral[:k=v,...]``           the orbit's keys plus ``amplitude=DEG`` (elevation swing, default
                               15) and ``zoom=F`` (radius swing as a fraction, default 0.2);
                               ``turns`` defaults to 2.
``default``                    the model's default camera, frozen (sweep t: "freeze the camera").
``FILE`` / ``FILE:K``          a camera file (docs/design.md section 3.1): a cam.json list, a 3DGS cameras.json, a
                               D-NeRF/nerfstudio transforms file; ``:K`` picks one camera (frozen).
``DATA:SPLIT``                 a dataset folder in the D-NeRF layout and a split (``test``, ``val``,
                               ``train``): each view at its own time, with its ground-truth image
                               (for the side-by-side mode).
=============================  ===================================================================

``--time`` (:func:`parse_time_spec`): ``A:B`` sweeps t from A to B over the frames (the default,
over the model's time range, unless every camera of the path has its own time, as dataset views
do: then each frame is rendered at its view's time); ``T`` freezes t (bullet time); ``own`` asks
for the views' own times explicitly.

Every problem raises :class:`PathError` whose message names the spec and the key. Numpy only.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cameras import Camera, CameraError, frame_image_path, load_view
from .errors import InputProblem

__all__ = ["PathError", "PathSpec", "TimeSpec", "PlannedFrame", "Reference", "OrbitParams",
           "parse_path_spec", "parse_time_spec", "look_at", "orbit_params_from_cameras",
           "orbit_cameras", "spiral_cameras", "plan_frames", "check_time", "DEFAULT_FRAMES",
           "KINDS", "SPLITS", "nearest_point_to_axes"]

#: Frames of a generated path (orbit, spiral, a frozen camera) when --frames is not given.
DEFAULT_FRAMES = 120
KINDS = ("orbit", "spiral", "default")
SPLITS = ("train", "val", "test")

_ORBIT_KEYS = ("centre", "center", "radius", "elevation", "up", "turns", "start", "fov", "from")
_SPIRAL_KEYS = _ORBIT_KEYS + ("amplitude", "zoom")
_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}


class PathError(InputProblem):
    """A camera path or time schedule that cannot be used; the message names the spec and key."""


# ---------------------------------------------------------------------------------------------
# specs


@dataclass(frozen=True)
class PathSpec:
    """A parsed ``--path``: `kind` is orbit, spiral, default, file or dataset."""

    text: str
    kind: str
    options: dict = field(default_factory=dict)  # orbit/spiral keys, values parsed
    file: str | None = None  # kind file: the camera file (with its ``:K`` suffix, if any)
    data: Path | None = None  # kind dataset: the folder
    split: str | None = None  # kind dataset: the split


@dataclass(frozen=True)
class TimeSpec:
    """A parsed ``--time``: `mode` is sweep (start..end), freeze (start) or own."""

    text: str
    mode: str
    start: float | None = None
    end: float | None = None


def _split_options(text: str, spec: str) -> list[str]:
    """Split ``k=v,k=[a,b,c]`` at the commas outside brackets."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
            if depth < 0:
                raise PathError(f"{spec}: unbalanced ']'")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    if depth:
        raise PathError(f"{spec}: unbalanced '['")
    parts.append(cur)
    return [p.strip() for p in parts if p.strip()]


def _float(value: str, key: str, spec: str) -> float:
    try:
        v = float(value)
    except ValueError:
        raise PathError(f"{spec}: {key}={value}: not a number") from None
    if not math.isfinite(v):
        raise PathError(f"{spec}: {key}={value}: not a finite number")
    return v


def _vector(value: str, key: str, spec: str, axis_ok: bool = False) -> np.ndarray:
    v = value.strip()
    if axis_ok:
        m = re.fullmatch(r"([+-]?)([xyz])", v.lower())
        if m:
            return np.array(_AXES[m.group(2)], np.float64) * (-1.0 if m.group(1) == "-" else 1.0)
    inner = v[1:-1] if v.startswith("[") and v.endswith("]") else v
    items = [s for s in re.split(r"[,\s]+", inner.strip()) if s]
    if len(items) != 3:
        hint = ", or an axis like z or -y" if axis_ok else ""
        raise PathError(f"{spec}: {key}={value}: expected three numbers [x,y,z]{hint}")
    out = np.array([_float(s, key, spec) for s in items], np.float64)
    if not np.abs(out).max() <= 1e9:
        raise PathError(f"{spec}: {key}={value}: each number must be within +-1e9")
    return out


def _parse_generated(kind: str, rest: str, spec: str) -> dict:
    allowed = _SPIRAL_KEYS if kind == "spiral" else _ORBIT_KEYS
    opts: dict = {}
    for part in _split_options(rest, spec):
        if "=" not in part:
            raise PathError(f"{spec}: {part!r} is not key=value (keys: {', '.join(allowed)})")
        key, value = (s.strip() for s in part.split("=", 1))
        key = key.lower()
        if key not in allowed:
            raise PathError(f"{spec}: unknown key {key!r} for {kind} (keys: {', '.join(allowed)})")
        if key == "center":
            key = "centre"
        if key in opts:
            raise PathError(f"{spec}: key {key!r} given twice")
        if key == "centre":
            opts[key] = _vector(value, key, spec)
        elif key == "up":
            up = _vector(value, key, spec, axis_ok=True)
            n = float(np.linalg.norm(up))
            if n < 1e-9:
                raise PathError(f"{spec}: up={value}: must not be the zero vector")
            opts[key] = up / n
        elif key == "from":
            if not value:
                raise PathError(f"{spec}: from=: expected a dataset folder or a camera file")
            opts[key] = value
        else:
            v = _float(value, key, spec)
            if key == "radius" and not 0 < v <= 1e9:
                raise PathError(f"{spec}: radius={value}: must be positive, at most 1e9")
            if key in ("turns", "start") and not abs(v) <= 1e6:
                raise PathError(f"{spec}: {key}={value}: must be within +-1e6")
            if key == "elevation" and not -90 < v < 90:
                raise PathError(f"{spec}: elevation={value}: must be in (-90, 90) degrees")
            if key == "fov" and not 0 < v < 180:
                raise PathError(f"{spec}: fov={value}: must be in (0, 180) degrees")
            if key == "zoom" and not 0 <= v < 1:
                raise PathError(f"{spec}: zoom={value}: must be in [0, 1)")
            if key == "amplitude" and not 0 <= v < 90:
                raise PathError(f"{spec}: amplitude={value}: must be in [0, 90) degrees")
            opts[key] = v
    return opts


def parse_path_spec(text) -> PathSpec:
    """Parse a ``--path`` (see the module doc). Only the syntax and the existence of the named
    file or folder are checked here; cameras are read by :func:`plan_frames`."""
    spec = str(text).strip()
    if not spec:
        raise PathError("empty camera path (expected orbit, spiral, default, a camera file or "
                        "DATA:SPLIT)")
    kind, _, rest = spec.partition(":")
    if kind.lower() in ("orbit", "spiral") and not os.path.exists(spec):
        return PathSpec(spec, kind.lower(), _parse_generated(kind.lower(), rest, spec))
    if spec.lower() == "default" and not os.path.exists(spec):
        return PathSpec(spec, "default")
    head, sep, tail = spec.rpartition(":")
    if sep and head and os.path.isdir(head):
        if tail not in SPLITS:
            raise PathError(f"{spec}: unknown split {tail!r} (expected one of {', '.join(SPLITS)})")
        return PathSpec(spec, "dataset", data=Path(head), split=tail)
    if os.path.isdir(spec):
        raise PathError(f"{spec}: a dataset folder needs a split, e.g. {spec}:test")
    m = re.match(r"^(.*\.json)[:#]([^:#/\\]*)$", spec, re.IGNORECASE)  # the index is checked later
    if os.path.isfile(spec) or (m and os.path.isfile(m.group(1))):
        return PathSpec(spec, "file", file=spec)
    raise PathError(f"{spec}: not a path kind (orbit, spiral, default), an existing camera file "
                    f"(FILE or FILE.json:K) or a dataset split (DATA:test)")


def parse_time_spec(text) -> TimeSpec:
    """Parse a ``--time``: ``A:B`` (sweep), ``T`` (freeze) or ``own``."""
    spec = str(text).strip()
    if spec.lower() == "own":
        return TimeSpec(spec, "own")
    if ":" in spec:
        a, b = spec.split(":", 1)
        start, end = _time_value(a, spec), _time_value(b, spec)
        return TimeSpec(spec, "sweep", start, end)
    return TimeSpec(spec, "freeze", _time_value(spec, spec))


def _time_value(s: str, spec: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise PathError(f"{spec}: expected a time T, a sweep A:B or 'own'; {s.strip()!r} is not "
                        f"a number") from None
    if not math.isfinite(v):
        raise PathError(f"{spec}: times must be finite numbers")
    return v


# ---------------------------------------------------------------------------------------------
# geometry


def look_at(eye, target, up) -> np.ndarray:
    """World-to-camera (4x4, OpenCV axes: x right, y down, z forward) of a camera at `eye`
    looking at `target` with `up` (world) pointing up in the image (docs/design.md section 3)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        raise PathError("look_at: the camera sits on its target")
    z = z / nz
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise PathError("look_at: the view direction is parallel to the up direction "
                        "(elevation of +-90 degrees)")
    x = x / nx
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _camera_up(cam: Camera) -> np.ndarray:
    """World direction of the image's up (-y of the OpenCV camera)."""
    return -cam.world_to_camera[1, :3]


def _camera_forward(cam: Camera) -> np.ndarray:
    return cam.world_to_camera[2, :3].copy()


def _snap_axis(v: np.ndarray) -> np.ndarray:
    i = int(np.argmax(np.abs(v)))
    out = np.zeros(3)
    out[i] = 1.0 if v[i] >= 0 else -1.0
    return out


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to `up` (right-handed with it)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - up * float(a @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return e1, e2


@dataclass
class OrbitParams:
    """A circle around `centre` in the plane perpendicular to `up`, at `radius`, `elevation`
    (degrees above that plane) starting at azimuth `start` (degrees), and the intrinsics of the
    reference camera (width, height, fx, fy)."""

    centre: np.ndarray
    up: np.ndarray
    radius: float
    elevation: float
    start: float
    width: int
    height: int
    fx: float
    fy: float


def nearest_point_to_axes(centres: np.ndarray, directions: np.ndarray) -> np.ndarray | None:
    """The point nearest every line ``centre + s direction`` (unit directions; least squares):
    where cameras look together. None when the lines are (nearly) parallel."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, directions):
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
    if not np.linalg.cond(a) < 1e6:
        return None
    return np.linalg.solve(a, b)


def orbit_params_from_cameras(cameras: list[Camera], aabb=None) -> OrbitParams:
    """Orbit parameters derived from reference (training) cameras.

    Several cameras: up is their mean image-up direction, the centre is the point nearest to all
    optical axes (least squares), radius and elevation the medians over the cameras. One camera:
    up is its image-up snapped to the nearest world axis and the centre the point of its optical
    axis nearest to the scene box's centre (`aabb`, (2, 3)), else to the world origin.
    """
    cams = list(cameras)
    if not cams:
        raise PathError("no reference camera to derive the orbit from")
    centres = np.stack([c.centre for c in cams])
    dirs = np.stack([_camera_forward(c) for c in cams])
    up = np.mean([_camera_up(c) for c in cams], axis=0)
    if len(cams) == 1 or np.linalg.norm(up) < 0.3:
        up = _snap_axis(_camera_up(cams[0]))
    up = up / np.linalg.norm(up)
    centre = nearest_point_to_axes(centres, dirs) if len(cams) > 1 else None
    if centre is None:
        target = np.zeros(3) if aabb is None else np.asarray(aabb, np.float64).reshape(2, 3).mean(0)
        c, d = centres[0], dirs[0]
        depth = float((target - c) @ d)
        if depth <= 1e-6:
            depth = max(float(np.linalg.norm(target - c)), 1.0)
        centre = c + depth * d
    rel = centres - centre
    dist = np.linalg.norm(rel, axis=1)
    radius = float(np.median(dist))
    if not radius > 1e-9:
        raise PathError("the reference cameras sit at the orbit centre; give radius= and centre=")
    elev = np.degrees(np.arcsin(np.clip((rel @ up) / np.maximum(dist, 1e-12), -1, 1)))
    e1, e2 = _basis(up)
    start = math.degrees(math.atan2(float(rel[0] @ e2), float(rel[0] @ e1)))
    ref = cams[0]
    return OrbitParams(centre, up, radius, float(np.median(elev)), start, ref.width, ref.height,
                       ref.fx, ref.fy)


def _orbit_camera(p: OrbitParams, azimuth: float, elevation: float, radius: float,
                  name: str) -> Camera:
    e1, e2 = _basis(p.up)
    az, el = math.radians(azimuth), math.radians(elevation)
    eye = p.centre + radius * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2)
                               + math.sin(el) * p.up)
    w2c = look_at(eye, p.centre, p.up)
    return Camera(p.width, p.height, p.fx, p.fy, p.width / 2, p.height / 2, w2c, None, name)


def orbit_cameras(p: OrbitParams, n: int, turns: float = 1.0) -> list[Camera]:
    """`n` cameras on the circle; azimuth start + 360 turns k / n (a closed loop)."""
    return [_orbit_camera(p, p.start + 360.0 * turns * k / n, p.elevation, p.radius, f"orbit {k}")
            for k in range(n)]


def spiral_cameras(p: OrbitParams, n: int, turns: float = 2.0, amplitude: float = 15.0,
                   zoom: float = 0.2) -> list[Camera]:
    """`n` cameras circling `turns` times while the elevation swings by +-`amplitude` degrees
    and the radius by +-`zoom` (a fraction), one period over the path."""
    out = []
    for k in range(n):
        s = 2 * math.pi * k / n
        el = float(np.clip(p.elevation + amplitude * math.sin(s), -89.0, 89.0))
        out.append(_orbit_camera(p, p.start + 360.0 * turns * k / n, el,
                                 p.radius * (1 + zoom * math.sin(s)), f"spiral {k}"))
    return out


# ---------------------------------------------------------------------------------------------
# planning


@dataclass(frozen=True)
class Reference:
    """What the scene offers to plan a path: its default camera, box, time range (None for a
    static scene)."""

    default_camera: Camera | None = None
    aabb: np.ndarray | None = None
    time_range: tuple[float, float] | None = (0.0, 1.0)


@dataclass(frozen=True)
class PlannedFrame:
    """One frame of a video: `index`, `camera`, `time` (None for a static scene) and the
    ground-truth image of a dataset view (None otherwise)."""

    index: int
    camera: Camera
    time: float | None
    ground_truth: str | None = None


def _reference_cameras(value: str, spec: str) -> list[Camera]:
    """Cameras of a ``from=`` value: a dataset folder (its train split) or a camera file."""
    p = Path(value)
    try:
        if p.is_dir():
            for split in ("train", "test", "val"):
                if (p / f"transforms_{split}.json").is_file():
                    cams = load_view(p / f"transforms_{split}.json")
                    break
            else:
                raise PathError(f"{spec}: from={value}: no transforms_train.json in the folder")
        else:
            cams = load_view(value)
    except CameraError as e:
        raise PathError(f"{spec}: from={value}: {e}") from None
    return cams if isinstance(cams, list) else [cams]


def _dataset_frames(spec: PathSpec) -> tuple[list[Camera], list[str]]:
    """The cameras of a D-NeRF split and the paths of its images (the ground truth)."""
    transforms = spec.data / f"transforms_{spec.split}.json"
    if not transforms.is_file():
        raise PathError(f"{spec.text}: {spec.data} has no transforms_{spec.split}.json "
                        f"(a D-NeRF layout folder is expected)")
    try:
        cams = load_view(transforms)
        cams = cams if isinstance(cams, list) else [cams]
        paths = [str(frame_image_path(transforms, k)) for k in range(len(cams))]
    except CameraError as e:
        raise PathError(f"{spec.text}: {e}") from None
    if not cams:
        raise PathError(f"{spec.text}: the split holds no frames")
    return cams, paths


def _path_cameras(spec: PathSpec, frames: int | None, ref: Reference):
    """(cameras, ground-truth paths or None, kind of list) of a path spec; the kind is
    "generated" (already `frames` long), "frozen" (one camera, repeated) or "list"."""
    if spec.kind in ("orbit", "spiral"):
        o = spec.options
        if "from" in o:
            cams = _reference_cameras(o["from"], spec.text)
        elif ref.default_camera is not None:
            cams = [ref.default_camera]
        elif "centre" in o and "radius" in o:
            cams = []
        else:
            raise PathError(f"{spec.text}: the scene has no default camera to derive the orbit "
                            f"from; give from=DATA (a dataset folder or camera file), or centre= "
                            f"and radius= (and fov=)")
        if cams:
            p = orbit_params_from_cameras(cams, ref.aabb)
        else:
            p = OrbitParams(np.zeros(3), np.array([0.0, 0.0, 1.0]), 1.0, 20.0, 0.0, 800, 800,
                            0.0, 0.0)
        if "up" in o:
            p.up = o["up"]
        if "centre" in o:
            p.centre = o["centre"]
        if "radius" in o:
            p.radius = o["radius"]
        if "elevation" in o:
            p.elevation = o["elevation"]
        if "start" in o:
            p.start = o["start"]
        fov = o.get("fov", None if cams else 50.0)
        if fov is not None:
            p.fx = p.fy = 0.5 * p.width / math.tan(math.radians(fov) / 2)
        n = frames or DEFAULT_FRAMES
        if spec.kind == "orbit":
            cams = orbit_cameras(p, n, o.get("turns", 1.0))
        else:
            cams = spiral_cameras(p, n, o.get("turns", 2.0), o.get("amplitude", 15.0),
                                  o.get("zoom", 0.2))
        return cams, None, "generated"
    if spec.kind == "default":
        if ref.default_camera is None:
            raise PathError(f"{spec.text}: the scene has no default camera (give a camera file)")
        return [ref.default_camera], None, "frozen"
    if spec.kind == "dataset":
        cams, gts = _dataset_frames(spec)
        return cams, gts, "list"
    try:
        cams = load_view(spec.file)
    except CameraError as e:
        raise PathError(str(e)) from None
    if isinstance(cams, list):
        return cams, None, "list"
    return [cams], None, "frozen"


def check_time(t: float, ref: Reference, extrapolate: bool, what: str) -> float:
    """`t`, or an error when it lies outside the trained range and `extrapolate` is off: the
    scene's one time check (runtime/scene.py), as a PathError."""
    from .scene import SceneError, check_time as check_scene_time

    try:
        return check_scene_time(ref.time_range, t, extrapolate, what)
    except SceneError as e:
        raise PathError(e.template, "time") from None


def plan_frames(path: PathSpec | str, time: TimeSpec | str | None = None,
                frames: int | None = None, size: tuple[int, int] | None = None,
                reference: Reference | None = None,
                extrapolate: bool = False, labels: dict | None = None) -> list[PlannedFrame]:
    """The frames of a video: cameras from `path`, times from `time` (module doc), resized to
    `size` (W, H; same field of view) when given.

    `frames`: the frame count of a generated path or a frozen camera (default
    :data:`DEFAULT_FRAMES`); a camera list has its own count (a different `frames` is an error).
    `reference`: the scene's default camera, box and time range (None range: a static scene,
    every time is None).
    `labels` names the inputs in messages (default: the placeholders of runtime/errors.py,
    ``{path}``, ``{time}``, ``{frames}``, ``{extrapolate}``, which each caller shows in its words).
    """
    lab = {"path": "{path}", "time": "{time}", "frames": "{frames}",
           "extrapolate": "{extrapolate}", **(labels or {})}
    ref = reference or Reference()
    spec = path if isinstance(path, PathSpec) else parse_path_spec(path)
    tspec = time if isinstance(time, TimeSpec) or time is None else parse_time_spec(time)
    if frames is not None and int(frames) < 1:
        raise PathError(f"frames {frames}: must be at least 1")
    if frames is not None:
        from .memory import check_plan_memory

        check_plan_memory(int(frames), f"{lab['frames']} {frames}")
    try:
        cams, gts, kind = _path_cameras(spec, frames, ref)
    except PathError as e:
        raise PathError(f"{lab['path']} {e.template}") from None
    if kind == "frozen":
        n = frames or DEFAULT_FRAMES
        if frames is None and (ref.time_range is None or (tspec is not None
                                                          and tspec.mode == "freeze")):
            n = 1  # nothing moves: one frame unless asked for more
        cams = cams * n
    elif kind == "list":
        if frames is not None and frames != len(cams):
            raise PathError(f"{lab['path']} {spec.text}: the path holds {len(cams)} cameras; "
                            f"{lab['frames']} {frames} does not match (leave it out)")
    n = len(cams)
    if ref.time_range is None:
        times = [None] * n
    else:
        own = [c.time for c in cams]
        # default: the views' own times, except a frozen camera with several frames (sweep t)
        has_own = all(t is not None for t in own)
        mode = tspec.mode if tspec is not None else (
            "own" if has_own and (kind != "frozen" or n == 1) else "sweep")
        if mode == "own":
            if any(t is None for t in own):
                raise PathError(f"{lab['time']} own: some cameras of {lab['path']} {spec.text} "
                                f"have no time")
            times = [check_time(float(t), ref, extrapolate, f"{lab['path']} {spec.text}")
                     for t in own]
        elif mode == "freeze":
            times = [check_time(tspec.start, ref, extrapolate, f"{lab['time']} {tspec.text}")] * n
        else:
            lo, hi = (tspec.start, tspec.end) if tspec is not None else ref.time_range
            what = f"{lab['time']} {tspec.text}" if tspec is not None else lab["time"]
            check_time(lo, ref, extrapolate, what)
            check_time(hi, ref, extrapolate, what)
            times = [float(v) for v in (np.linspace(lo, hi, n) if n > 1 else [lo])]
    out = []
    for k, cam in enumerate(cams):
        if size is not None:
            cam = cam.with_size(int(size[0]), int(size[1]))
        out.append(PlannedFrame(k, cam, times[k], gts[k] if gts else None))
    return out
