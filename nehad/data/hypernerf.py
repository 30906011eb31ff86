"""Reader for HyperNeRF / nerfies captures, read the way 4DGS reads them (docs/design.md sections 3 and 5).

Layout (Google's nerfies / HyperNeRF release; 4DGS ``scene/hyper_loader.py``)::

    scene.json        {"scale": s, "center": [cx, cy, cz], "near": n, "far": f}
    metadata.json     {"<id>": {"warp_id": k, "appearance_id": k, "camera_id": c}, ...}
    dataset.json      {"ids": [...], "train_ids": [...], "val_ids": [...]}
    camera/<id>.json  {"orientation": 3x3, "position": [x, y, z], "focal_length": f,
                       "principal_point": [px, py], "skew": 0, "pixel_aspect_ratio": 1,
                       "radial_distortion": [k1, k2, k3], "tangential_distortion": [p1, p2],
                       "image_size": [W, H]}
    rgb/<S>x/<id>.png images at 1/S of the camera files' resolution (1x, 2x, 4x, ...)
    points.npy        optional (N, 3) points; else points3D_downsample2.ply / points3D.ply / ...

What the reader does, and where it comes from:

- Cameras (nerfies ``camera.py``): ``orientation`` is the world-to-camera rotation in OpenCV axes
  (x right, y down, z forward), ``position`` the camera centre; a point projects to
  ``u = f x + skew y + px``, ``v = f * pixel_aspect_ratio * y + py`` with pixel centres at
  i + 0.5, the docs/design.md section 3 convention, so ``fx = f``, ``fy = f * pixel_aspect_ratio``, ``cx = px``,
  ``cy = py``. 4DGS ignores the principal point and the aspect ratio; we keep them.
- World frame (nerfies / TiNeuVox / early 4DGS ``Load_hyper_data``): positions and points are
  normalised as ``(x - center) * scale`` with ``scene.json``'s values; ``near``/``far`` are kept
  on the scene object. Point files (``points.npy`` and the COLMAP ``points3D*.ply`` that 4DGS's
  ``hypernerf2colmap.py`` triangulates from the same camera files) are in the raw frame and are
  normalised the same way.
- Time (4DGS): ``t = warp_id / max(warp_id)`` over all ids (``time_id`` when there is no
  ``warp_id``), so t lies in [0, 1] (docs/design.md section 3).
- Splits (4DGS): ``train`` = the ``train_ids``, ``test`` (alias ``val``) = the ``val_ids``, both in
  the order of ``ids``. A scene without ``val_ids`` (the "interp" scenes) is split as 4DGS does:
  train = every 4th image (index % 4 == 0), test = train + 2 (without the last).
- Image scale: ``downscale`` = S reads ``rgb/<S>x`` when that folder exists, the camera scaled by
  1/S as nerfies ``Camera.scale`` does (focal and principal point times 1/S); otherwise it reads
  ``rgb/1x`` and averages S x S blocks, as the D-NeRF reader does. 4DGS uses ``rgb/2x``, which is
  the ``hypernerf`` preset's ``data.downscale = 2`` (536 x 960, the paper's resolution).
- Distortion and skew: by default the images are undistorted (our renderer is a pinhole camera):
  each image is resampled with OpenCV (``cv2.remap``, bilinear, edge pixels repeated outside the
  source) into the pinhole camera of the same size, focal length and principal point, using the
  nerfies distortion model (= OpenCV's k1 k2 p1 p2 k3) and skew. 4DGS trains on the distorted
  images as they are. ``undistort=False`` refuses a camera with distortion or skew instead, with a
  message naming the file and field.

Bad data (a missing or malformed file, a missing field, an id without a camera file or image)
raises :class:`~nehad.data.dnerf.DatasetError` naming the file. Numpy (and OpenCV for
undistortion) only, no torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nehad.data.common import (check_background, check_downscale, check_rotation, check_stride,
                               find_point_cloud, number, read_json, read_points, read_rgb, remap,
                               undistortion_maps, vector)
from nehad.data.common import (DatasetError, DNeRFScene, Frame, area_downscale,
                              downscale_camera, check_scene_args)
from nehad.runtime.cameras import Camera

__all__ = ["load_hypernerf", "read_hypernerf_camera", "HyperNeRFCamera", "POINT_FILES",
           "SPLIT_ALIASES", "is_hypernerf"]

#: Initial point files looked for, in this order (all in the raw, un-normalised world frame).
POINT_FILES = ("points.npy", "points3D_downsample2.ply", "points3D_downsample.ply",
               "points3D.ply", "points3d.ply", "fused.ply")
#: Split names accepted and the dataset.json list they read.
SPLIT_ALIASES = {"train": "train", "test": "val", "val": "val"}
#: Distortion coefficients smaller than this (in absolute value) count as zero.
DISTORTION_EPS = 1e-12


def is_hypernerf(root) -> bool:
    root = Path(root)
    return all((root / n).is_file() for n in ("dataset.json", "metadata.json", "scene.json"))


class HyperNeRFCamera:
    """One ``camera/<id>.json`` as stored (1x resolution, raw world frame)."""

    def __init__(self, path: Path, orientation, position, focal, principal, skew, aspect,
                 radial, tangential, size):
        self.path = path
        self.orientation = orientation  # (3, 3) world-to-camera, OpenCV axes
        self.position = position  # (3,) camera centre, raw world frame
        self.focal = focal
        self.principal = principal  # (2,)
        self.skew = skew
        self.aspect = aspect
        self.radial = radial  # (3,)
        self.tangential = tangential  # (2,)
        self.size = size  # (W, H)

    @property
    def distorted(self) -> bool:
        return bool(np.abs(self.radial).max() > DISTORTION_EPS
                    or np.abs(self.tangential).max() > DISTORTION_EPS)

    def camera(self, center, scale, factor: float, width: int, height: int, time: float,
               name: str) -> Camera:
        """The pinhole Camera of this file in the normalised world, for an image `factor` times
        the file's resolution (nerfies ``Camera.scale``) of size width x height."""
        c = (self.position - center) * scale
        w2c = np.eye(4)
        w2c[:3, :3] = self.orientation
        w2c[:3, 3] = -self.orientation @ c
        return Camera(int(width), int(height), self.focal * factor,
                      self.focal * self.aspect * factor, float(self.principal[0] * factor),
                      float(self.principal[1] * factor), w2c, time, name)


