"""A user's capture, made up: synchronised videos of a camera rig, or one orbiting video, of a
synthetic scene in front of a textured backdrop (issue 30; docs/capture.md).

`nehad prepare` has to pose what a person films, so the project needs captures whose true
cameras it knows. These are drawn by the analytic ray caster of :mod:`nehad.data.synth` (the
objects of :func:`~nehad.data.synth.scene_objects`), with a ground and four walls around the
scene covered in a random two-scale texture (:class:`~nehad.data.synth.Surface` ``"noise"``):
structure from motion matches features on static texture, which the plain synthetic scenes have
not. The backdrop is drawn once per fixed camera and reused for each frame.

Written to `out_dir`:

- ``rig``: ``videos/camNN.mp4``, one H.264 video per fixed camera, every video the same
  `frames` frames at `fps` (frame i at time i / (frames - 1));
- ``orbit``: ``orbit.mp4``, one video from a camera that travels `orbit_degrees` around the
  scene while the objects move;
- ``truth.json``: the true cameras (``camera_to_world`` 4 x 4, Blender/OpenGL axes, world z up;
  ``focal`` in pixels; the image size), per video (rig) or per frame (orbit), and
  ``extent`` (the mean camera distance from the scene centre). Only the tests and
  ``bench/prepare.py`` read it; `nehad prepare` never does.

Numpy and PyAV only; the same arguments give the same bytes (the videos are encoded
`reproducible`, nehad.runtime.mp4, at crf 17: about the bytes crf 18 took with x264's
macroblock tree, 125 against 126 kB for a 24-frame 200x200 orbit, 2026-11-28).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from nehad.data.synth import (Box, Surface, copy_buffers, draw_objects, new_buffers,
                              orbit_camera_to_world, resolve_buffers, scene_objects)
from nehad.runtime.cameras import Camera
from nehad.runtime.images import atomic_write_bytes

__all__ = ["backdrop_objects", "rig_poses", "orbit_poses", "orbit_frames", "synthesize_capture",
           "pose_errors", "CAPTURE_KINDS"]

CAPTURE_KINDS = ("rig", "orbit")

#: Camera distance from the scene centre and the horizontal field of view of the captures.
_RADIUS = 4.0
_FOV_DEG = 50.0
#: The ground's top face (just under the objects' [-1.3, 1.3]^3) and the walls' distance.
_GROUND_Z = -1.35
_WALL = 8.0
#: The videos' H.264 quality (module doc).
_CRF = 17


def backdrop_objects() -> list[Box]:
    """A textured ground, four textured walls and six textured crates around the scene
    (unlabelled: they count as background in label masks). Cells of about 0.1 scene units:
    10-20 pixels at 400x400 from the cameras here."""
    eye = np.eye(3)
    ground = Box("ground", np.array([0.0, 0.0, _GROUND_Z - 0.05]), np.array([_WALL, _WALL, 0.05]),
                 eye, (0.85, 0.7, 0.45), Surface("noise", (0.25, 0.3, 0.55), 160), labelled=False)
    walls = []
    colours = [((0.8, 0.35, 0.3), (0.95, 0.9, 0.6)), ((0.3, 0.6, 0.8), (0.95, 0.95, 0.9)),
               ((0.45, 0.75, 0.4), (0.2, 0.2, 0.35)), ((0.7, 0.5, 0.85), (0.9, 0.8, 0.3))]
    height = 3.0
    for k, (cx, cy) in enumerate([(_WALL, 0.0), (-_WALL, 0.0), (0.0, _WALL), (0.0, -_WALL)]):
        half = (np.array([0.05, _WALL, height]) if cx else np.array([_WALL, 0.05, height]))
        first, second = colours[k]
        walls.append(Box(f"wall{k}", np.array([cx, cy, _GROUND_Z + height]), half, eye, first,
                         Surface("noise", second, int(2 * _WALL / 0.1), unlit=True),
                         labelled=False))
    props = []  # static textured crates between the scene and the walls: depth, not one plane
    palette = [(0.9, 0.55, 0.2), (0.25, 0.55, 0.35), (0.6, 0.3, 0.6), (0.85, 0.8, 0.3),
               (0.3, 0.45, 0.8), (0.75, 0.3, 0.3)]
    for k in range(6):
        az = math.radians(30.0 + 60.0 * k)
        half = np.array([0.45, 0.45, 0.5 + 0.25 * (k % 3)])
        centre = np.array([5.5 * math.cos(az), 5.5 * math.sin(az), _GROUND_Z + half[2]])
        props.append(Box(f"crate{k}", centre, half, _axis_angle_z(az + 0.4), palette[k],
                         Surface("noise", (0.95, 0.95, 0.9), 12), labelled=False))
    return [ground] + walls + props


def _axis_angle_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rig_poses(cameras: int) -> list[np.ndarray]:
    """Camera-to-world matrices of `cameras` fixed cameras on an arc of 150 degrees in front
    of the scene, at elevations alternating 12 and 30 degrees (a rig of tripods)."""
    out = []
    for c in range(cameras):
        az = math.radians(-75.0 + 150.0 * c / max(cameras - 1, 1))
        el = math.radians(12.0 if c % 2 == 0 else 30.0)
        out.append(orbit_camera_to_world(az, el, _RADIUS))
    return out


def orbit_poses(frames: int, degrees: float) -> list[np.ndarray]:
    """Camera-to-world matrices of a camera walking `degrees` around the scene over `frames`
    frames, bobbing between 15 and 25 degrees of elevation (a handheld orbit)."""
    out = []
    for i in range(frames):
        u = i / max(frames - 1, 1)
        az = math.radians(-0.5 * degrees + degrees * u)
        el = math.radians(20.0 + 5.0 * math.sin(2.0 * math.pi * u))
        out.append(orbit_camera_to_world(az, el, _RADIUS))
    return out


def _camera(c2w: np.ndarray, resolution: int, t: float) -> Camera:
    focal = 0.5 * resolution / math.tan(0.5 * math.radians(_FOV_DEG))
    return Camera.from_camera_to_world(c2w, resolution, resolution, focal, focal, time=t)


def _frame(scene: str, t: float, cam: Camera, backdrop_buffers, n_backdrop: int,
           supersample: int) -> np.ndarray:
    """uint8 (H, W, 3) of the scene at time `t` over a drawn backdrop."""
    buffers = copy_buffers(backdrop_buffers)
    draw_objects(scene_objects(scene, t), cam, buffers, supersample, first_id=n_backdrop)
    rgba = resolve_buffers(buffers, cam, supersample)
    return np.clip(np.round(rgba[..., :3] * 255.0), 0, 255).astype(np.uint8)


def orbit_frames(frames: int, degrees: float, resolution: int, scene: str = "spheres",
                 supersample: int = 2):
    """(t, camera-to-world, uint8 (H, W, 3) image) of each frame of the ``orbit`` capture, frame
    i at time i / (frames - 1), as `synthesize_capture` encodes them."""
    backdrop = backdrop_objects()
    for i, c2w in enumerate(orbit_poses(frames, degrees)):
        t = i / (frames - 1)
        cam = _camera(c2w, resolution, t)
        base = new_buffers(cam, supersample)
        draw_objects(backdrop, cam, base, supersample)
        yield t, c2w, _frame(scene, t, cam, base, len(backdrop), supersample)


def _truth_camera(c2w: np.ndarray, resolution: int) -> dict:
    focal = 0.5 * resolution / math.tan(0.5 * math.radians(_FOV_DEG))
    return {"camera_to_world": [[float(x) for x in row] for row in c2w], "focal": focal,
            "width": resolution, "height": resolution}


def synthesize_capture(out_dir, kind: str = "rig", scene: str = "spheres", resolution: int = 400,
                       frames: int = 60, cameras: int = 12, fps: float = 30.0,
                       orbit_degrees: float = 120.0, supersample: int = 2,
                       progress=None, rig=None) -> Path:
    """Write a made-up capture of `kind` (``rig`` or ``orbit``) to `out_dir` (module doc) and
    return its path. `progress`, if given, is called once per frame drawn. `rig` replaces the
    rig's cameras by these camera-to-world matrices (OpenGL axes): the tests' bad rigs."""
    from nehad.runtime.mp4 import encode

    if kind not in CAPTURE_KINDS:
        raise ValueError(f"kind: expected one of {', '.join(CAPTURE_KINDS)}, got {kind!r}")
    resolution, frames, cameras = int(resolution), int(frames), int(cameras)
    if resolution < 16 or frames < 2 or (kind == "rig" and cameras < 2):
        raise ValueError("a capture needs resolution >= 16, frames >= 2 and (rig) cameras >= 2")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    backdrop = backdrop_objects()
    times = [i / (frames - 1) for i in range(frames)]

    def tick():
        if progress is not None:
            progress()

    truth = {"kind": kind, "scene": scene, "fps": fps, "frames": frames, "times": times,
             "extent": _RADIUS}
    if kind == "rig":
        (out / "videos").mkdir(exist_ok=True)
        truth["cameras"] = {}
        for c, c2w in enumerate(rig_poses(cameras) if rig is None else rig):
            cam = _camera(c2w, resolution, 0.0)
            base = new_buffers(cam, supersample)
            draw_objects(backdrop, cam, base, supersample)
            images = []
            for t in times:
                images.append(_frame(scene, t, cam, base, len(backdrop), supersample))
                tick()
            name = f"cam{c:02d}"
            encode(images, out / "videos" / f"{name}.mp4", fps, _CRF, reproducible=True)
            truth["cameras"][name] = _truth_camera(c2w, resolution)
    else:
        images, truth["cameras"] = [], []
        for _, c2w, image in orbit_frames(frames, orbit_degrees, resolution, scene, supersample):
            images.append(image)
            truth["cameras"].append(_truth_camera(c2w, resolution))
            tick()
        encode(images, out / "orbit.mp4", fps, _CRF, reproducible=True)
    atomic_write_bytes(out / "truth.json", (json.dumps(truth, indent=1) + "\n").encode("utf-8"))
    return out


def pose_errors(scene_dir, truth_path) -> dict:
    """How well `nehad prepare` posed a made-up capture, against the true cameras of
    ``truth.json``. Structure from motion fixes the cameras only up to a similarity, so each
    error is taken after the alignment that is best for it: centres after the similarity that
    best maps the estimated centres onto the true ones (:func:`nehad.data.sfm.similarity`), as
    a fraction of ``extent``; rotations after the rotation that best maps the estimated
    orientations onto the true ones (the chordal mean of their differences). Aligning the
    orientations by the centres' fit instead would add that fit's own error: on an orbit's short
    arc a 0.3% centre error tilts it by over 0.5 degree. Returns the largest and median rotation
    error (degrees), the largest centre error and the number of cameras compared (a rig camera
    once; an orbit frame by its source time)."""
    from nehad.data.sfm import similarity

    truth = json.loads(Path(truth_path).read_text())
    est, ref = {}, {}
    for split in ("train", "test"):
        doc = json.loads((Path(scene_dir) / f"transforms_{split}.json").read_text())
        for fr in doc["frames"]:
            if truth["kind"] == "rig":
                key, true = fr["camera"], truth["cameras"][fr["camera"]]
            else:
                key = int(round(fr["source_time"] * truth["fps"]))
                true = truth["cameras"][key]
            est[key] = np.asarray(fr["transform_matrix"], dtype=np.float64)
            ref[key] = np.asarray(true["camera_to_world"], dtype=np.float64)
    keys = sorted(est)
    scale, rot, shift = similarity(np.array([est[k][:3, 3] for k in keys]),
                                   np.array([ref[k][:3, 3] for k in keys]))
    u, _, vt = np.linalg.svd(sum(ref[k][:3, :3] @ est[k][:3, :3].T for k in keys))
    turn = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt  # nearest rotation
    pos, ang = [], []
    for k in keys:
        centre = scale * rot @ est[k][:3, 3] + shift
        pos.append(float(np.linalg.norm(centre - ref[k][:3, 3])))
        r = (turn @ est[k][:3, :3]).T @ ref[k][:3, :3]
        ang.append(math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))))
    return {"cameras": len(keys), "rotation_max_deg": max(ang),
            "rotation_median_deg": float(np.median(ang)),
            "position_max": max(pos) / truth["extent"]}
