"""The base every dataset reader stands on (numpy only): the loaded scene (`DNeRFScene`, one
container for every layout), its frames, `DatasetError`, and the helpers the D-NeRF, HyperNeRF
and DyNeRF readers and the synthetic writers share.

Conventions are those of docs/design.md section 3: cameras are :class:`~nehad.runtime.cameras.Camera`
objects (OpenCV axes, pixel (i, j) centred at (i + 0.5, j + 0.5)); images are float32 (H, W, 3) in
[0, 1]; every problem with a file is a :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nehad.runtime.cameras import Camera
from nehad.runtime.images import atomic_write_bytes, read_image

__all__ = ["DatasetError", "DNeRFScene", "Frame", "read_json", "number", "read_rgb",
           "area_downscale", "downscale_camera", "read_ply_points", "check_scene_args",
           "check_rotation", "find_point_cloud", "distort_normalized", "undistort_normalized",
           "undistortion_maps", "remap", "atomic_write_bytes", "atomic_write_json",
           "check_background", "check_stride"]

#: The cube D-NeRF draws its random initial points in (and the scene bounds without points).
DNERF_INIT_BOUND = 1.3


class DatasetError(ValueError):
    """A dataset file is missing or holds a bad value; the message names the file and field."""


@dataclass
class Frame:
    """One posed image. `camera` carries the frame's normalised time in ``camera.time``."""

    camera: Camera
    image: np.ndarray  # (H, W, 3) float32 in [0, 1], composited over the scene background
    alpha: np.ndarray | None  # (H, W) float32 coverage, None for RGB images
    path: Path  # the image file

    @property
    def time(self) -> float:
        return float(self.camera.time)


@dataclass
class DNeRFScene:
    """A loaded D-NeRF scene: frames per split, background, optional initial points."""

    root: Path
    frames: dict[str, list[Frame]]
    background: tuple[float, float, float]
    initial_points: np.ndarray | None = None  # (M, 3) float32
    initial_colors: np.ndarray | None = None  # (M, 3) float32 in [0, 1]
    time_range: tuple[float, float] = (0.0, 1.0)  # of the normalised times of the loaded frames
    source_time_range: tuple[float, float] = (0.0, 1.0)  # file times that map to 0 and 1
    points_path: Path | None = None
    downscale: int = 1

    def cameras(self, split: str = "train") -> list[Camera]:
        return [f.camera for f in self._split(split)]

    def times(self, split: str = "train") -> np.ndarray:
        return np.array([f.time for f in self._split(split)], dtype=np.float64)

    def _split(self, split: str) -> list[Frame]:
        if split not in self.frames:
            raise KeyError(f"split {split!r} was not loaded (loaded: {', '.join(self.frames)})")
        return self.frames[split]

    @property
    def extent(self) -> float:
        """Scene extent as 3DGS computes it (``getNerfppNorm``): 1.1 x the largest distance of a
        train camera centre from the mean centre (all loaded cameras if train was not loaded).
        Used to scale position learning rates and sigma_s (docs/design.md sections 4 and 5)."""
        frames = self.frames.get("train") or [f for fs in self.frames.values() for f in fs]
        if not frames:
            return 1.0
        centres = np.stack([f.camera.centre for f in frames])
        radius = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()) * 1.1
        return radius if radius > 0 else 1.0

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (min, max) of the initial points, else D-NeRF's [-1.3, 1.3]^3 cube."""
        if self.initial_points is not None and len(self.initial_points):
            return (self.initial_points.min(axis=0).astype(np.float64),
                    self.initial_points.max(axis=0).astype(np.float64))
        b = np.full(3, DNERF_INIT_BOUND)
        return -b, b.copy()


def read_json(path: Path, what: str) -> object:
    """Parsed JSON of `path`; a missing or malformed file is a DatasetError naming it (shared by
    every reader as `nehad.data.common.read_json`)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError, a 5000-digit number
        raise DatasetError(f"{path}: malformed JSON ({exc})") from None
    except RecursionError:
        raise DatasetError(f"{path}: malformed JSON (nested too deeply)") from None


def number(value, path: Path, field_name: str, positive: bool = False) -> float:
    """A finite (optionally positive) number from a dataset file, else a DatasetError naming the
    file and field (shared by every reader as `nehad.data.common.number`)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{path}: field '{field_name}': expected a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise DatasetError(f"{path}: field '{field_name}': expected a finite number, got {x}")
    if positive and x <= 0:
        raise DatasetError(f"{path}: field '{field_name}': expected a positive number, got {x}")
    return x