def read_hypernerf_camera(path: Path) -> HyperNeRFCamera:
    """Parse and check one nerfies camera file (the fields of the module docstring)."""
    doc = read_json(path, "camera file")
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(doc).__name__}")

    def need(key):
        if key not in doc:
            raise DatasetError(f"{path}: field '{key}': missing")
        return doc[key]

    rows = need("orientation")
    if not isinstance(rows, list) or len(rows) != 3:
        raise DatasetError(f"{path}: field 'orientation': expected a 3x3 matrix")
    orientation = np.stack([vector(r, 3, path, "orientation") for r in rows])
    check_rotation(orientation, path, "field 'orientation'")
    position = vector(need("position"), 3, path, "position")
    focal = number(need("focal_length"), path, "focal_length", positive=True)
    principal = vector(need("principal_point"), 2, path, "principal_point")
    skew = number(doc.get("skew", 0.0), path, "skew")
    aspect = number(doc.get("pixel_aspect_ratio", 1.0), path, "pixel_aspect_ratio", positive=True)
    radial = vector(doc.get("radial_distortion", [0.0, 0.0, 0.0]), 3, path, "radial_distortion")
    tkey = "tangential_distortion" if "tangential_distortion" in doc else "tangential"
    tangential = vector(doc.get(tkey, [0.0, 0.0]), 2, path, tkey)
    size = vector(need("image_size"), 2, path, "image_size")
    if (size <= 0).any() or (size != np.round(size)).any():
        raise DatasetError(f"{path}: field 'image_size': expected two positive whole numbers "
                           f"[width, height], got {size.tolist()}")
    return HyperNeRFCamera(path, orientation, position, focal, principal, skew, aspect, radial,
                           tangential, (int(size[0]), int(size[1])))


