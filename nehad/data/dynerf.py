"""Reader for DyNeRF ("Neural 3D Video", Li et al. 2022) multi-view video captures, read the way
4DGS reads them (``scene/neural_3D_dataset_NDC.py``; docs/design.md sections 3 and 5).

Layout::

    poses_bounds.npy   (N, 17) float: LLFF poses, one row per camera in sorted camera order
    cam00.mp4 ... camNN.mp4      one synchronised video per camera (cam00 is the test camera)
    cam00/images/0000.png ...    frames extracted from the video (written on first use, or
                                 shipped pre-extracted instead of the videos)
    points3D_downsample2.ply     optional initial points (4DGS's COLMAP cloud), world frame

- ``poses_bounds.npy`` (LLFF ``imgs2poses``): row i is ``[P (3x5) row-major, near, far]`` where
  ``P[:, :3]`` is the camera-to-world rotation with LLFF column order (down, right, back),
  ``P[:, 3]`` the camera centre and ``P[:, 4] = (H, W, focal)`` the size and focal length in
  pixels of the images the poses were estimated on. The OpenCV camera-to-world is
  ``[right, down, forward] = [P1, P0, -P2]`` (4DGS reaches the same matrix through OpenGL axes).
  Poses are used as they are (4DGS no longer recentres them); near/far are kept on the scene.
- Cameras are the sorted ``cam*`` names (videos ``cam*.mp4`` or folders ``cam*/images``); row i of
  the poses belongs to the i-th camera, and their counts must agree. The first camera (cam00 in
  DyNeRF) is the ``test`` split (alias ``val``), the others the ``train`` split (4DGS
  ``eval_index = 0``).
- Frames: a video is decoded with PyAV once and its frames cached as ``camXX/images/%04d.png``
  (4DGS's cache location), written into a temporary folder that is renamed into place when
  complete, so an interrupted extraction leaves no partial cache. A folder of PNGs is read as it
  is, in natural name order.
- Intrinsics: ``focal`` is rescaled to the decoded frame size (``fx = focal * w / W``,
  ``fy = focal * h / H``), principal point at the image centre (LLFF). ``downscale`` averages
  S x S blocks as the D-NeRF reader does; the ``dynerf`` preset uses 2 (1352 x 1014 from the
  2704 x 2028 videos, the paper's resolution, which 4DGS gets by LANCZOS resizing).
- Time: the videos are cut to a common length n = min(frame counts, `max_frames` = 300, 4DGS's
  cap) and frame k has ``t = k / (n - 1)``, so the 300 frames of a DyNeRF video span [0, 1]
  (docs/design.md section 3; 4DGS uses k / 300). `frame_stride` keeps every s-th frame (k = 0, s, 2s, ...) with
  the same times, so a strided run and a full one agree on what t means.

Memory: every loaded frame is an (H, W, 3) float32 array; 19 train cameras x 300 frames at
1352 x 1014 are 94 GB, so CPU runs need ``frame_stride`` and/or a larger ``downscale``.

Bad data (no poses file, a pose count that does not match the cameras, an unreadable video or
frame) raises :class:`~nehad.data.dnerf.DatasetError` naming the file. Numpy and PyAV only.
"""

from __future__ import annotations

from fractions import Fraction

import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from nehad.data.common import (check_background, check_downscale, check_rotation, check_stride,
                               find_point_cloud, read_points, read_rgb)
from nehad.data.common import (DatasetError, DNeRFScene, Frame, area_downscale, check_scene_args,
                              downscale_camera)
from nehad.runtime.cameras import Camera, CameraError
from nehad.runtime.images import STILL_SUFFIXES

__all__ = ["load_dynerf", "llff_to_camera_to_world", "camera_to_world_to_llff", "extract_frames",
           "find_cameras", "is_dynerf", "POINT_FILES", "MAX_FRAMES", "TEST_CAMERA_INDEX"]

#: Initial point files looked for, in this order (world frame of the poses).
POINT_FILES = ("points3D_downsample2.ply", "points3D_downsample.ply", "points3D.ply",
               "points3d.ply", "fused.ply", "points3D_dense.ply")
