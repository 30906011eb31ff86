"""The stress suite: one synthetic scene per failure class of dynamic scenes, MuJoCo protocol.

Each scene is drawn by the analytic ray caster of :mod:`nehad.data.synth` (exact intersections,
nothing shared with a Gaussian rasteriser) and written the way the MuJoCo scenes of
``../shared/data`` are laid out (docs/results.md, "The stress suite"):

- a rig of 12 fixed cameras around the scene (four at the sides, one above, one high diagonal,
  four at 45 degrees between the sides, two low), 50 degrees horizontal field of view, looking at a
  point above the floor;
- ``frames`` timestamps ``t_k = k / (frames - 1)``, each seen by ONE camera of the rig (the rig is
  cycled in a fixed shuffled order, monocular per timestamp);
- split by blocks of 20 consecutive timestamps: 14 train, 3 test, 3 val;
- RGBA PNGs over a transparent background, an opaque unlit white floor (white over the white
  evaluation background, as MuJoCo's floor), per-object label masks ``SPLIT/masks/r_XXXX.png`` and
  ``class_mapping.json`` (the floor is background);
- ``fused.ply``: 100k random points in a cube with random colours, the MuJoCo initial cloud.

The world is z-up; the floor's top is z = 0. Scenes (the failure they probe):

``occluder``
    a small sphere on a long loop that passes behind a large static wall;
``crossing``
    two identical spheres whose paths cross (at different times);
``scaling``
    a sphere that grows 5.6-fold and a box that shrinks 5-fold;
``split_merge``
    one sphere splitting into two, and two spheres merging into one;
``spinning_textures``
    a checkered sphere that spins and bounces, a striped box that spins;
``thin_rod``
    a rod 23 times longer than it is thick, spinning four turns;
``fast_few_frames``
    a ball that flies across the scene within 15% of the time range (seen in about 12 train
    frames) and is hidden under the floor the rest of the time, beside a still block.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from nehad.data.common import points_ply_bytes
from nehad.runtime.cameras import Camera
from nehad.runtime.images import atomic_write_bytes

from .synth import (Box, Sphere, Surface, _axis_angle, class_mapping,
                    orbit_camera_to_world, write_frame)

__all__ = ["FLOOR", "STRESS_SCENES", "stress_objects", "rig_cameras", "rig_camera", "stress_plan",
           "synthesize_stress_scene", "synthesize_stress_suite"]

#: One scene per failure class (module docstring).
STRESS_SCENES = ("occluder", "crossing", "scaling", "split_merge", "spinning_textures",
                 "thin_rod", "fast_few_frames")

FLOOR = Box("floor", np.array([0.0, 0.0, -0.02]), np.array([4.0, 4.0, 0.02]), np.eye(3),
             (1.0, 1.0, 1.0), surface=Surface(unlit=True), labelled=False)
_TARGET = (0.0, 0.0, 0.4)
_FOV_DEG = 50.0
_BLOCK, _BLOCK_TRAIN, _BLOCK_TEST = 20, 14, 3  # per 20 timestamps: 14 train, 3 test, 3 val
_RIG_ORDER = (11, 6, 5, 7, 0, 4, 10, 2, 9, 1, 8, 3)  # which rig camera sees timestamp k (k mod 12)


def _unknown(name: str) -> ValueError:
    return ValueError(f"scene: unknown stress scene {name!r}; expected one of "
                      f"{', '.join(STRESS_SCENES)}")


def _smooth(x: float) -> float:
    """Smoothstep of x clipped to [0, 1]."""
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _occluder(t: float) -> list:
    """A small sphere on a long loop that passes behind a large static wall."""
    th = 2.0 * math.pi * t
    return [
        FLOOR,
        Box("wall", np.array([0.0, 0.0, 0.75]), np.array([0.06, 1.1, 0.75]), np.eye(3),
            (0.2, 0.3, 0.9)),
        Sphere("sphere", np.array([1.0 * math.cos(th), 1.45 * math.sin(th),
                                   0.4 + 0.25 * math.sin(2.0 * th)]), 0.11, (1.0, 0.55, 0.1)),
    ]


def _crossing(t: float) -> list:
    """Two identical spheres whose paths cross (at different times)."""
    colour = (0.35, 0.8, 0.45)
    return [
        FLOOR,
        Sphere("sphere_1", np.array([2.2 * (t - 0.35), 1.5 * (t - 0.35), 0.25]), 0.25, colour),
        Sphere("sphere_2", np.array([2.2 * (t - 0.65), -1.5 * (t - 0.65), 0.25]), 0.25, colour),
    ]


def _scaling(t: float) -> list:
    """A sphere that grows 5.6-fold and a box that shrinks 5-fold."""
    r = 0.08 * (0.45 / 0.08) ** t
    h = 0.4 * (0.08 / 0.4) ** t
    return [
        FLOOR,
        Sphere("grower", np.array([-0.6, -0.1, r]), r, (0.9, 0.3, 0.25)),
        Box("shrinker", np.array([0.6, 0.3, h]), np.array([h, h, h]),
            _axis_angle([0.0, 0.0, 1.0], 0.5), (0.25, 0.5, 0.9)),
    ]


def _split_merge(t: float) -> list:
    """One sphere splitting into two, and two spheres merging into one."""
    split = _smooth((t - 0.1) / 0.4)
    merge = 1.0 - _smooth((t - 0.5) / 0.4)
    a = np.array([-0.6, -0.3, 0.22])
    m = np.array([0.6, 0.5, 0.22])
    pink, blue = (0.85, 0.3, 0.6), (0.2, 0.6, 0.9)
    return [
        FLOOR,
        Sphere("piece_stays", a, 0.22, pink),
        Sphere("piece_splits_off", a + split * np.array([0.9, -0.6, 0.0]), 0.22, pink),
        Sphere("merger_1", m + merge * np.array([0.0, 0.9, 0.0]), 0.22, blue),
        Sphere("merger_2", m + merge * np.array([-0.8, -0.4, 0.0]), 0.22, blue),
    ]


def _spinning_textures(t: float) -> list:
    """A checkered sphere that spins and bounces, a striped box that spins."""
    r = 0.35
    return [
        FLOOR,
        Sphere("checker_sphere",
               np.array([-0.5 + 1.0 * t, -0.2, r + 0.7 * abs(math.sin(3.0 * math.pi * t))]), r,
               (0.6, 0.2, 0.8), rotation=_axis_angle([0.3, 0.2, 1.0], 6.0 * math.pi * t),
               surface=Surface("checker", (0.95, 0.9, 0.3), cells=8)),
        Box("striped_box", np.array([0.7, 0.6, 0.3]), np.array([0.3, 0.2, 0.3]),
            _axis_angle([0.0, 0.0, 1.0], 4.0 * math.pi * t), (0.1, 0.5, 0.3),
            surface=Surface("stripes", (0.95, 0.95, 0.95), cells=6)),
    ]


def _thin_rod(t: float) -> list:
    """A rod 23 times longer than it is thick, spinning four turns."""
    return [
        FLOOR,
        Box("rod", np.array([0.0, 0.0, 0.6]), np.array([0.7, 0.03, 0.03]),
            _axis_angle([0.3, 0.2, 1.0], 8.0 * math.pi * t), (0.9, 0.25, 0.2)),
    ]


def _fast_few_frames(t: float) -> list:
    """A ball that flies across the scene within 15% of the time range and is hidden under the
    floor the rest of the time, beside a still block."""
    u = (t - 0.33) / 0.15  # in flight over timestamps 40-57: test frames 54-56 see it
    if u < 0.0:
        ball = np.array([-1.5, 0.3, -0.6])  # under the floor: hidden from every camera
    elif u > 1.0:
        ball = np.array([1.5, 0.3, -0.6])
    else:
        ball = np.array([-1.5 + 3.0 * u, 0.3, -0.3 + 6.4 * u * (1.0 - u)])
    return [
        FLOOR,
        Box("block", np.array([0.0, -0.7, 0.25]), np.array([0.25, 0.25, 0.25]),
            _axis_angle([0.0, 0.0, 1.0], 0.3), (0.3, 0.7, 0.35)),
        Sphere("ball", ball, 0.15, (0.95, 0.8, 0.1)),
    ]


#: The objects of each stress scene as a function of time, in STRESS_SCENES order.
_SCENE_OBJECTS = {"occluder": _occluder, "crossing": _crossing, "scaling": _scaling,
                  "split_merge": _split_merge, "spinning_textures": _spinning_textures,
                  "thin_rod": _thin_rod, "fast_few_frames": _fast_few_frames}


def stress_objects(name: str, t: float) -> list:
    """The objects of stress scene `name` at time `t` in [0, 1] (the floor first, unlabelled)."""
    t = float(t)
    if name not in STRESS_SCENES:
        raise _unknown(name)
    return _SCENE_OBJECTS[name](t)


def rig_cameras() -> list[np.ndarray]:
    """Camera-to-world matrices (Blender/OpenGL axes) of the 12 fixed cameras."""
    views = []  # (azimuth deg, elevation deg, distance)
    views += [(az, 26.6, 5.4) for az in (0, 90, 180, 270)]  # the sides
    views += [(0, 89.0, 5.6), (45, 63.4, 5.9)]  # above, high diagonal
    views += [(az, 35.3, 6.9) for az in (45, 135, 225, 315)]  # between the sides
    views += [(0, 22.1, 3.5), (180, 22.1, 3.5)]  # low and close
    return [orbit_camera_to_world(math.radians(az), math.radians(el), dist, target=_TARGET)
            for az, el, dist in views]


def rig_camera(cam_id: int, resolution: int, time: float | None = None) -> Camera:
    """Rig camera `cam_id` (any integer: taken modulo the rig's 12) as the suite's frames see
    it: square, `resolution` pixels wide, 50 degrees of horizontal field of view."""
    rig = rig_cameras()
    focal = 0.5 * resolution / math.tan(0.5 * math.radians(_FOV_DEG))
    return Camera.from_camera_to_world(rig[int(cam_id) % len(rig)], resolution, resolution,
                                       focal, focal, time=time)


def stress_plan(frames: int) -> dict[str, list[tuple[int, float, int]]]:
    """Per split, the (timestamp index, time, rig camera) of each frame (module docstring)."""
    plan = {"train": [], "val": [], "test": []}
    for k in range(frames):
        pos = k % _BLOCK
        split = ("train" if pos < _BLOCK_TRAIN else
                 "test" if pos < _BLOCK_TRAIN + _BLOCK_TEST else "val")
        plan[split].append((k, k / (frames - 1), _RIG_ORDER[k % len(_RIG_ORDER)]))
    return plan


def synthesize_stress_scene(out_dir, name: str, resolution: int = 400, frames: int = 120,
                            seed: int = 0, supersample: int = 2, points: int = 100_000,
                            progress=None, objects=None) -> Path:
    """Write stress scene `name` to `out_dir` (module docstring) and return its path.

    `resolution` is the square image size, `frames` the number of timestamps (120: 84 train,
    18 test, 18 val); `seed` only draws ``fused.ply``. `progress`, if given, is called once per
    image. `objects`, if given, is a function of time returning the objects to draw instead of
    scene `name`'s (the floor first; ``bench/variant_scenes.py`` writes unseen scenes of each
    kind this way). Same arguments give the same bytes.
    """
    if objects is None and name not in STRESS_SCENES:
        raise _unknown(name)
    objects_at = objects or (lambda t: stress_objects(name, t))
    resolution, frames = int(resolution), int(frames)
    if resolution < 4:
        raise ValueError(f"resolution: expected an integer >= 4, got {resolution}")
    if frames < _BLOCK:
        raise ValueError(f"frames: expected at least {_BLOCK} (one block of 14 train, 3 test, "
                         f"3 val timestamps), got {frames}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    angle_x = math.radians(_FOV_DEG)
    rig = rig_cameras()
    for split, entries in stress_plan(frames).items():
        (out / split).mkdir(exist_ok=True)
        records = []
        for k, t, cam_id in entries:
            cam = rig_camera(cam_id, resolution, time=t)
            file = f"r_{k:04d}"
            write_frame(out, split, file, objects_at(t), cam, supersample)
            if progress is not None:
                progress()
            records.append({"file_path": f"./{split}/{file}", "time": t, "camera": cam_id,
                            "transform_matrix": [[float(x) for x in row] for row in rig[cam_id]]})
        atomic_write_bytes(out / f"transforms_{split}.json", (json.dumps(
            {"camera_angle_x": angle_x, "frames": records}, indent=2) + "\n").encode("utf-8"))
    atomic_write_bytes(out / "class_mapping.json", (json.dumps(
        class_mapping(objects_at(0.0)), indent=2) + "\n").encode("utf-8"))
    if points > 0:
        rng = np.random.default_rng(int(seed))
        pts = rng.uniform(-2.0, 2.0, size=(int(points), 3)).astype(np.float32)
        cols = rng.integers(0, 256, size=(int(points), 3)).astype(np.uint8)
        atomic_write_bytes(out / "fused.ply", points_ply_bytes(pts, cols))
    return out


def synthesize_stress_suite(out_dir, names=STRESS_SCENES, progress=None, **kwargs) -> list[Path]:
    """Write each stress scene of `names` to ``out_dir/NAME``; keyword arguments as
    :func:`synthesize_stress_scene`."""
    return [synthesize_stress_scene(Path(out_dir) / n, n, progress=progress, **kwargs)
            for n in names]
