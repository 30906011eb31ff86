"""Reader for dynamic scenes in the D-NeRF "blender" layout (docs/design.md sections 3 and 5).

A scene folder holds ``transforms_{train,val,test}.json`` and the images they name::

    {"camera_angle_x": 0.69,
     "frames": [{"file_path": "./train/r_000", "time": 0.0,
                 "transform_matrix": [[...4 x 4 camera-to-world, Blender/OpenGL axes...]]}, ...]}

- ``file_path`` has no extension in D-NeRF (the reader appends ``.png``, as D-NeRF does); a path
  that already ends in an image extension is used as it is.
- ``transform_matrix`` is camera-to-world with OpenGL axes (y up, z back); it becomes a
  :class:`~nehad.runtime.cameras.Camera` (OpenCV axes) through ``Camera.from_camera_to_world``.
- Intrinsics: ``fx = 0.5 W / tan(camera_angle_x / 2)``, ``fy = fx``, principal point at the image
  centre; per-frame ``fl_x, fl_y, cx, cy, w, h`` (or the same keys at the top level of the file,
  nerfstudio style) take precedence when present.
- Times are normalised to [0, 1] (docs/design.md section 3): kept when the file's times already lie there,
  otherwise min-max normalised over every split file present in the folder.
- RGBA images are composited over the caller's background (``rgb a + bg (1 - a)`` with the file's
  straight colour; white for D-NeRF RGBA data, black for ``dnerf_lego_100``, docs/design.md section 5); RGB
  images are used as they are. ``read_image`` returns RGBA with premultiplied colour (OpenImageIO's
  associated alpha), so the code adds ``bg (1 - a)`` to what it returns.
- ``fused.ply``, ``points3d.ply`` or ``points3D.ply`` (first found), when present, gives the initial
  point cloud (docs/design.md section 5: otherwise the trainer draws random points in [-1.3, 1.3]^3).

Bad data raises :class:`DatasetError` naming the file and the field. Numpy only, no torch.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nehad.runtime.cameras import Camera, CameraError
from nehad.runtime.images import read_image

__all__ = ["DatasetError", "Frame", "DNeRFScene", "load_dnerf", "SPLITS", "POINT_CLOUD_NAMES"]

#: The split files a D-NeRF scene may hold.
SPLITS = ("train", "val", "test")
#: Initial point clouds looked for in the scene folder, in this order.
POINT_CLOUD_NAMES = ("fused.ply", "points3d.ply", "points3D.ply")
#: Half side of the cube D-NeRF initialises random points in (docs/design.md section 5).
DNERF_INIT_BOUND = 1.3

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


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


# --------------------------------------------------------------------------------------------
# transforms files


def _read_json(path: Path, what: str) -> object:
    """Parsed JSON of `path`; a missing or malformed file is a DatasetError naming it (shared by
    every reader as `nehad.data.common.read_json`)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: malformed JSON ({exc})") from None


def _read_transforms(path: Path) -> dict:
    doc = _read_json(path, "transforms file")
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level, got {type(doc).__name__}")
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise DatasetError(f"{path}: field 'frames': expected a list of frames, "
                           f"got {'nothing' if frames is None else type(frames).__name__}")
    for k, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(f"{path}: frames[{k}]: expected an object, got {type(fr).__name__}")
    return doc


def _number(value, path: Path, field_name: str, positive: bool = False) -> float:
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


def _frame_time(frame: dict, k: int, path: Path) -> float:
    if "time" not in frame:
        raise DatasetError(f"{path}: frames[{k}].time: missing (D-NeRF frames need a time)")
    return _number(frame["time"], path, f"frames[{k}].time")