#: 4DGS reads at most this many frames per video.
MAX_FRAMES = 300
#: Index (in sorted camera order) of the held-out camera: cam00.
TEST_CAMERA_INDEX = 0
SPLITS = ("train", "test", "val")
_CAM_NAME = re.compile(r"^cam.*$")


def is_dynerf(root) -> bool:
    return (Path(root) / "poses_bounds.npy").is_file()


def _natural_key(name: str):
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def llff_to_camera_to_world(pose: np.ndarray) -> np.ndarray:
    """4x4 OpenCV camera-to-world of an LLFF 3x5 (or 3x4) pose (columns down, right, back, c)."""
    p = np.asarray(pose, np.float64)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = p[:, 1], p[:, 0], -p[:, 2], p[:, 3]
    return c2w


def camera_to_world_to_llff(c2w: np.ndarray, height: float, width: float,
                            focal: float) -> np.ndarray:
    """The LLFF 3x5 pose of an OpenCV camera-to-world (inverse of llff_to_camera_to_world)."""
    c2w = np.asarray(c2w, np.float64)
    p = np.zeros((3, 5))
    p[:, 0], p[:, 1], p[:, 2], p[:, 3] = c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]
    p[:, 4] = (height, width, focal)
    return p


def find_cameras(root: Path) -> list[tuple[str, Path | None, Path | None]]:
    """Sorted (name, video or None, images folder or None) of every camera in `root`."""
    names: dict[str, list] = {}
    for p in root.iterdir():
        if p.is_file() and p.suffix.lower() == ".mp4" and _CAM_NAME.match(p.stem):
            names.setdefault(p.stem, [None, None])[0] = p
        elif p.is_dir() and _CAM_NAME.match(p.name) and _frame_files(p / "images"):
            names.setdefault(p.name, [None, None])[1] = p / "images"
    return [(n, *names[n]) for n in sorted(names, key=_natural_key)]


def _frame_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    files = [p for p in folder.iterdir()
             if p.suffix.lower() in STILL_SUFFIXES and not p.name.startswith(".")]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _video_error(video: Path, exc: Exception) -> DatasetError:
    return DatasetError(f"{video}: cannot decode video ({type(exc).__name__}: {exc})")


def probe_video(video: Path) -> tuple[int, Fraction]:
    """(frame count, frame rate) of a video from its container (the packet count when the
    header does not say; rate 0 when it says none); DatasetError naming it when it cannot be
    read, has no video stream or no frames. The DyNeRF reader and `nehad prepare` read videos
    through it."""
    import av

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise DatasetError(f"{video}: holds no video stream")
            stream = container.streams.video[0]
            rate = Fraction(stream.average_rate or stream.guessed_rate or 0)
            n = int(stream.frames or 0)
            if n <= 0:
                n = sum(1 for pkt in container.demux(stream) if pkt.size)
    except DatasetError:
        raise
    except Exception as exc:  # av.error.FFmpegError and friends: corrupt or not a video
        raise _video_error(video, exc) from None
    if n <= 0:
        raise DatasetError(f"{video}: holds no frames")
    return n, rate


def extract_frames(video: Path, dest: Path) -> list[Path]:
    """Decode `video` with PyAV into ``dest/0000.png, 0001.png, ...`` (8-bit RGB), atomically:
    the frames go to a temporary folder beside `dest` that is renamed to `dest` only when every
    frame was written. Returns the frame files."""
    import av
    import cv2

    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        n = 0
        try:
            with av.open(str(video)) as container:
                if not container.streams.video:
                    raise DatasetError(f"{video}: holds no video stream")
                for frame in container.decode(container.streams.video[0]):
                    rgb = frame.to_ndarray(format="rgb24")
                    ok = cv2.imwrite(str(tmp / f"{n:04d}.png"), rgb[:, :, ::-1],
                                     [cv2.IMWRITE_PNG_COMPRESSION, 1])
                    if not ok:
                        raise OSError(f"{tmp / f'{n:04d}.png'}: cannot write frame")
                    n += 1
        except (DatasetError, OSError):
            raise
        except Exception as exc:  # av.error.FFmpegError and friends
            raise _video_error(video, exc) from None
        if n == 0:
            raise DatasetError(f"{video}: holds no frames")
        try:
            os.rename(tmp, dest)
        except OSError:
            if not _frame_files(dest):  # not a concurrent extraction that finished first
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return _frame_files(dest)