def _id_list(doc: dict, key: str, path: Path, required: bool = True) -> list[str]:
    if key not in doc:
        if required:
            raise DatasetError(f"{path}: field '{key}': missing")
        return []
    ids = doc[key]
    if not isinstance(ids, list) or not all(isinstance(i, str) and i for i in ids):
        raise DatasetError(f"{path}: field '{key}': expected a list of image ids (strings)")
    return ids


def _split_indices(root: Path):
    """(ids, {"train": [...], "val": [...]} as indices into ids), the 4DGS way."""
    path = root / "dataset.json"
    doc = read_json(path, "dataset file")
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    ids = _id_list(doc, "ids", path)
    if not ids:
        raise DatasetError(f"{path}: field 'ids': is empty")
    if len(set(ids)) != len(ids):
        raise DatasetError(f"{path}: field 'ids': holds duplicates")
    val_ids = _id_list(doc, "val_ids", path, required=False)
    if not val_ids:  # "interp" scenes: 4DGS's every-4th split
        train = [i for i in range(len(ids)) if i % 4 == 0]
        val = [i + 2 for i in train][:-1]
        val = [i for i in val if i < len(ids)]
        return ids, {"train": train, "val": val}
    train_ids = _id_list(doc, "train_ids", path)
    known = set(ids)
    for key, lst in (("train_ids", train_ids), ("val_ids", val_ids)):
        missing = [i for i in lst if i not in known]
        if missing:
            raise DatasetError(f"{path}: field '{key}': id {missing[0]!r} is not in 'ids'")
    tr, va = set(train_ids), set(val_ids)
    return ids, {"train": [i for i, x in enumerate(ids) if x in tr],
                 "val": [i for i, x in enumerate(ids) if x in va]}


def _times(root: Path, ids: list[str]):
    """Normalised times (warp_id / max warp_id, 4DGS) per id and the max id."""
    path = root / "metadata.json"
    meta = read_json(path, "metadata file")
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    raw = []
    for i in ids:
        entry = meta.get(i)
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: entry '{i}': missing (every id of dataset.json needs one)")
        key = "warp_id" if "warp_id" in entry else "time_id"
        if key not in entry:
            raise DatasetError(f"{path}: entry '{i}': field 'warp_id': missing")
        v = number(entry[key], path, f"{i}.{key}")
        if v < 0 or v != int(v):
            raise DatasetError(f"{path}: entry '{i}': field '{key}': expected an integer >= 0, "
                               f"got {entry[key]!r}")
        raw.append(int(v))
    top = max(raw)
    return [r / top if top > 0 else 0.0 for r in raw], top


def _scene_json(root: Path):
    path = root / "scene.json"
    doc = read_json(path, "scene file")
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    if "scale" not in doc:
        raise DatasetError(f"{path}: field 'scale': missing")
    if "center" not in doc:
        raise DatasetError(f"{path}: field 'center': missing")
    scale = number(doc["scale"], path, "scale", positive=True)
    center = vector(doc["center"], 3, path, "center")
    near = number(doc["near"], path, "near") if "near" in doc else None
    far = number(doc["far"], path, "far") if "far" in doc else None
    return scale, center, near, far


def _image_folder(root: Path, downscale: int) -> tuple[Path, int]:
    """(folder to read, remaining integer area downscale)."""
    rgb = root / "rgb"
    direct = rgb / f"{downscale}x"
    if direct.is_dir():
        return direct, 1
    base = rgb / "1x"
    if base.is_dir():
        return base, downscale
    have = sorted(p.name for p in rgb.iterdir() if p.is_dir()) if rgb.is_dir() else []
    raise DatasetError(f"{direct}: image folder not found (and no rgb/1x to downscale from); "
                       f"{rgb} holds {', '.join(have) if have else 'no scale folders'}")