def _frame_matrix(frame: dict, k: int, path: Path) -> np.ndarray:
    name = f"frames[{k}].transform_matrix"
    if "transform_matrix" not in frame:
        raise DatasetError(f"{path}: {name}: missing")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {name}: expected a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise DatasetError(f"{path}: {name}: expected a 4x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise DatasetError(f"{path}: {name}: holds NaN or infinite values")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DatasetError(f"{path}: {name}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    if abs(np.linalg.det(m[:3, :3])) < 1e-8:
        raise DatasetError(f"{path}: {name}: rotation part is singular")
    return m


def _lookup(frame: dict, doc: dict, key: str):
    """Per-frame value of `key`, else the file-level one, else None (with the field's name)."""
    if key in frame:
        return frame[key], "frames[{k}]." + key
    if key in doc:
        return doc[key], key
    return None, key


def _intrinsics(doc: dict, frame: dict, k: int, path: Path, width: int, height: int):
    """(fx, fy, cx, cy) at the image's full resolution; checks w/h against the image size."""
    vals = {}
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        v, name = _lookup(frame, doc, key)
        if v is not None:
            vals[key] = _number(v, path, name.format(k=k), positive=key != "cx" and key != "cy")
    for key, actual in (("w", width), ("h", height)):
        if key in vals and int(round(vals[key])) != actual:
            _, name = _lookup(frame, doc, key)
            raise DatasetError(f"{path}: {name.format(k=k)}: says {int(round(vals[key]))} but the "
                               f"image is {width}x{height}")
    if "fl_x" in vals:
        fx = vals["fl_x"]
    elif "camera_angle_x" in doc:
        angle = _number(doc["camera_angle_x"], path, "camera_angle_x", positive=True)
        if angle >= math.pi:
            raise DatasetError(f"{path}: field 'camera_angle_x': expected radians in (0, pi), got {angle}")
        fx = 0.5 * width / math.tan(0.5 * angle)
    else:
        raise DatasetError(f"{path}: field 'camera_angle_x': missing (and frames[{k}] has no fl_x)")
    if "fl_y" in vals:
        fy = vals["fl_y"]
    elif "fl_x" not in vals and "camera_angle_y" in doc:
        angle = _number(doc["camera_angle_y"], path, "camera_angle_y", positive=True)
        fy = 0.5 * height / math.tan(0.5 * angle)
    else:
        fy = fx
    cx = vals.get("cx", width / 2.0)
    cy = vals.get("cy", height / 2.0)
    return fx, fy, cx, cy


def _image_path(root: Path, frame: dict, k: int, path: Path) -> Path:
    fp = frame.get("file_path")
    if not isinstance(fp, str) or not fp:
        raise DatasetError(f"{path}: frames[{k}].file_path: expected a relative image path, got {fp!r}")
    base = root / fp
    if base.suffix.lower() in _IMAGE_SUFFIXES:
        candidates = [base]
    else:
        candidates = [base.with_name(base.name + s) for s in (".png", ".jpg", ".jpeg")] + [base]
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetError(f"{candidates[0]}: image file not found (named by {path} frames[{k}].file_path)")


# --------------------------------------------------------------------------------------------
# images


def _load_image(img_path: Path, background: np.ndarray, downscale: int, json_path: Path, k: int):
    try:
        pixels = read_image(img_path)
    except Exception as exc:  # ImageError and OpenImageIO failures
        raise DatasetError(f"{img_path}: cannot read image (named by {json_path} "
                           f"frames[{k}].file_path): {exc}") from None
    c = pixels.shape[2]
    if c == 1:
        rgb, alpha = np.repeat(pixels, 3, axis=2), None
    elif c == 2:
        rgb, alpha = np.repeat(pixels[:, :, :1], 3, axis=2), pixels[:, :, 1]
    elif c in (3, 4):
        rgb, alpha = pixels[:, :, :3], (pixels[:, :, 3] if c == 4 else None)
    else:
        raise DatasetError(f"{img_path}: expected 1 to 4 channels, got {c}")
    if alpha is not None:
        # read_image hands RGBA over with associated (premultiplied) colour, OpenImageIO's
        # convention, so rgb_file * a + bg (1 - a) is rgb + bg (1 - a) here.
        rgb = rgb + background.astype(np.float32) * (1.0 - alpha[:, :, None])
    if downscale > 1:
        rgb = _area_downscale(rgb, downscale)
        alpha = None if alpha is None else _area_downscale(alpha[:, :, None], downscale)[:, :, 0]
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    alpha = None if alpha is None else np.ascontiguousarray(alpha, dtype=np.float32)
    return rgb, alpha, pixels.shape[1], pixels.shape[0]


def _area_downscale(img: np.ndarray, f: int) -> np.ndarray:
    """Mean over f x f blocks; a remainder at the right/bottom edge is cropped."""
    h, w, c = img.shape
    h2, w2 = h // f, w // f
    return img[: h2 * f, : w2 * f].reshape(h2, f, w2, f, c).mean(axis=(1, 3), dtype=np.float32)


def _downscale_camera(cam: Camera, f: int) -> Camera:
    if cam.width % f == 0 and cam.height % f == 0:
        return cam.scaled(1.0 / f)
    # Cropping the remainder keeps the pixel grid origin, so every intrinsic divides by f.
    return dataclasses.replace(cam, width=cam.width // f, height=cam.height // f, fx=cam.fx / f,
                               fy=cam.fy / f, cx=cam.cx / f, cy=cam.cy / f)


# --------------------------------------------------------------------------------------------
# PLY point clouds (x y z and optional colours; the 3DGS Gaussian PLY reader lives elsewhere)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices of an ascii or binary PLY file: (M, 3) float32 points, (M, 3) colours in [0, 1]."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []  # elements: [name, count, [(prop, type or None-for-list)]]
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

    if fmt == "ascii":
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
        cols = {p: table[:, i] for i, p in enumerate(prop_names)}
        types = dict(props)
    else:
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
        cols = {p: rec[p] for p in prop_names}
        types = dict(props)
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float32)
    if not np.isfinite(points).all():
        raise DatasetError(f"{path}: element vertex: x/y/z hold NaN or infinite values")
    colours = None
    for trio in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(c in cols for c in trio):
            rgb = np.stack([cols[c] for c in trio], axis=1).astype(np.float64)
            kind = np.dtype(types[trio[0]])
            if kind.kind in "iu":
                rgb = rgb / float(np.iinfo(kind).max)
            colours = np.clip(rgb, 0.0, 1.0).astype(np.float32)
            break
    return points, colours


