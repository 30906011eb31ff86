"""Pinhole cameras in the conventions of docs/design.md section 3, and the `--view` file of docs/design.md section 3.1.

A :class:`Camera` always stores the world-to-camera transform in OpenCV axes (x right, y down,
z forward). Pixel (i, j) has its centre at (i + 0.5, j + 0.5); a camera-space point (X, Y, Z)
projects to u = fx X/Z + cx, v = fy Y/Z + cy.

Camera descriptions accepted by :func:`parse_camera` / :func:`load_view` (docs/design.md section 3.1):

* cam.json (canonical form, written by :func:`camera_to_dict` / :func:`save_view`)::

    {"width": 800, "height": 800, "fx": 1111.1, "fy": 1111.1, "cx": 400, "cy": 400,
     "camera_to_world": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]], "convention": "opengl",
     "time": 0.5}

  ``cx``/``cy`` default to W/2, H/2. ``fov_x`` (radians, in (0, pi)) may replace ``fx``;
  ``fov_y`` may replace ``fy``; when only one focal length is given through a field of view the
  pixels are square (fx = fy). ``world_to_camera`` may replace ``camera_to_world``; either is
  4x4 (bottom row [0, 0, 0, 1]) or 3x4. ``convention`` is ``"opengl"`` (default: Blender/D-NeRF
  axes, y up, z back) or ``"opencv"`` (y down, z forward) and names the axes of the camera frame
  of the given matrix. ``time`` (optional) is the scene time in [0, 1]; ``name`` optional.
* an entry of the 3DGS ``cameras.json`` (``id, img_name, width, height, position, rotation, fx,
  fy``), recognised by its ``position`` and ``rotation`` keys: ``rotation`` is the 3x3
  camera-to-world rotation in OpenCV axes and ``position`` the camera centre.
* a D-NeRF / Blender / nerfstudio transforms file (``frames[k].transform_matrix`` is an OpenGL
  camera-to-world; focal from ``camera_angle_x`` (and ``camera_angle_y``) or ``fl_x``/``fl_y``,
  top level or per frame; size from ``w``/``h`` or, when absent, the header of the frame's image
  next to the json). The frame's ``time`` becomes :attr:`Camera.time`.
* a JSON list of cam.json dicts or 3DGS entries: a camera path.

A frame of a multi-camera file is chosen with ``load_view(path, frame=K)`` or with the suffix
``path.json:K`` in the path string (``path.json#K`` is accepted as well). Every problem raises
:class:`CameraError` naming the file and the field; nothing half-valid comes back.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputProblem
from .images import CAMERA_IMAGE_SUFFIXES, STILL_SUFFIXES

# Blender/NeRF/D-NeRF store camera-to-world with OpenGL axes (y up, z back); negating the
# rotation's columns 1 and 2 turns it into OpenCV axes (docs/design.md section 3).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

ROTATION_TOLERANCE = 1e-4  # |R^T R - I| (max abs) and |det R - 1| allowed in a camera rotation
_BOTTOM_ROW_TOLERANCE = 1e-6
_CONVENTIONS = ("opengl", "opencv")


class CameraError(InputProblem):
    """A camera description is missing a field or holds an invalid value (names the field)."""


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(repr=False)  # (4, 4) float64, OpenCV axes
    time: float | None = None
    name: str = ""

    def __post_init__(self):
        m = np.asarray(self.world_to_camera, dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise CameraError(f"world_to_camera: expected a 4x4 matrix, got shape {m.shape}")
        object.__setattr__(self, "world_to_camera", m)

    @classmethod
    def from_camera_to_world(cls, camera_to_world, width, height, fx, fy, cx=None, cy=None,
                             convention="opengl", time=None, name=""):
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        if convention == "opengl":
            c2w = c2w @ _GL_TO_CV
        elif convention != "opencv":
            raise CameraError(f"convention: expected 'opengl' or 'opencv', got {convention!r}")
        w2c = np.linalg.inv(c2w)
        return cls(int(width), int(height), float(fx), float(fy),
                   float(width) / 2 if cx is None else float(cx),
                   float(height) / 2 if cy is None else float(cy), w2c, time, name)

    @property
    def camera_to_world(self) -> np.ndarray:
        """Camera-to-world in OpenCV axes."""
        return np.linalg.inv(self.world_to_camera)

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        r = self.world_to_camera[:3, :3]
        return -r.T @ self.world_to_camera[:3, 3]

    @property
    def fov_x(self) -> float:
        return float(2 * np.arctan(self.width / (2 * self.fx)))

    @property
    def fov_y(self) -> float:
        return float(2 * np.arctan(self.height / (2 * self.fy)))

    @property
    def camera_to_world_opengl(self) -> np.ndarray:
        """Camera-to-world with OpenGL camera axes (the Blender/D-NeRF `transform_matrix`)."""
        return _rigid_inverse(self.world_to_camera) @ _GL_TO_CV

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) -> (pixel coordinates (N, 2), view depth z (N,)).

        Follows docs/design.md section 3: u = fx X/Z + cx, v = fy Y/Z + cy in OpenCV camera axes.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = p @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * cam[:, 0] / z + self.cx, self.fy * cam[:, 1] / z + self.cy], 1)
        return uv, z

    def isclose(self, other: "Camera", atol: float = 1e-9) -> bool:
        """Same size, intrinsics, pose (to `atol`) and time."""
        return (self.width == other.width and self.height == other.height
                and np.allclose([self.fx, self.fy, self.cx, self.cy],
                                [other.fx, other.fy, other.cx, other.cy], rtol=0, atol=atol)
                and np.allclose(self.world_to_camera, other.world_to_camera, rtol=0, atol=atol)
                and (self.time is None) == (other.time is None)
                and (self.time is None or abs(self.time - other.time) <= atol))

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 for half resolution)."""
        return self.with_size(int(round(self.width * factor)), int(round(self.height * factor)))

    def with_size(self, width: int, height: int) -> "Camera":
        """The same field of view rendered at another image size."""
        sx, sy = width / self.width, height / self.height
        return Camera(int(width), int(height), self.fx * sx, self.fy * sy, self.cx * sx,
                      self.cy * sy, self.world_to_camera, self.time, self.name)