def _checked_camera(root: Path, ident: str, undistort: bool) -> HyperNeRFCamera:
    """Read ``camera/<ident>.json``; DatasetError when it is missing, or distorted or skewed
    while `undistort` is off."""
    cam_path = root / "camera" / f"{ident}.json"
    if not cam_path.is_file():
        raise DatasetError(f"{cam_path}: camera file not found (id {ident!r} of "
                           f"{root / 'dataset.json'})")
    cam = read_hypernerf_camera(cam_path)
    if not undistort and (cam.distorted or abs(cam.skew) > DISTORTION_EPS):
        fld = "skew" if not cam.distorted else "radial_distortion"
        raise DatasetError(
            f"{cam_path}: field '{fld}': the camera is distorted or skewed and "
            f"undistortion is off; load with undistort=True to resample the image "
            f"into a pinhole camera")
    return cam


def _checked_cameras(root: Path, ids: list[str], wanted: dict, folder: Path,
                     undistort: bool) -> dict[int, HyperNeRFCamera]:
    """The camera file of every index in `wanted`, each checked along with its image file
    before any image is decoded."""
    cams: dict[int, HyperNeRFCamera] = {}
    for s, idx in wanted.items():
        for i in idx:
            if i not in cams:
                cams[i] = _checked_camera(root, ids[i], undistort)
            img = folder / f"{ids[i]}.png"
            if not img.is_file():
                raise DatasetError(f"{img}: image file not found (id {ids[i]!r})")
    return cams


@dataclass
class _Reading:
    """What every frame of one load shares: the ids, their times, the normalisation of the
    world frame, the image folder with the `extra` area downscale still to apply and the camera
    scale `factor` of its files, the background and the undistortion maps made so far."""

    ids: list[str]
    times: list[float]
    center: np.ndarray
    scale: float
    folder: Path
    extra: int
    factor: float
    bg: np.ndarray
    maps: dict = field(default_factory=dict)


def _check_image_size(img: Path, hc: HyperNeRFCamera, w: int, h: int, factor: float) -> None:
    """DatasetError unless the image is the camera file's ``image_size`` at scale `factor`."""
    exp_w, exp_h = hc.size[0] * factor, hc.size[1] * factor
    if abs(w - exp_w) >= 1.0 or abs(h - exp_h) >= 1.0:
        raise DatasetError(f"{img}: image is {w}x{h} but {hc.path} field 'image_size' "
                           f"{list(hc.size)} at scale {factor:g} gives "
                           f"{exp_w:g}x{exp_h:g}")


def _undistorted(rgb, alpha, hc: HyperNeRFCamera, cam: Camera, rd: _Reading):
    """`rgb` and `alpha` resampled into the pinhole `cam` when the file's camera is distorted
    or skewed (the maps are cached in `rd` by camera)."""
    if not (hc.distorted or abs(hc.skew) > DISTORTION_EPS):
        return rgb, alpha
    (h, w), factor = rgb.shape[:2], rd.factor
    key = (w, h, cam.fx, cam.fy, cam.cx, cam.cy, hc.skew * factor,
           tuple(hc.radial), tuple(hc.tangential))
    if key not in rd.maps:
        rd.maps[key] = undistortion_maps(w, h, cam.fx, cam.fy, cam.cx, cam.cy,
                                         hc.skew * factor, hc.radial, hc.tangential)
    rgb = remap(rgb, *rd.maps[key])
    alpha = None if alpha is None else remap(alpha, *rd.maps[key])
    return rgb, alpha


def _load_frame(hc: HyperNeRFCamera, i: int, name: str, rd: _Reading):
    """(camera, rgb, alpha, image path) of id index `i`: read, checked against its camera
    file, undistorted and area-downscaled."""
    img = rd.folder / f"{rd.ids[i]}.png"
    rgb, alpha = read_rgb(img, rd.bg, f"id {rd.ids[i]!r}")
    h, w = rgb.shape[:2]
    _check_image_size(img, hc, w, h, rd.factor)
    cam = hc.camera(rd.center, rd.scale, rd.factor, w, h, rd.times[i], name)
    rgb, alpha = _undistorted(rgb, alpha, hc, cam, rd)
    if rd.extra > 1:
        rgb = area_downscale(rgb, rd.extra)
        alpha = None if alpha is None else area_downscale(alpha[:, :, None], rd.extra)[:, :, 0]
        cam = downscale_camera(cam, rd.extra)
    rgb = np.ascontiguousarray(rgb, np.float32)
    alpha = None if alpha is None else np.ascontiguousarray(alpha, np.float32)
    return cam, rgb, alpha, img


