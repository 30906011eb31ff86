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

import math
from pathlib import Path

import numpy as np

from nehad.data.common import (DNERF_INIT_BOUND, DatasetError, DNeRFScene, Frame,  # noqa: F401
                               area_downscale, check_background, check_scene_args,
                               downscale_camera, number, read_json, read_ply_points,
                               unreadable_image)
from nehad.runtime.cameras import Camera, CameraError, check_rotation
from nehad.runtime.images import DNERF_IMAGE_SUFFIXES, STILL_SUFFIXES, read_image

__all__ = ["DatasetError", "Frame", "DNeRFScene", "load_dnerf", "SPLITS", "POINT_CLOUD_NAMES"]

#: The split files a D-NeRF scene may hold.
SPLITS = ("train", "val", "test")
#: Initial point clouds looked for in the scene folder, in this order.
POINT_CLOUD_NAMES = ("fused.ply", "points3d.ply", "points3D.ply")

# --------------------------------------------------------------------------------------------
# transforms files


def _read_transforms(path: Path) -> dict:
    doc = read_json(path, "transforms file")
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


def _frame_time(frame: dict, k: int, path: Path) -> float:
    if "time" not in frame:
        raise DatasetError(f"{path}: frames[{k}].time: missing (D-NeRF frames need a time)")
    return number(frame["time"], path, f"frames[{k}].time")


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
    try:  # a cam.json's rule, so that what trains also renders
        check_rotation(m[:3, :3], name, str(path))
    except CameraError as e:
        raise DatasetError(str(e)) from None
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
            vals[key] = number(v, path, name.format(k=k), positive=key != "cx" and key != "cy")
    for key, actual in (("w", width), ("h", height)):
        if key in vals and int(round(vals[key])) != actual:
            _, name = _lookup(frame, doc, key)
            raise DatasetError(f"{path}: {name.format(k=k)}: says {int(round(vals[key]))} but the "
                               f"image is {width}x{height}")
    if "fl_x" in vals:
        fx = vals["fl_x"]
    elif "camera_angle_x" in doc:
        angle = number(doc["camera_angle_x"], path, "camera_angle_x", positive=True)
        if angle >= math.pi:
            raise DatasetError(f"{path}: field 'camera_angle_x': expected radians in (0, pi), got {angle}")
        fx = 0.5 * width / math.tan(0.5 * angle)
    else:
        raise DatasetError(f"{path}: field 'camera_angle_x': missing (and frames[{k}] has no fl_x)")
    if "fl_y" in vals:
        fy = vals["fl_y"]
    elif "fl_x" not in vals and "camera_angle_y" in doc:
        angle = number(doc["camera_angle_y"], path, "camera_angle_y", positive=True)
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
    if base.suffix.lower() in DNERF_IMAGE_SUFFIXES:
        candidates = [base]
    else:
        candidates = [base.with_name(base.name + s) for s in STILL_SUFFIXES] + [base]
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
        raise unreadable_image(img_path, exc, f"named by {json_path} frames[{k}].file_path"
                               ) from None
    if not np.isfinite(pixels).all():  # a float EXR/TIFF can hold them; training would die
        raise DatasetError(f"{img_path}: holds NaN or infinite pixel values (named by "
                           f"{json_path} frames[{k}].file_path)")
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
        rgb = area_downscale(rgb, downscale)
        alpha = None if alpha is None else area_downscale(alpha[:, :, None], downscale)[:, :, 0]
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    alpha = None if alpha is None else np.ascontiguousarray(alpha, dtype=np.float32)
    return rgb, alpha, pixels.shape[1], pixels.shape[0]


def _check_downscale(downscale) -> int:
    """`downscale` as an int; ValueError unless it is an integer >= 1 (not a bool)."""
    if isinstance(downscale, bool) or int(downscale) != downscale or int(downscale) < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale!r}")
    return int(downscale)


def _read_split_files(root: Path, splits: tuple) -> dict[str, tuple[Path, dict]]:
    """(path, parsed document) of every requested split, plus the other standard splits present
    (their times take part in the normalisation, so a split's times do not depend on which
    splits were asked for)."""
    docs: dict[str, tuple[Path, dict]] = {}
    for split in splits + tuple(s for s in SPLITS if s not in splits):
        path = root / f"transforms_{split}.json"
        if split in splits or path.is_file():
            docs[split] = (path, _read_transforms(path))
    return docs


