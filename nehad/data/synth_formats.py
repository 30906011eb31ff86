"""The synthetic scenes of :mod:`nehad.data.synth` written in the HyperNeRF and DyNeRF layouts
(the readers' test fixtures, docs/design.md section 5), each optionally with its D-NeRF "twin".

The same analytic ray caster draws the images; what changes is the capture and the files:

- ``hypernerf`` (monocular "vrig", as Google's HyperNeRF release): a moving "left" camera sweeps
  an arc and sees time step k = 0 .. F-1 (the ``train_ids``); a "right" camera a few degrees
  away sees about a quarter of the same time steps (the ``val_ids``). Files: ``scene.json`` (a
  scale and centre that are not the identity, so the reader's normalisation is exercised),
  ``metadata.json`` (warp/appearance id = k, camera id 0/1), ``dataset.json``,
  ``camera/<id>.json`` (nerfies fields, a principal point off the image centre, optional lens
  distortion and skew), ``rgb/1x/<id>.png`` and ``rgb/2x/<id>.png`` (RGB over `background`),
  ``points.npy`` (surface points in the raw frame).
- ``dynerf`` (multi-view video, as the Neural 3D Video release): C cameras on an arc facing the
  scene record F synchronised frames; ``cam00`` (the test camera) sits in the middle.
  ``poses_bounds.npy`` (LLFF rows), ``camXX.mp4`` per camera (H.264 in its lossless RGB profile,
  ``libx264rgb`` at crf 0, through PyAV: :func:`nehad.runtime.mp4.encode` with ``lossless``; any
  size, odd ones included, is kept exactly) or, with ``video="png"``, pre-extracted
  ``camXX/images/0000.png ...``; ``points3D_downsample2.ply`` (4DGS's name) in the world frame.

The twin (``twin=DIR``) is the D-NeRF version of exactly the same views: ``transforms_*.json``
with per-frame intrinsics and the times the other reader computes, and RGB PNGs holding the same
8-bit values (its ``test`` and ``val`` are the held-out views), so that reading both folders must
give the same cameras and images. With lens distortion the twin holds the undistorted (pinhole)
truth. Files are written atomically; the same arguments give the same bytes (checked for the
mp4 files with one PyAV/x264 build; another build may encode them differently, losslessly).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nehad.data.common import (area_downscale, atomic_write_bytes, atomic_write_json,
                               points_ply_bytes,
                               undistort_normalized)
from nehad.data.dynerf import camera_to_world_to_llff
from nehad.data.synth import (SCENES, _surface_points, orbit_camera_to_world,
                              render_view, scene_objects, synthesize_scene)
from nehad.runtime.cameras import Camera
from nehad.runtime.images import write_image
from nehad.runtime.mp4 import DEFAULT_FPS, encode

__all__ = ["FORMATS", "synthesize_format", "planned_images", "write_dnerf_twin"]

FORMATS = ("dnerf", "hypernerf", "dynerf")

#: The hypernerf writer's raw world frame: raw = normalised / SCALE + CENTER.
HYPERNERF_SCALE = 0.5
HYPERNERF_CENTER = (0.4, -0.3, 1.2)
_RADIUS = 4.0


def planned_images(format: str, frames: int, cameras: int = 4) -> int:
    """How many images :func:`synthesize_format` renders (for progress bars)."""
    if format == "hypernerf":
        return frames + len(_val_steps(frames))
    if format == "dynerf":
        return frames * cameras
    return frames + 2 * max(1, int(round(0.1 * frames)))


def _val_steps(frames: int) -> list[int]:
    n = max(1, math.ceil(frames / 4))
    return sorted({int(round(x)) for x in np.linspace(0, frames - 1, n)})


def _q8(img: np.ndarray) -> np.ndarray:
    """The 8-bit values a PNG / lossless video stores, back as float32 in [0, 1]."""
    return (np.round(np.clip(img, 0.0, 1.0) * 255.0) / 255.0).astype(np.float32)


def _u8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def _composite(rgba: np.ndarray, bg: np.ndarray) -> np.ndarray:
    return rgba[:, :, :3] + bg.astype(np.float32) * (1.0 - rgba[:, :, 3:4])


def _size(resolution) -> tuple[int, int]:
    if isinstance(resolution, (tuple, list)):
        w, h = (int(v) for v in resolution)
    else:
        w = h = int(resolution)
    if w < 4 or h < 4:
        raise ValueError(f"resolution: expected at least 4 pixels per side, got {resolution!r}")
    return w, h


def _distort_image(img: np.ndarray, cam: Camera, skew: float, k, p) -> np.ndarray:
    """The image a camera with lens distortion (k, p) and skew would see, resampled from the
    pinhole image `img` of `cam` (nerfies model; inverse of the reader's undistortion)."""
    from nehad.data.common import remap

    u = np.arange(cam.width, dtype=np.float64) + 0.5
    v = np.arange(cam.height, dtype=np.float64) + 0.5
    yd = ((v - cam.cy) / cam.fy)[:, None].repeat(cam.width, 1)
    xd = (u[None, :] - cam.cx - skew * yd) / cam.fx
    x, y = undistort_normalized(xd, yd, k, p)
    map_x = (cam.fx * x + cam.cx - 0.5).astype(np.float32)
    map_y = (cam.fy * y + cam.cy - 0.5).astype(np.float32)
    return remap(img, map_x, map_y)


# --------------------------------------------------------------------------------------------
# D-NeRF twin


def write_dnerf_twin(out, views: dict[str, list[tuple[Camera, np.ndarray, str]]],
                     points: np.ndarray | None = None, colours: np.ndarray | None = None) -> Path:
    """Write views {split: [(camera with time, (H, W, 3) float image, name)]} as a D-NeRF
    folder: ``transforms_<split>.json`` (OpenGL camera-to-world, per-frame fl_x fl_y cx cy w h)
    and ``<split>/<name>.png`` (RGB, 8 bit); `points` (in the cameras' world) as points3d.ply."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for split, items in views.items():
        (out / split).mkdir(exist_ok=True)
        records = []
        angle = None
        for cam, img, name in items:
            write_image(out / split / f"{name}.png", _q8(img))
            angle = 2.0 * math.atan(0.5 * cam.width / cam.fx)
            records.append({"file_path": f"./{split}/{name}", "time": float(cam.time),
                            "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
                            "w": cam.width, "h": cam.height,
                            "transform_matrix": [[float(x) for x in row]
                                                 for row in cam.camera_to_world_opengl]})
        atomic_write_json(out / f"transforms_{split}.json",
                          {"camera_angle_x": angle, "frames": records})
    if points is not None:
        cols = colours if colours is not None else np.full((len(points), 3), 128, np.uint8)
        atomic_write_bytes(out / "points3d.ply", points_ply_bytes(np.asarray(points, np.float32), cols))
    return out


# --------------------------------------------------------------------------------------------
# HyperNeRF


@dataclass(frozen=True)
class _HyperCapture:
    """What every view of a hypernerf write shares: the scene drawn, the image size and
    intrinsics, the lens (radial `k`, tangential `p`, `skew`), the arc the cameras sweep (from
    azimuth `az0`, elevation `el0`) and the raw frame's `center`."""

    out: Path
    scene: str
    w: int
    h: int
    focal: float
    px: float
    py: float
    k: tuple
    p: tuple
    skew: float
    distorted: bool
    az0: float
    el0: float
    frames: int
    center: np.ndarray
    fixed_time: float | None
    bg: np.ndarray
    supersample: int
    progress: object


def _hypernerf_capture(out: Path, scene, size, frames, rng, fixed_time, progress, bg,
                       distortion, skew, fov_deg, supersample) -> _HyperCapture:
    """The capture of a hypernerf write; draws the arc's start from `rng`."""
    w, h = size
    focal = 0.5 * w / math.tan(0.5 * math.radians(fov_deg))
    k = tuple(float(v) for v in (distortion or (0.0,) * 5)[:3])
    p = tuple(float(v) for v in (distortion or (0.0,) * 5)[3:5])
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    el0 = math.radians(rng.uniform(20.0, 35.0))
    return _HyperCapture(out, scene, w, h, focal, 0.53 * w, 0.48 * h,  # off-centre principal point
                         k, p, skew, distortion is not None, az0, el0, frames,
                         np.asarray(HYPERNERF_CENTER), fixed_time, bg, supersample, progress)


def _hypernerf_camera(cap: _HyperCapture, rig: str, kk: int) -> Camera:
    """The pinhole camera of time step `kk` of the "left" or "right" rig camera: along a 60
    degree arc, the right one 8 degrees further, elevation swinging by 6 degrees."""
    frames = cap.frames
    steps = frames - 1 if frames > 1 else 1
    arc, baseline = math.radians(60.0), math.radians(8.0)
    s = kk / steps if frames > 1 else 0.0
    az = cap.az0 + arc * s + (baseline if rig == "right" else 0.0)
    el = cap.el0 + math.radians(6.0) * math.sin(2.0 * math.pi * s)
    c2w = orbit_camera_to_world(az, el, _RADIUS)
    t = kk / (frames - 1) if frames > 1 else 0.0  # = warp_id / max(warp_id), the reader's
    return Camera.from_camera_to_world(c2w, cap.w, cap.h, cap.focal, cap.focal, cap.px, cap.py,
                                       time=t)


def _hypernerf_camera_doc(cap: _HyperCapture, cam: Camera) -> dict:
    """The nerfies ``camera/<id>.json`` of `cam` (position in the raw frame)."""
    r = cam.world_to_camera[:3, :3]
    return {"orientation": [[float(x) for x in row] for row in r],
            "position": [float(x) for x in cam.centre / HYPERNERF_SCALE + cap.center],
            "focal_length": cap.focal, "principal_point": [cap.px, cap.py],
            "skew": float(cap.skew), "pixel_aspect_ratio": 1.0, "radial_distortion": list(cap.k),
            "tangential_distortion": list(cap.p), "image_size": [cap.w, cap.h]}


def _write_hypernerf_view(cap: _HyperCapture, rig: str, kk: int):
    """Render time step `kk` from the `rig` camera and write its images (1x, 2x; distorted
    when the lens is) and camera file. Returns (image id, camera, pinhole image)."""
    cam = _hypernerf_camera(cap, rig, kk)
    t_scene = cam.time if cap.fixed_time is None else cap.fixed_time
    pinhole = _composite(render_view(scene_objects(cap.scene, t_scene), cam, cap.supersample),
                         cap.bg)
    img = pinhole
    if cap.distorted or cap.skew:
        img = _distort_image(pinhole, cam, cap.skew, cap.k, cap.p)
    image_id = f"{rig}_{kk:06d}"
    write_image(cap.out / "rgb" / "1x" / f"{image_id}.png", _q8(img))
    write_image(cap.out / "rgb" / "2x" / f"{image_id}.png", _q8(area_downscale(img, 2)))
    if cap.progress is not None:
        cap.progress()
    atomic_write_json(cap.out / "camera" / f"{image_id}.json", _hypernerf_camera_doc(cap, cam))
    return image_id, cam, pinhole


def _write_hypernerf_points(out: Path, scene, points, fixed_time, rng, center: np.ndarray):
    """Write `points` surface points to ``points.npy`` in the raw frame; returns them in the
    normalised frame (what the reader will compute) and their colours."""
    t_pts = 0.5 if fixed_time is None else fixed_time
    pts, cols = _surface_points(scene_objects(scene, t_pts), int(points), rng)
    raw = pts.astype(np.float64) / HYPERNERF_SCALE + center
    atomic_write_bytes(out / "points.npy", _npy_bytes(raw))
    return (raw - center) * HYPERNERF_SCALE, cols


def _write_hypernerf(out: Path, scene, size, frames, seed, fixed_time, points, progress, bg,
                     twin, distortion, skew, fov_deg, supersample):
    rng = np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])
    cap = _hypernerf_capture(out, scene, size, frames, rng, fixed_time, progress, bg,
                             distortion, skew, fov_deg, supersample)
    for sub in ("camera", "rgb/1x", "rgb/2x"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    plan = [("left", 0, kk, "train") for kk in range(frames)]
    plan += [("right", 1, kk, "val") for kk in _val_steps(frames)]
    ids, train_ids, val_ids, meta = [], [], [], {}
    twin_views: dict[str, list] = {"train": [], "val": [], "test": []}
    for rig, cam_id, kk, split in plan:
        image_id, cam, pinhole = _write_hypernerf_view(cap, rig, kk)
        ids.append(image_id)
        (train_ids if split == "train" else val_ids).append(image_id)
        meta[image_id] = {"warp_id": kk, "appearance_id": kk, "camera_id": cam_id}
        for twin_split in (("train",) if split == "train" else ("val", "test")):
            twin_views[twin_split].append((cam, pinhole, image_id))
    atomic_write_json(out / "scene.json", {"scale": HYPERNERF_SCALE,
                                           "center": cap.center.tolist(),
                                           "near": (_RADIUS - 2.3) * 1.0, "far": _RADIUS + 2.3})
    atomic_write_json(out / "metadata.json", meta)
    atomic_write_json(out / "dataset.json", {"count": len(ids), "num_exemplars": len(train_ids),
                                             "ids": ids, "train_ids": train_ids,
                                             "val_ids": val_ids})
    pts = cols = None
    if points > 0:
        pts, cols = _write_hypernerf_points(out, scene, points, fixed_time, rng, cap.center)
    if twin is not None:
        write_dnerf_twin(twin, twin_views, pts, cols)


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


# --------------------------------------------------------------------------------------------
# DyNeRF


def _write_dynerf(out: Path, scene, size, frames, seed, fixed_time, points, progress, bg, twin,
                  cameras, video, fov_deg, supersample):
    w, h = size
    if cameras < 2:
        raise ValueError(f"cameras: a DyNeRF scene needs at least 2 cameras, got {cameras}")
    if video not in ("mp4", "png"):
        raise ValueError(f"video: expected 'mp4' or 'png', got {video!r}")
    rng = np.random.default_rng(np.random.SeedSequence(int(seed)).spawn(1)[0])
    focal = 0.5 * w / math.tan(0.5 * math.radians(fov_deg))
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    el = math.radians(rng.uniform(15.0, 30.0))
    step = math.radians(50.0) / max(cameras - 1, 1)
    # cam00 in the middle of the rig, the others alternately left and right of it
    offsets = [0.0] + [step * ((j + 1) // 2) * (1 if j % 2 == 0 else -1) for j in range(cameras - 1)]
    digits = max(2, len(str(cameras - 1)))
    rows = []
    twin_views: dict[str, list] = {"train": [], "val": [], "test": []}
    for c, off in enumerate(offsets):
        name = f"cam{c:0{digits}d}"
        c2w_gl = orbit_camera_to_world(az0 + off, el, _RADIUS)
        c2w_cv = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])
        pose = camera_to_world_to_llff(c2w_cv, h, w, focal)
        rows.append(np.concatenate([pose.reshape(-1), [_RADIUS - 2.3, _RADIUS + 2.3]]))
        frames_u8 = []
        for kk in range(frames):
            t = kk / (frames - 1) if frames > 1 else 0.0
            cam = Camera.from_camera_to_world(c2w_cv, w, h, focal, focal, w / 2.0, h / 2.0,
                                              convention="opencv", time=t)
            t_scene = t if fixed_time is None else fixed_time
            img = _composite(render_view(scene_objects(scene, t_scene), cam, supersample), bg)
            frames_u8.append(_u8(img))
            if progress is not None:
                progress()
            entry = (cam, img, f"{name}_{kk:04d}")
            if c == 0:
                twin_views["test"].append(entry)
                twin_views["val"].append(entry)
            else:
                twin_views["train"].append(entry)
        if video == "mp4":
            encode(frames_u8, out / f"{name}.mp4", DEFAULT_FPS, lossless=True)
        else:
            (out / name / "images").mkdir(parents=True, exist_ok=True)
            for kk, arr in enumerate(frames_u8):
                write_image(out / name / "images" / f"{kk:04d}.png", arr.astype(np.float32) / 255.0)
    atomic_write_bytes(out / "poses_bounds.npy", _npy_bytes(np.stack(rows)))
    pts = cols = None
    if points > 0:
        t_pts = 0.5 if fixed_time is None else fixed_time
        pts, cols = _surface_points(scene_objects(scene, t_pts), int(points), rng)
        atomic_write_bytes(out / "points3D_downsample2.ply", points_ply_bytes(pts, cols))
    if twin is not None:
        write_dnerf_twin(twin, twin_views, pts, cols)


# --------------------------------------------------------------------------------------------


def synthesize_format(out_dir, format: str = "dnerf", scene: str = "spheres", resolution=64,
                      frames: int = 50, seed: int = 0, fixed_time: float | None = None,
                      points: int = 2000, progress=None, cameras: int = 4,
                      background=(0.0, 0.0, 0.0), twin=None, distortion=None, skew: float = 0.0,
                      video: str = "mp4", fov_deg: float = 45.0, supersample: int = 3) -> Path:
    """Write a synthetic dynamic scene in `format` ("dnerf", "hypernerf", "dynerf") to `out_dir`.

    "dnerf" is :func:`nehad.data.synth.synthesize_scene` (RGBA, monocular per timestamp; the
    options below it does not take are ignored). For the others: `resolution` is an int (square)
    or (width, height); `frames` the time steps (HyperNeRF: train images; DyNeRF: frames per
    video); `cameras` the DyNeRF camera count (cam00 is the test camera); `background` the colour
    the RGB images are composited over; `twin` a folder that gets the D-NeRF version of the same
    views; `distortion` = (k1, k2, k3, p1, p2) and `skew` (HyperNeRF) give the camera files lens
    distortion and the images the matching warp; `video` = "mp4" (lossless H.264 per camera) or
    "png" (pre-extracted frames). `fixed_time` freezes the content (file times still count the
    frames). `points` > 0 writes that many surface points at t = 0.5.
    """
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {format!r}")
    if scene not in SCENES:
        raise ValueError(f"scene: unknown synthetic scene {scene!r}; expected one of "
                         f"{', '.join(SCENES)}")
    frames = int(frames)
    if frames < 1:
        raise ValueError(f"frames: expected an integer >= 1, got {frames}")
    if fixed_time is not None and not 0.0 <= float(fixed_time) <= 1.0:
        raise ValueError(f"fixed_time: expected a time in [0, 1], got {fixed_time}")
    if format == "dnerf":
        if not isinstance(resolution, int):
            raise ValueError("resolution: the D-NeRF writer draws square images (an int)")
        return synthesize_scene(out_dir, scene=scene, resolution=resolution, frames=frames,
                                seed=seed, fixed_time=fixed_time, points=points,
                                progress=progress, fov_deg=fov_deg, supersample=supersample)
    size = _size(resolution)
    bg = np.asarray(background, np.float64).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.size != 3 or not np.isfinite(bg).all():
        raise ValueError(f"background: expected three finite numbers, got {background!r}")
    if distortion is not None and len(distortion) != 5:
        raise ValueError(f"distortion: expected (k1, k2, k3, p1, p2), got {distortion!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if format == "hypernerf":
        _write_hypernerf(out, scene, size, frames, seed, fixed_time, points, progress, bg, twin,
                         distortion, float(skew), fov_deg, supersample)
    else:
        _write_dynerf(out, scene, size, frames, seed, fixed_time, points, progress, bg, twin,
                      int(cameras), video, fov_deg, supersample)
    return out