def _renamed(cam: Camera, name: str) -> Camera:
    return Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                  cam.world_to_camera, cam.time, name)


def _load_frames(wanted: dict, cams: dict, rd: _Reading) -> dict[str, list[Frame]]:
    """The frames of each split; an image that two splits share is decoded once."""
    frames: dict[str, list[Frame]] = {}
    loaded_by_index: dict[int, tuple] = {}
    for s, idx in wanted.items():
        out = []
        for i in idx:
            name = f"{s}/{rd.ids[i]}"
            if i in loaded_by_index:  # test and val read the same images
                cam, rgb, alpha, img = loaded_by_index[i]
                out.append(Frame(_renamed(cam, name), rgb, alpha, img))
                continue
            loaded_by_index[i] = _load_frame(cams[i], i, name, rd)
            out.append(Frame(*loaded_by_index[i]))
        frames[s] = out
    return frames


def _initial_points(root: Path, center, scale):
    """(points in the normalised frame, colours, file) of the first point file, or Nones."""
    points = colours = None
    points_path = find_point_cloud(root, POINT_FILES)
    if points_path is not None:
        raw, colours = read_points(points_path)
        points = ((raw - center) * scale).astype(np.float32)
    return points, colours, points_path


def load_hypernerf(root, splits=("train", "test"), background=(0.0, 0.0, 0.0),
                   downscale: int = 1, frame_stride: int = 1,
                   undistort: bool = True) -> DNeRFScene:
    """Load a HyperNeRF / nerfies scene folder (see the module docstring for the format).

    `splits`: any of "train", "test" and "val" (test and val both read the ``val_ids``).
    `background`: RGBA images are composited over it (HyperNeRF images are RGB). `downscale`:
    integer S >= 1, the ``rgb/<S>x`` images (or ``rgb/1x`` averaged over S x S blocks).
    `frame_stride`: keep every n-th image of each split. `undistort`: resample distorted or
    skewed images into pinhole ones (True) or refuse them (False). Returns the same scene object
    as the D-NeRF reader. Raises DatasetError (a ValueError) naming the file on bad data.
    """
    root, splits = check_scene_args(root, splits, SPLIT_ALIASES, "HyperNeRF")
    downscale = check_downscale(downscale)
    frame_stride = check_stride(frame_stride)
    bg = check_background(background)

    scale, center, near, far = _scene_json(root)
    ids, index = _split_indices(root)
    times, top = _times(root, ids)
    folder, extra = _image_folder(root, downscale)
    factor = 1.0 / downscale if extra == 1 else 1.0  # the camera scale of the files read

    wanted = {s: index[SPLIT_ALIASES[s]][::frame_stride] for s in splits}
    cams = _checked_cameras(root, ids, wanted, folder, undistort)
    frames = _load_frames(wanted, cams, _Reading(ids, times, center, scale, folder, extra,
                                                 factor, bg))
    points, colours, points_path = _initial_points(root, center, scale)

    loaded = [f.time for fs in frames.values() for f in fs]
    scene = DNeRFScene(root=root, frames=frames, background=tuple(float(x) for x in bg),
                       initial_points=points, initial_colors=colours,
                       time_range=(min(loaded), max(loaded)) if loaded else (0.0, 1.0),
                       source_time_range=(0.0, float(top)), points_path=points_path,
                       downscale=downscale)
    scene.near, scene.far = near, far  # scene.json values, normalised frame (informative)
    scene.format = "hypernerf"
    return scene