# ---------------------------------------------------------------------------------------------
# validation helpers (every message: "<source>: <field>: <problem>")


def _parse_failure(e: BaseException) -> str:
    """A parser's failure in a few words (RecursionError's own message names Python's stack)."""
    return "nested too deeply" if isinstance(e, RecursionError) else str(e)[:200]


def _err(source: str, fld: str, problem: str) -> CameraError:
    prefix = f"{source}: " if source else ""
    return CameraError(f"{prefix}{fld}: {problem}")


def _number(obj: dict, key: str, source: str, *, fld: str | None = None) -> float:
    fld = fld or key
    if key not in obj:
        raise _err(source, fld, "missing field")
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(source, fld, f"expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise _err(source, fld, f"must be finite, got {v}")
    return v


def _positive(obj: dict, key: str, source: str, *, fld: str | None = None) -> float:
    v = _number(obj, key, source, fld=fld)
    if v <= 0:
        raise _err(source, fld or key, f"must be positive, got {v:g}")
    return v


def _size(obj: dict, key: str, source: str, *, fld: str | None = None) -> int:
    v = _positive(obj, key, source, fld=fld)
    if v != int(v):
        raise _err(source, fld or key, f"must be a whole number of pixels, got {v:g}")
    return int(v)


def _fov(obj: dict, key: str, source: str, *, fld: str | None = None) -> float:
    v = _number(obj, key, source, fld=fld)
    if not 0 < v < math.pi:
        raise _err(source, fld or key, f"field of view must be in (0, pi) radians, got {v:g}")
    return v


def _matrix(value, fld: str, source: str, shapes=((4, 4), (3, 4))) -> np.ndarray:
    """A numeric matrix of one of `shapes`, finite; 3x4 is completed to 4x4."""
    if isinstance(value, (str, bytes, dict)) or value is None:
        raise _err(source, fld, f"expected a matrix (list of rows), got {type(value).__name__}")
    try:
        rows = [list(r) for r in value]
    except TypeError:
        raise _err(source, fld, "expected a matrix (list of rows)") from None
    for r in rows:
        for v in r:
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
                raise _err(source, fld, f"expected numbers, got {v!r}")
    if len({len(r) for r in rows}) > 1:
        raise _err(source, fld, "rows of different lengths")
    m = np.asarray(rows, dtype=np.float64)
    if m.shape not in shapes:
        want = " or ".join(f"{a}x{b}" for a, b in shapes)
        got = "x".join(map(str, m.shape))
        raise _err(source, fld, f"expected a {want} matrix, got {got}")
    bad = ~np.isfinite(m)
    if bad.any():
        raise _err(source, fld, f"{int(bad.sum())} entries are NaN or infinite")
    if m.shape == (4, 4):
        if np.abs(m[3] - [0, 0, 0, 1]).max() > _BOTTOM_ROW_TOLERANCE:
            raise _err(source, fld, f"bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
        m = m.copy()
        m[3] = [0, 0, 0, 1]
    elif m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return m


def check_rotation(r: np.ndarray, fld: str, source: str) -> None:
    """CameraError unless `r` is a rotation (orthonormal, det +1, to ROTATION_TOLERANCE): the
    rule of every camera a user gives, a cam.json's and a dataset's (nehad.data.dnerf)."""
    err = np.abs(r.T @ r - np.eye(3)).max()
    det = float(np.linalg.det(r))
    if err > ROTATION_TOLERANCE or abs(det - 1) > ROTATION_TOLERANCE:
        if err <= ROTATION_TOLERANCE:
            raise _err(source, fld, f"rotation of {fld} is a reflection (det = {det:.6g}, must be +1)")
        raise _err(source, fld, f"rotation of {fld} is not orthonormal "
                   f"(|R^T R - I| = {err:.2g}, det = {det:.6g}; scale or shear is not allowed)")


def _rigid_inverse(m: np.ndarray) -> np.ndarray:
    r, t = m[:3, :3], m[:3, 3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ t
    return out


def _rigid(value, fld: str, source: str) -> np.ndarray:
    m = _matrix(value, fld, source)
    check_rotation(m[:3, :3], fld, source)
    return m


def _convention(obj: dict, source: str) -> str:
    conv = obj.get("convention", "opengl")
    if not isinstance(conv, str) or conv.lower() not in _CONVENTIONS:
        raise _err(source, "convention", f"expected 'opengl' or 'opencv', got {conv!r}")
    return conv.lower()


def _time(obj: dict, source: str, key: str = "time", fld: str | None = None) -> float | None:
    if obj.get(key) is None:
        return None
    return _number(obj, key, source, fld=fld)


def _name(obj: dict, source: str, default: str = "") -> str:
    for key in ("name", "img_name"):
        if key in obj and obj[key] is not None:
            return str(obj[key])
    return default


def _focals(obj: dict, width: int, height: int, source: str, prefix: str = "") -> tuple[float, float]:
    """fx, fy from `fx`/`fy` or `fov_x`/`fov_y` (square pixels when one comes from a fov)."""
    fx = _positive(obj, "fx", source, fld=prefix + "fx") if "fx" in obj else None
    fy = _positive(obj, "fy", source, fld=prefix + "fy") if "fy" in obj else None
    fx_fov = fy_fov = None
    if "fov_x" in obj:
        fx_fov = 0.5 * width / math.tan(0.5 * _fov(obj, "fov_x", source, fld=prefix + "fov_x"))
    if "fov_y" in obj:
        fy_fov = 0.5 * height / math.tan(0.5 * _fov(obj, "fov_y", source, fld=prefix + "fov_y"))
    for explicit, derived, name in ((fx, fx_fov, "fov_x"), (fy, fy_fov, "fov_y")):
        if explicit is not None and derived is not None and abs(explicit - derived) > 1e-6 * explicit:
            raise _err(source, prefix + name, f"disagrees with f{name[-1]} "
                       f"({derived:.9g} from the field of view, {explicit:.9g} given)")
    fx = fx if fx is not None else fx_fov
    fy = fy if fy is not None else fy_fov
    if fx is None and fy is None:
        raise _err(source, prefix + "fx", "missing field (give fx and fy, or fov_x)")
    if fx is None:
        if fy_fov is None:
            raise _err(source, prefix + "fx", "missing field (give fx, or fov_x)")
        fx = fy
    if fy is None:
        if fx_fov is None:
            raise _err(source, prefix + "fy", "missing field (give fy, or fov_y)")
        fy = fx
    return fx, fy


def _principal(obj: dict, key: str, default: float, source: str, prefix: str = "") -> float:
    if obj.get(key) is None:
        return default
    return _number(obj, key, source, fld=prefix + key)


# ---------------------------------------------------------------------------------------------
# parsing


def _is_3dgs_entry(obj: dict) -> bool:
    return "position" in obj and "rotation" in obj and not (
        "camera_to_world" in obj or "world_to_camera" in obj)


def parse_camera(obj: dict, *, source: str = "") -> Camera:
    """One camera from a cam.json dict or a 3DGS ``cameras.json`` entry (docs/design.md section 3.1).

    `source` (e.g. the file name) prefixes every error message. Raises :class:`CameraError`.
    """
    if not isinstance(obj, dict):
        raise _err(source, "camera", f"expected a JSON object, got {type(obj).__name__}")
    if _is_3dgs_entry(obj):
        return _parse_3dgs_entry(obj, source)
    width = _size(obj, "width", source)
    height = _size(obj, "height", source)
    fx, fy = _focals(obj, width, height, source)
    cx = _principal(obj, "cx", width / 2, source)
    cy = _principal(obj, "cy", height / 2, source)
    conv = _convention(obj, source)
    has_c2w, has_w2c = "camera_to_world" in obj, "world_to_camera" in obj
    if has_c2w and has_w2c:
        raise _err(source, "camera_to_world", "give either camera_to_world or world_to_camera, not both")
    if not (has_c2w or has_w2c):
        raise _err(source, "camera_to_world", "missing field (or world_to_camera)")
    if has_c2w:
        c2w = _rigid(obj["camera_to_world"], "camera_to_world", source)
        if conv == "opengl":
            c2w = c2w @ _GL_TO_CV
        w2c = _rigid_inverse(c2w)
    else:
        w2c = _rigid(obj["world_to_camera"], "world_to_camera", source)
        if conv == "opengl":
            w2c = _GL_TO_CV @ w2c
    return Camera(width, height, fx, fy, cx, cy, w2c, _time(obj, source), _name(obj, source))


def _parse_3dgs_entry(obj: dict, source: str) -> Camera:
    """3DGS `cameras.json` entry: rotation = camera-to-world rotation (OpenCV), position = centre."""
    width = _size(obj, "width", source)
    height = _size(obj, "height", source)
    fx, fy = _focals(obj, width, height, source)
    cx = _principal(obj, "cx", width / 2, source)
    cy = _principal(obj, "cy", height / 2, source)
    rot = _matrix(obj["rotation"], "rotation", source, shapes=((3, 3),))
    check_rotation(rot, "rotation", source)
    pos = _matrix([obj["position"]], "position", source, shapes=((1, 3),))[0]
    c2w = np.eye(4)
    c2w[:3, :3] = rot
    c2w[:3, 3] = pos
    name = _name(obj, source, default=str(obj.get("id", "")))
    return Camera(width, height, fx, fy, cx, cy, _rigid_inverse(c2w), _time(obj, source), name)


def _image_size(base: Path, file_path, source: str, fld: str) -> tuple[int, int]:
    """Width and height from the header of the frame's image (no pixels are decoded)."""
    if not isinstance(file_path, str) or not file_path:
        raise _err(source, fld, "missing field (needed for the image size when w/h are absent)")
    p = base / file_path
    candidates = [p] + [p.with_name(p.name + ext) for ext in CAMERA_IMAGE_SUFFIXES]
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise _err(source, fld, f"image {p} not found (give w and h in the transforms file)")
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(found))
    if inp is None:
        raise _err(source, fld, f"cannot read the header of {found} ({oiio.geterror()})")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def _parse_transforms_frame(doc: dict, index: int, base: Path, source: str) -> Camera:
    frames = doc["frames"]
    fr = frames[index]
    pre = f"frames[{index}]."
    if not isinstance(fr, dict):
        raise _err(source, f"frames[{index}]", "expected a JSON object")

    def pick(key):  # per-frame value wins over the top-level one
        if fr.get(key) is not None:
            return fr, pre + key
        if doc.get(key) is not None:
            return doc, key
        return None, key

    src_w, fw = pick("w")
    src_h, fh = pick("h")
    if src_w is not None and src_h is not None:
        width, height = _size(src_w, "w", source, fld=fw), _size(src_h, "h", source, fld=fh)
    elif src_w is not None or src_h is not None:
        missing = fh if src_h is None else fw
        raise _err(source, missing, "missing field (w and h go together)")
    else:
        width, height = _image_size(base, fr.get("file_path"), source, pre + "file_path")

    fx = fy = None
    src, f = pick("fl_x")
    if src is not None:
        fx = _positive(src, "fl_x", source, fld=f)
    src, f = pick("fl_y")
    if src is not None:
        fy = _positive(src, "fl_y", source, fld=f)
    if fx is None:
        src, f = pick("camera_angle_x")
        if src is not None:
            fx = 0.5 * width / math.tan(0.5 * _fov(src, "camera_angle_x", source, fld=f))
    if fy is None:
        src, f = pick("camera_angle_y")
        if src is not None:
            fy = 0.5 * height / math.tan(0.5 * _fov(src, "camera_angle_y", source, fld=f))
    if fx is None and fy is None:
        raise _err(source, "camera_angle_x", "missing field (or fl_x/fl_y)")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy

    src, f = pick("cx")
    cx = width / 2 if src is None else _number(src, "cx", source, fld=f)
    src, f = pick("cy")
    cy = height / 2 if src is None else _number(src, "cy", source, fld=f)

    if "transform_matrix" not in fr:
        raise _err(source, pre + "transform_matrix", "missing field")
    c2w = _rigid(fr["transform_matrix"], pre + "transform_matrix", source) @ _GL_TO_CV
    time = _time(fr, source, fld=pre + "time")
    name = str(fr.get("file_path", "")) or f"frame {index}"
    return Camera(width, height, fx, fy, cx, cy, _rigid_inverse(c2w), time, name)


# FILE.json:K; any K after the colon is taken as the index, so that `:-1` or `:x` is reported as
# a bad index rather than as a missing file
_FRAME_SUFFIX = re.compile(r"^(.*\.json)[:#]([^:#/\\]*)$", re.IGNORECASE)


def _split_frame(path, frame: int | None) -> tuple[Path, int | None]:
    s = os.fspath(path)
    if not os.path.exists(s):
        m = _FRAME_SUFFIX.match(s)
        if m:
            text = m.group(2).strip()
            try:
                suffix = int(text)
            except ValueError:
                if not os.path.exists(m.group(1)):
                    return Path(m.group(1)), frame  # reported as a missing file
                raise CameraError(f"{s}: frame index {text!r} is not a whole number (expected "
                                  f"{m.group(1)}:K with K = 0, 1, ...)") from None
            if frame is not None and frame != suffix:
                raise CameraError(f"{s}: frame index given twice ({suffix} in the path, {frame} as argument)")
            return Path(m.group(1)), suffix
    return Path(s), frame


def _check_index(frame, count: int, source: str, fld: str) -> int:
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise _err(source, fld, f"frame index must be an integer, got {frame!r}")
    if not 0 <= frame < count:
        raise _err(source, fld, f"frame index {frame} out of range (the file holds {count} camera"
                   f"{'s' if count != 1 else ''}: 0..{count - 1})")
    return int(frame)


def load_view(path, frame: int | None = None) -> Camera | list[Camera]:
    """Cameras from a `--view` file (docs/design.md section 3.1).

    `path` is a cam.json (one object -> :class:`Camera`; a list -> a camera path), a 3DGS
    ``cameras.json`` (list), or a D-NeRF/nerfstudio transforms file (``frames``). With a frame
    index -- ``frame=K`` or the path suffix ``file.json:K`` (also ``file.json#K``) -- a single
    :class:`Camera` comes back; without one, a list file gives the whole list. Raises
    :class:`CameraError` naming the file and the field.
    """
    p, frame = _split_frame(path, frame)
    source = str(p)
    if not p.is_file():
        raise CameraError(f"{source}: no such camera file")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise CameraError(f"{source}: cannot read camera file ({e})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise CameraError(f"{source}: malformed JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except (ValueError, RecursionError) as e:  # a 5000-digit number; arrays nested 100k deep
        raise CameraError(f"{source}: malformed JSON ({_parse_failure(e)})") from None

    if isinstance(doc, dict) and "frames" in doc:
        frames = doc["frames"]
        if not isinstance(frames, list) or not frames:
            raise _err(source, "frames", "expected a non-empty list of frames")
        if frame is not None:
            i = _check_index(frame, len(frames), source, "frame")
            return _parse_transforms_frame(doc, i, p.parent, source)
        return [_parse_transforms_frame(doc, i, p.parent, source) for i in range(len(frames))]
    if isinstance(doc, dict):
        if frame is not None:
            _check_index(frame, 1, source, "frame")
        return parse_camera(doc, source=source)
    if isinstance(doc, list):
        if not doc:
            raise CameraError(f"{source}: empty camera list")
        if frame is not None:
            i = _check_index(frame, len(doc), source, "frame")
            return parse_camera(doc[i], source=f"{source}[{i}]")
        return [parse_camera(d, source=f"{source}[{i}]") for i, d in enumerate(doc)]
    raise CameraError(f"{source}: expected a camera object, a list of cameras or a transforms "
                      f"file, got {type(doc).__name__}")


# ---------------------------------------------------------------------------------------------
# writing


def frame_image_path(transforms_path, index: int) -> Path:
    """The image file of frame `index` of a D-NeRF transforms file: ``file_path`` relative to
    the file's folder, with ``.png`` (then ``.jpg``, ``.jpeg``) appended when it has no image
    extension, as D-NeRF writes it (docs/design.md, cameras)."""
    path = Path(transforms_path)
    try:
        doc = json.loads(path.read_text())
        fp = doc["frames"][index].get("file_path")
    except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError,
            RecursionError) as e:
        raise CameraError(f"{path}: frames[{index}].file_path: cannot be read "
                          f"({_parse_failure(e)})") from None
    if not isinstance(fp, str) or not fp:
        raise _err(str(path), f"frames[{index}].file_path", "expected a relative image path")
    base = path.parent / fp
    if base.suffix in CAMERA_IMAGE_SUFFIXES:
        candidates = [base]
    else:
        candidates = [base.with_name(base.name + ext) for ext in STILL_SUFFIXES] + [base]
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise _err(str(path), f"frames[{index}].file_path", f"image {candidates[0]} not found")
    return found


def camera_to_dict(cam: Camera) -> dict:
    """The canonical cam.json form of `cam` (docs/design.md section 3.1; OpenGL camera-to-world)."""
    c2w = cam.camera_to_world_opengl
    d = {"width": int(cam.width), "height": int(cam.height), "fx": float(cam.fx),
         "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
         "camera_to_world": [[float(v) for v in row] for row in c2w], "convention": "opengl"}
    if cam.time is not None:
        d["time"] = float(cam.time)
    if cam.name:
        d["name"] = cam.name
    return d


def save_view(path, cam: Camera | list[Camera]) -> Path:
    """Write one camera (or a camera path) as cam.json, atomically (docs/design.md section 3.1, 10)."""
    from .images import atomic_path

    path = Path(path)
    doc = [camera_to_dict(c) for c in cam] if isinstance(cam, (list, tuple)) else camera_to_dict(cam)
    text = json.dumps(doc, indent=1) + "\n"
    with atomic_path(path, CameraError) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    return path