def _read_poses(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: poses file not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise DatasetError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.dtype.kind not in "fiu":
        raise DatasetError(f"{path}: expected an (N, 17) array of numbers (LLFF poses_bounds), "
                           f"got shape {arr.shape} {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise DatasetError(f"{path}: holds NaN or infinite values")
    return arr


def _matched_cameras(root: Path, poses_path: Path, poses: np.ndarray,
                     splits: tuple) -> list[tuple[str, Path | None, Path | None]]:
    """The cameras of `root` (:func:`find_cameras`), one per row of the poses file, and at
    least two when the train split is asked for."""
    cameras = find_cameras(root)
    if len(cameras) != len(poses):
        names = ", ".join(c[0] for c in cameras[:8]) + (", ..." if len(cameras) > 8 else "")
        raise DatasetError(f"{poses_path}: holds {len(poses)} camera poses but {root} has "
                           f"{len(cameras)} camera videos / frame folders"
                           + (f" ({names})" if cameras else " (no cam*.mp4 or cam*/images)"))
    if len(cameras) < 2 and "train" in splits:
        raise DatasetError(f"{root}: needs at least two cameras (cam00 is held out for testing), "
                           f"found {len(cameras)}")
    return cameras


def _camera_poses(poses: np.ndarray, cameras, poses_path: Path):
    """Every camera's OpenCV camera-to-world and (height, width, focal), checked before any
    decoding."""
    c2ws, intr = [], []
    for i, row in enumerate(poses):
        p = row[:15].reshape(3, 5)
        c2w = llff_to_camera_to_world(p)
        check_rotation(c2w[:3, :3], poses_path, f"row {i} ({cameras[i][0]}) rotation")
        h, w, f = p[:, 4]
        if min(h, w, f) <= 0:
            raise DatasetError(f"{poses_path}: row {i} ({cameras[i][0]}): height, width and focal "
                               f"must be positive, got {h:g}, {w:g}, {f:g}")
        c2ws.append(c2w)
        intr.append((h, w, f))
    return c2ws, intr


def _time_axis(cameras, max_frames: int, frame_stride: int):
    """(n, times, keep): a frame count common to every camera (cheap: cache or container),
    capped at `max_frames`, the time of each frame and the frame indices kept."""
    counts = []
    for name, video, images in cameras:
        counts.append(len(_frame_files(images)) if images is not None
                      else probe_video(video)[0])
    n = min(min(counts), int(max_frames))
    times = [k / (n - 1) if n > 1 else 0.0 for k in range(n)]
    return n, times, list(range(0, n, frame_stride))


def _split_frames(splits: tuple, camera_count: int, load_camera) -> dict[str, list[Frame]]:
    """The frames of each split (train: every camera but cam00; test, val: cam00), each camera
    loaded once by `load_camera(index)` and its frames renamed per split."""
    split_cams = {"train": [i for i in range(camera_count) if i != TEST_CAMERA_INDEX],
                  "test": [TEST_CAMERA_INDEX], "val": [TEST_CAMERA_INDEX]}
    frames: dict[str, list[Frame]] = {}
    cache: dict[int, list[Frame]] = {}
    for s in splits:
        out = []
        for i in split_cams[s]:
            if i not in cache:
                cache[i] = load_camera(i)
            out.extend(Frame(_renamed(f.camera, f"{s}/{f.camera.name}"), f.image, f.alpha,
                             f.path) for f in cache[i])
        frames[s] = out
    return frames


def _initial_points(root: Path):
    """(float32 points, colours, file) of the first of POINT_FILES in `root`, or Nones."""
    points = colours = None
    points_path = find_point_cloud(root, POINT_FILES)
    if points_path is not None:
        pts, colours = read_points(points_path)
        points = pts.astype(np.float32)
    return points, colours, points_path


def load_dynerf(root, splits=("train", "test"), background=(0.0, 0.0, 0.0), downscale: int = 1,
                frame_stride: int = 1, max_frames: int = MAX_FRAMES) -> DNeRFScene:
    """Load a DyNeRF scene folder (see the module docstring for the format).

    `splits`: any of "train" (every camera but cam00), "test" and "val" (both cam00).
    `background`: RGBA frames are composited over it (video frames are RGB). `downscale`: integer
    area downscale. `frame_stride`: keep frames 0, s, 2s, ... `max_frames`: cap on the frames
    per video (300, as 4DGS). Videos of the loaded cameras are decoded and cached on first use.
    Returns the same scene object as the D-NeRF reader; DatasetError names the file on bad data.
    """
    root, splits = check_scene_args(root, splits, SPLITS, "DyNeRF")
    downscale = check_downscale(downscale)
    frame_stride = check_stride(frame_stride)
    if isinstance(max_frames, bool) or int(max_frames) < 1:
        raise ValueError(f"max_frames: expected an integer >= 1, got {max_frames!r}")
    bg = check_background(background)

    poses_path = root / "poses_bounds.npy"
    poses = _read_poses(poses_path)
    cameras = _matched_cameras(root, poses_path, poses, splits)
    c2ws, intr = _camera_poses(poses, cameras, poses_path)
    n, times, keep = _time_axis(cameras, max_frames, frame_stride)

    def load_camera(i: int) -> list[Frame]:
        return _load_camera(i, cameras[i], c2ws[i], intr[i], poses_path, keep, times, bg,
                            downscale)

    frames = _split_frames(splits, len(cameras), load_camera)
    points, colours, points_path = _initial_points(root)
    loaded = [f.time for fs in frames.values() for f in fs]
    scene = DNeRFScene(root=root, frames=frames, background=tuple(float(x) for x in bg),
                       initial_points=points, initial_colors=colours,
                       time_range=(min(loaded), max(loaded)) if loaded else (0.0, 1.0),
                       source_time_range=(0.0, float(max(n - 1, 0))), points_path=points_path,
                       downscale=downscale)
    scene.near = float(poses[:, 15].min())
    scene.far = float(poses[:, 16].max())
    scene.format = "dynerf"
    scene.num_frames = n
    return scene


def _renamed(cam: Camera, name: str) -> Camera:
    return Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.world_to_camera,
                  cam.time, name)


def _load_camera(i, cam_entry, c2w, intr, poses_path, keep, times, bg, downscale):
    name, video, images = cam_entry
    files = _frame_files(images) if images is not None else []
    if not files:
        files = extract_frames(video, video.parent / name / "images")
    if len(files) <= keep[-1]:
        src = video if video is not None else images
        raise DatasetError(f"{src}: has {len(files)} frames, fewer than the {keep[-1] + 1} "
                           f"needed")
    h_pose, w_pose, focal = intr
    out = []
    for k in keep:
        path = files[k]
        rgb, alpha = read_rgb(path, bg, f"frame {k} of {name}")
        h, w = rgb.shape[:2]
        sx, sy = w / w_pose, h / h_pose
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise DatasetError(f"{path}: frame is {w}x{h} but {poses_path} row {i} ({name}) says "
                               f"{w_pose:g}x{h_pose:g}: the aspect ratios differ")
        try:
            cam = Camera.from_camera_to_world(c2w, w, h, focal * sx, focal * sy, w / 2.0, h / 2.0,
                                              convention="opencv", time=times[k],
                                              name=f"{name}/{k:04d}")
        except (CameraError, np.linalg.LinAlgError) as exc:
            raise DatasetError(f"{poses_path}: row {i} ({name}): invalid camera ({exc})") from None
        if downscale > 1:
            rgb = area_downscale(rgb, downscale)
            alpha = None if alpha is None else area_downscale(alpha[:, :, None], downscale)[:, :, 0]
            cam = downscale_camera(cam, downscale)
        out.append(Frame(cam, np.ascontiguousarray(rgb, np.float32),
                         None if alpha is None else np.ascontiguousarray(alpha, np.float32), path))
    return out