def area_downscale(img: np.ndarray, f: int) -> np.ndarray:
    """Mean over f x f blocks; a remainder at the right/bottom edge is cropped."""
    h, w, c = img.shape
    h2, w2 = h // f, w // f
    if h2 == 0 or w2 == 0:
        raise DatasetError(f"data.downscale {f}: an image of {w}x{h} pixels has no pixel left "
                           f"(at most {min(w, h)} for these images)")
    return img[: h2 * f, : w2 * f].reshape(h2, f, w2, f, c).mean(axis=(1, 3), dtype=np.float32)


def downscale_camera(cam: Camera, f: int) -> Camera:
    if cam.width % f == 0 and cam.height % f == 0:
        return cam.scaled(1.0 / f)
    # Cropping the remainder keeps the pixel grid origin, so every intrinsic divides by f.
    return dataclasses.replace(cam, width=cam.width // f, height=cam.height // f, fx=cam.fx / f,
                               fy=cam.fy / f, cx=cam.cx / f, cy=cam.cy / f)


# PLY point clouds (x y z and optional colours; the 3DGS Gaussian PLY reader lives elsewhere)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _ply_header(path: Path, data: bytes) -> tuple[list[str], int]:
    """The header lines of a PLY file (before ``end_header``) and where its body starts."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    return data[:end].decode("ascii", errors="replace").splitlines(), body_start


def _ply_elements(path: Path, header: list[str]) -> tuple[str | None, list]:
    """The format and the elements of a PLY header: [name, count, [(prop, type or None for a
    list)]] each."""
    fmt, elements = None, []
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            try:
                elements.append([parts[1], int(parts[2]), []])
            except ValueError:
                raise DatasetError(f"{path}: header: bad element count in {line!r}") from None
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], None))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise DatasetError(f"{path}: header: unsupported property {line!r}")
    return fmt, elements


def _ply_vertex_element(path: Path, fmt, elements) -> int:
    """The index of the vertex element, checked: a known format, x/y/z, no list property and
    at least one point."""
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(f"{path}: header: format: expected ascii or binary, got {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise DatasetError(f"{path}: header: no 'element vertex'")
    vi = names.index("vertex")
    _, count, props = elements[vi]
    prop_names = [p for p, _ in props]
    for axis in ("x", "y", "z"):
        if axis not in prop_names:
            raise DatasetError(f"{path}: element vertex: property '{axis}' missing")
    if any(t is None for _, t in props):
        raise DatasetError(f"{path}: element vertex: list properties are not supported")
    if count <= 0:
        raise DatasetError(f"{path}: element vertex: count is {count}, expected at least one point")
    return vi


def _ply_ascii_columns(path: Path, data: bytes, body_start: int, elements, vi: int) -> dict:
    """The vertex properties of an ascii PLY body, by name (float64 columns)."""
    _, count, props = elements[vi]
    lines = data[body_start:].decode("ascii", errors="replace").splitlines()
    skip = sum(e[1] for e in elements[:vi])
    rows = lines[skip: skip + count]
    if len(rows) < count:
        raise DatasetError(f"{path}: element vertex: expected {count} rows, file has {len(rows)}")
    try:
        table = np.array([r.split() for r in rows], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}: element vertex: rows are not {len(props)} numbers each") from None
    if table.ndim != 2 or table.shape[1] != len(props):
        raise DatasetError(f"{path}: element vertex: rows are not {len(props)} numbers each")
    return {p: table[:, i] for i, (p, _) in enumerate(props)}


def _ply_binary_columns(path: Path, data: bytes, body_start: int, fmt: str, elements,
                        vi: int) -> dict:
    """The vertex properties of a binary PLY body, by name (columns of their stored type)."""
    _, count, props = elements[vi]
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    for name, n, eprops in elements[:vi]:
        if any(t is None for _, t in eprops):
            raise DatasetError(f"{path}: element {name}: list properties before the vertices "
                               f"are not supported")
        offset += n * np.dtype([(p, order + t) for p, t in eprops]).itemsize
    dtype = np.dtype([(p, order + t) for p, t in props])
    if offset + count * dtype.itemsize > len(data):
        raise DatasetError(f"{path}: element vertex: file is truncated "
                           f"({count} vertices of {dtype.itemsize} bytes announced)")
    rec = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return {p: rec[p] for p, _ in props}


def _ply_colours(cols: dict, types: dict) -> np.ndarray | None:
    """(M, 3) colours in [0, 1] from the first colour trio present (integers scaled by their
    type's maximum), or None."""
    for trio in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(c in cols for c in trio):
            rgb = np.stack([cols[c] for c in trio], axis=1).astype(np.float64)
            kind = np.dtype(types[trio[0]])
            if kind.kind in "iu":
                rgb = rgb / float(np.iinfo(kind).max)
            return np.clip(rgb, 0.0, 1.0).astype(np.float32)
    return None


def points_ply_bytes(points: np.ndarray, colours: np.ndarray) -> bytes:
    """A binary PLY of points with uint8 colours (``x y z red green blue``), as
    :func:`read_ply_points` reads it back."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rec = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                       ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["red"], rec["green"], rec["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    return header.encode("ascii") + rec.tobytes()


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices of an ascii or binary PLY file: (M, 3) float32 points, (M, 3) colours in [0, 1]."""
    data = path.read_bytes()
    header, body_start = _ply_header(path, data)
    fmt, elements = _ply_elements(path, header)
    vi = _ply_vertex_element(path, fmt, elements)
    if fmt == "ascii":
        cols = _ply_ascii_columns(path, data, body_start, elements, vi)
    else:
        cols = _ply_binary_columns(path, data, body_start, fmt, elements, vi)
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
    if not np.isfinite(points).all():
        raise DatasetError(f"{path}: element vertex: x/y/z hold NaN or infinite values")
    return points, _ply_colours(cols, dict(elements[vi][2]))


# --------------------------------------------------------------------------------------------
# the loader


def check_scene_args(root, splits, known=None, layout: str = "") -> tuple[Path, tuple]:
    """The arguments every reader shares: `root` must be a folder, `splits` one name or a
    non-empty sequence of names (each in `known`, when given). Returns (Path, tuple)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: scene folder not found")
    splits = (splits,) if isinstance(splits, str) else tuple(splits)
    if not splits:
        raise ValueError("splits: expected at least one split name")
    for s in splits:
        if known is not None and s not in known:
            raise ValueError(f"splits: unknown split {s!r} for a {layout} scene "
                             f"(one of {', '.join(known)})")
    return root, splits



#: |R^T R - I| (max abs) and |det R - 1| allowed in a rotation read from a dataset file.
ROTATION_TOLERANCE = 1e-4



def vector(value, n: int, path: Path, field: str) -> np.ndarray:
    """`n` finite numbers (a list) as float64 (numpy's number types count as numbers)."""
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or any(isinstance(v, bool) or not isinstance(v, numbers.Real) for v in value)):
        raise DatasetError(f"{path}: field '{field}': expected a list of {n} numbers, got {value!r}")
    out = np.asarray(value, dtype=np.float64)
    if not np.isfinite(out).all():
        raise DatasetError(f"{path}: field '{field}': holds NaN or infinite values")
    return out


def check_rotation(r: np.ndarray, path, field: str) -> None:
    """A proper rotation (orthonormal, det +1) to ROTATION_TOLERANCE, else a DatasetError."""
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise DatasetError(f"{path}: {field}: expected a finite 3x3 rotation")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if err > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise DatasetError(f"{path}: {field}: not a rotation (|R^T R - I| = {err:.2g}, "
                           f"det = {det:.6g})")


def unreadable_image(path: Path, exc: Exception, named_by: str = "") -> DatasetError:
    """The DatasetError for an image that would not load: `path: cannot read image (named_by):
    why`, the reader's own "path: cannot read image" taken off `why` (it was said twice)."""
    why = str(exc)
    for head in (f"{path}: ", "cannot read image"):
        if why.startswith(head):
            why = why[len(head):].strip()
    if why.startswith("(") and why.endswith(")") and why.count("(") == 1:
        why = why[1:-1]
    by = f" ({named_by})" if named_by else ""
    return DatasetError(f"{path}: cannot read image{by}: {why or type(exc).__name__}")


def read_rgb(path: Path, background: np.ndarray, named_by: str = ""):
    """(rgb (H, W, 3) float32, alpha (H, W) or None) of an image file; RGBA is composited over
    `background` as the D-NeRF reader does (read_image hands colour over premultiplied)."""
    try:
        pixels = read_image(path)
    except Exception as exc:  # ImageError and OpenImageIO failures
        raise unreadable_image(path, exc, named_by) from None
    c = pixels.shape[2]
    if c in (1, 2):
        rgb, alpha = np.repeat(pixels[:, :, :1], 3, axis=2), (pixels[:, :, 1] if c == 2 else None)
    elif c in (3, 4):
        rgb, alpha = pixels[:, :, :3], (pixels[:, :, 3] if c == 4 else None)
    else:
        raise DatasetError(f"{path}: expected 1 to 4 channels, got {c}")
    if alpha is not None:
        rgb = rgb + np.asarray(background, np.float32) * (1.0 - alpha[:, :, None])
    return np.ascontiguousarray(rgb, dtype=np.float32), alpha


def find_point_cloud(root: Path, names) -> Path | None:
    """The first of `names` that is a file in `root` (exact case), or None."""
    present = {p.name for p in root.iterdir()} if root.is_dir() else set()
    for name in names:
        if name in present and (root / name).is_file():
            return root / name
    return None


def read_points(path: Path):
    """(points (M, 3) float32, colours (M, 3) float32 in [0, 1] or None) of a PLY or .npy file."""
    if path.suffix.lower() == ".npy":
        try:
            pts = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise DatasetError(f"{path}: cannot read points ({exc})") from None
        if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0 or pts.dtype.kind not in "fiu":
            raise DatasetError(f"{path}: expected an (N, 3) array of numbers, got shape "
                               f"{pts.shape} {pts.dtype}")
        pts = np.asarray(pts[:, :3], np.float64)
        if not np.isfinite(pts).all():
            raise DatasetError(f"{path}: holds NaN or infinite values")
        return pts, None
    pts, cols = read_ply_points(path)
    return pts.astype(np.float64), cols


def check_background(background) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.size != 3 or not np.isfinite(bg).all():
        raise ValueError(f"background: expected three finite numbers, got {background!r}")
    return bg


def check_stride(frame_stride) -> int:
    if isinstance(frame_stride, bool) or int(frame_stride) != frame_stride or int(frame_stride) < 1:
        raise ValueError(f"frame_stride: expected an integer >= 1, got {frame_stride!r}")
    return int(frame_stride)


def check_downscale(downscale) -> int:
    if isinstance(downscale, bool) or int(downscale) != downscale or int(downscale) < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale!r}")
    return int(downscale)