# --------------------------------------------------------------------------------------------
# the loader


def _check_background(background) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.size != 3 or not np.isfinite(bg).all():
        raise ValueError(f"background: expected three finite numbers, got {background!r}")
    return bg


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


def load_dnerf(root, splits=SPLITS, background=(1.0, 1.0, 1.0), downscale: int = 1) -> DNeRFScene:
    """Load a D-NeRF scene folder (see the module docstring for the format).

    `splits`: which ``transforms_<split>.json`` files to load (each must exist). `background`:
    RGB (or one grey value) that RGBA images are composited over. `downscale`: integer >= 1; images
    are area-averaged over ``downscale x downscale`` blocks and the cameras scaled to match.
    Raises :class:`DatasetError` (a ValueError) naming the file and field on bad data.
    """
    root, splits = check_scene_args(root, splits)
    if isinstance(downscale, bool) or int(downscale) != downscale or int(downscale) < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale!r}")
    downscale = int(downscale)
    bg = _check_background(background)

    # Parse every requested split, plus the other standard splits present (their times take part
    # in the normalisation, so a split's times do not depend on which splits were asked for).
    docs: dict[str, tuple[Path, dict]] = {}
    for split in splits + tuple(s for s in SPLITS if s not in splits):
        path = root / f"transforms_{split}.json"
        if split in splits or path.is_file():
            docs[split] = (path, _read_transforms(path))

    raw_times: dict[str, list[float]] = {}
    for split, (path, doc) in docs.items():
        raw_times[split] = [_frame_time(fr, k, path) for k, fr in enumerate(doc["frames"])]
    every = [t for ts in raw_times.values() for t in ts]
    if every and (min(every) < 0.0 or max(every) > 1.0):
        t0, t1 = min(every), max(every)
    else:
        t0, t1 = 0.0, 1.0
    span = t1 - t0

    def normalise(t: float) -> float:
        return (t - t0) / span if span > 0 else 0.0

    frames: dict[str, list[Frame]] = {}
    for split in splits:
        path, doc = docs[split]
        out = []
        for k, fr in enumerate(doc["frames"]):  # validate the camera fields before decoding
            _frame_matrix(fr, k, path)
            _image_path(root, fr, k, path)
        for k, fr in enumerate(doc["frames"]):
            c2w = _frame_matrix(fr, k, path)
            img_path = _image_path(root, fr, k, path)
            rgb, alpha, width, height = _load_image(img_path, bg, downscale, path, k)
            fx, fy, cx, cy = _intrinsics(doc, fr, k, path, width, height)
            try:
                cam = Camera.from_camera_to_world(c2w, width, height, fx, fy, cx, cy,
                                                  convention="opengl",
                                                  time=normalise(raw_times[split][k]),
                                                  name=f"{split}/{img_path.stem}")
            except (CameraError, np.linalg.LinAlgError) as exc:
                raise DatasetError(f"{path}: frames[{k}]: invalid camera ({exc})") from None
            if downscale > 1:
                cam = _downscale_camera(cam, downscale)
            out.append(Frame(cam, rgb, alpha, img_path))
        frames[split] = out

    points = colours = points_path = None
    for name in POINT_CLOUD_NAMES:
        candidate = root / name
        if candidate.is_file() and candidate.name in {p.name for p in root.iterdir()}:
            points, colours = _read_ply_points(candidate)
            points_path = candidate
            break

    loaded = [f.time for fs in frames.values() for f in fs]
    time_range = (min(loaded), max(loaded)) if loaded else (0.0, 1.0)
    return DNeRFScene(root=root, frames=frames, background=tuple(float(x) for x in bg),
                      initial_points=points, initial_colors=colours, time_range=time_range,
                      source_time_range=(float(t0), float(t1)), points_path=points_path,
                      downscale=downscale)