def _source_time_range(raw_times: dict[str, list[float]]) -> tuple[float, float]:
    """(t0, t1) that the file times are normalised by: (0, 1) when they all lie in [0, 1]
    already, else their minimum and maximum."""
    every = [t for ts in raw_times.values() for t in ts]
    if every and (min(every) < 0.0 or max(every) > 1.0):
        return min(every), max(every)
    return 0.0, 1.0


def _load_frame(root: Path, fr: dict, k: int, path: Path, doc: dict, split: str, time: float,
                bg: np.ndarray, downscale: int) -> Frame:
    """Frame `k` of a split's transforms file `path`: its image composited and downscaled, its
    camera at the normalised `time`."""
    c2w = _frame_matrix(fr, k, path)
    img_path = _image_path(root, fr, k, path)
    rgb, alpha, width, height = _load_image(img_path, bg, downscale, path, k)
    fx, fy, cx, cy = _intrinsics(doc, fr, k, path, width, height)
    try:
        cam = Camera.from_camera_to_world(c2w, width, height, fx, fy, cx, cy,
                                          convention="opengl", time=time,
                                          name=f"{split}/{img_path.stem}")
    except (CameraError, np.linalg.LinAlgError) as exc:
        raise DatasetError(f"{path}: frames[{k}]: invalid camera ({exc})") from None
    if downscale > 1:
        cam = downscale_camera(cam, downscale)
    return Frame(cam, rgb, alpha, img_path)


def _load_split(root: Path, split: str, path: Path, doc: dict, times: list[float],
                bg: np.ndarray, downscale: int) -> list[Frame]:
    """The frames of one split at their normalised `times`; every frame's camera fields and
    image file are checked before any image is decoded."""
    for k, fr in enumerate(doc["frames"]):  # validate the camera fields before decoding
        _frame_matrix(fr, k, path)
        _image_path(root, fr, k, path)
    frames = [_load_frame(root, fr, k, path, doc, split, times[k], bg, downscale)
              for k, fr in enumerate(doc["frames"])]
    for fr in frames[1:]:  # one size per split: its metrics stack the frames (nehad eval)
        if fr.image.shape != frames[0].image.shape:
            size = lambda f: f"{f.image.shape[1]}x{f.image.shape[0]}"  # noqa: E731
            raise DatasetError(f"{fr.path}: {size(fr)} pixels, but {frames[0].path.name} of the "
                               f"same split ({path.name}) is {size(frames[0])}")
    return frames


def _initial_points(root: Path):
    """(points, colours, file) of the first of POINT_CLOUD_NAMES in `root` (the name spelled
    exactly so), or Nones."""
    for name in POINT_CLOUD_NAMES:
        candidate = root / name
        if candidate.is_file() and candidate.name in {p.name for p in root.iterdir()}:
            points, colours = read_ply_points(candidate)
            return points, colours, candidate
    return None, None, None


def load_dnerf(root, splits=SPLITS, background=(1.0, 1.0, 1.0), downscale: int = 1) -> DNeRFScene:
    """Load a D-NeRF scene folder (see the module docstring for the format).

    `splits`: which ``transforms_<split>.json`` files to load (each must exist). `background`:
    RGB (or one grey value) that RGBA images are composited over. `downscale`: integer >= 1; images
    are area-averaged over ``downscale x downscale`` blocks and the cameras scaled to match.
    Raises :class:`DatasetError` (a ValueError) naming the file and field on bad data.
    """
    root, splits = check_scene_args(root, splits)
    downscale = _check_downscale(downscale)
    bg = check_background(background)

    docs = _read_split_files(root, splits)
    raw_times: dict[str, list[float]] = {}
    for split, (path, doc) in docs.items():
        raw_times[split] = [_frame_time(fr, k, path) for k, fr in enumerate(doc["frames"])]
    t0, t1 = _source_time_range(raw_times)
    span = t1 - t0

    def normalise(t: float) -> float:
        return (t - t0) / span if span > 0 else 0.0

    frames: dict[str, list[Frame]] = {}
    for split in splits:
        path, doc = docs[split]
        times = [normalise(t) for t in raw_times[split]]
        frames[split] = _load_split(root, split, path, doc, times, bg, downscale)
    points, colours, points_path = _initial_points(root)

    loaded = [f.time for fs in frames.values() for f in fs]
    time_range = (min(loaded), max(loaded)) if loaded else (0.0, 1.0)
    return DNeRFScene(root=root, frames=frames, background=tuple(float(x) for x in bg),
                      initial_points=points, initial_colors=colours, time_range=time_range,
                      source_time_range=(float(t0), float(t1)), points_path=points_path,
                      downscale=downscale)