# --------------------------------------------------------------------------------------------
# lens distortion: the radial (k1, k2, k3) + tangential (p1, p2) model of nerfies / HyperNeRF
# `camera.py`, which is also OpenCV's (k1, k2, p1, p2, k3) model, plus nerfies' skew term.


def distort_normalized(x, y, k, p):
    """Distorted normalised coordinates of the undistorted ones (x, y); k = (k1, k2, k3),
    p = (p1, p2)."""
    r2 = x * x + y * y
    d = 1.0 + r2 * (k[0] + r2 * (k[1] + k[2] * r2))
    xd = x * d + 2.0 * p[0] * x * y + p[1] * (r2 + 2.0 * x * x)
    yd = y * d + 2.0 * p[1] * x * y + p[0] * (r2 + 2.0 * y * y)
    return xd, yd


def undistort_normalized(xd, yd, k, p, iterations: int = 20):
    """Inverse of :func:`distort_normalized` by Newton's method (as nerfies does), from (xd, yd)."""
    x, y = np.array(xd, np.float64), np.array(yd, np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        d = 1.0 + r2 * (k[0] + r2 * (k[1] + k[2] * r2))
        fx = d * x + 2 * p[0] * x * y + p[1] * (r2 + 2 * x * x) - xd
        fy = d * y + 2 * p[1] * x * y + p[0] * (r2 + 2 * y * y) - yd
        d_r = k[0] + r2 * (2.0 * k[1] + 3.0 * k[2] * r2)
        d_x, d_y = 2.0 * x * d_r, 2.0 * y * d_r
        fx_x = d + d_x * x + 2.0 * p[0] * y + 6.0 * p[1] * x
        fx_y = d_y * x + 2.0 * p[0] * x + 2.0 * p[1] * y
        fy_x = d_x * y + 2.0 * p[1] * y + 2.0 * p[0] * x
        fy_y = d + d_y * y + 2.0 * p[1] * x + 6.0 * p[0] * y
        den = fy_x * fx_y - fx_x * fy_y
        ok = np.abs(den) > 1e-12
        safe = np.where(ok, den, 1.0)
        x = x + np.where(ok, (fx * fy_y - fy * fx_y) / safe, 0.0)
        y = y + np.where(ok, (fy * fx_x - fx * fy_x) / safe, 0.0)
    return x, y


def undistortion_maps(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                      skew: float, k, p):
    """cv2.remap maps that resample a distorted (and skewed) image into the pinhole image of the
    same size with intrinsics (fx, fy, cx, cy) and no skew: output pixel centre (u, v) looks up
    the source at ``(fx xd + skew yd + cx, fy yd + cy)`` where (xd, yd) is the distorted image of
    its normalised ray (nerfies `Camera.project`). OpenCV puts pixel centres at integers, so both
    coordinates shift by 0.5 (docs/design.md section 3 puts them at i + 0.5)."""
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    x = ((u - cx) / fx)[None, :].repeat(height, 0)
    y = ((v - cy) / fy)[:, None].repeat(width, 1)
    xd, yd = distort_normalized(x, y, k, p)
    map_x = (fx * xd + skew * yd + cx - 0.5).astype(np.float32)
    map_y = (fy * yd + cy - 0.5).astype(np.float32)
    return map_x, map_y


def remap(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear resampling with OpenCV; samples outside the source repeat its edge pixels."""
    import cv2

    out = cv2.remap(np.ascontiguousarray(image, np.float32), map_x, map_y,
                    interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(map_x.shape + image.shape[2:]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# atomic writes (docs/design.md section 10)


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2) + "\n").encode("utf-8"))
