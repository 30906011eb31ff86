"""A small synthetic dynamic scene in the D-NeRF layout, drawn by an analytic ray caster.

The images come from exact ray-sphere and ray-box intersections with Lambertian shading, so they
share nothing with a Gaussian rasteriser: a model that fits them has learnt the scene, not the
renderer. The output is what a D-NeRF "blender" scene looks like on disk (docs/design.md section 5 readers,
docs/design.md section 3 conventions):

- ``train/``, ``val/``, ``test/``: 8-bit RGBA PNGs (straight colour in the file, like D-NeRF's),
  alpha = pixel coverage from supersampling, transparent background;
- ``transforms_{train,val,test}.json``: ``camera_angle_x`` and frames
  ``{"file_path": "./train/r_000", "time": t, "transform_matrix": c2w}`` where ``c2w`` is
  camera-to-world in Blender/OpenGL axes (y up, z back) and ``file_path`` has no extension;
- ``points3d.ply`` (optional): points on the object surfaces at mid time, ``x y z red green blue``;
- ``SPLIT/masks/r_XXX.png`` and ``class_mapping.json``: per-object label masks (uint8 ids,
  0 = background) as the MuJoCo scenes have them (:func:`label_mask`).

The world is z-up like the Blender scenes; every object stays inside [-1.3, 1.3]^3, the cube
D-NeRF's random initialisation fills (docs/design.md section 5). Cameras sit on a sphere of radius 4 and look
at the origin. Train frame k has time k/(frames-1) and its own camera (monocular per timestamp, like
D-NeRF); val and test hold about 10% as many frames each at other cameras and times.

Everything is numpy, vectorised over pixels, and deterministic for a seed. Files are written
atomically (docs/design.md section 10).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nehad.data.common import points_ply_bytes
from nehad.runtime.cameras import Camera
from nehad.runtime.images import atomic_write_bytes, write_image

__all__ = [
    "SCENES", "BOUND", "Sphere", "Box", "Surface", "scene_objects", "orbit_camera_to_world",
    "render_view", "label_mask", "class_mapping", "write_frame", "synthesize_scene",
]

#: Names accepted by :func:`synthesize_scene` and :func:`scene_objects`.
SCENES = ("spheres", "boxes")

#: Objects stay inside [-BOUND, BOUND]^3 at every time (D-NeRF's init cube).
BOUND = 1.3

# Lighting: one directional light from above plus ambient (world is z-up).
_LIGHT = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])
_AMBIENT = 0.3
_NEAR = 1e-3


@dataclass(frozen=True)
class Surface:
    """How an object's surface looks: a flat colour, or a two-colour pattern fixed to the object.

    `pattern` is None, ``"checker"``, ``"stripes"`` or ``"noise"``; `cells` the number of pattern
    cells around the object (checker: `cells` around x `cells // 2` from pole to pole on a sphere,
    `cells` per box edge; stripes: `cells` stripes around a sphere's local z axis, across a box's
    local x; noise: `cells` per box edge, each cell a random mix of the two colours, darkened by
    a random factor per block of 5 x 5 cells: texture that structure from motion can match).
    `unlit` surfaces show their colour unshaded (a floor that looks like the background).
    """

    pattern: str | None = None
    second_colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cells: int = 8
    unlit: bool = False


PLAIN = Surface()


@dataclass(frozen=True)
class Sphere:
    """A sphere with a Lambertian colour; `rotation` (columns: the local axes in world
    coordinates) only matters for a patterned `surface`. `labelled` objects get an id in label
    masks; the others (a floor) count as background there."""

    name: str
    centre: np.ndarray  # (3,)
    radius: float
    colour: tuple[float, float, float]
    rotation: np.ndarray | None = None
    surface: Surface = PLAIN
    labelled: bool = True

    @property
    def bounding_radius(self) -> float:
        return float(self.radius)


@dataclass(frozen=True)
class Box:
    """An oriented box: ``x_world = centre + rotation @ x_local`` with ``|x_local| <= half_size``."""

    name: str
    centre: np.ndarray  # (3,)
    half_size: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3), columns are the box axes in world coordinates
    colour: tuple[float, float, float]
    surface: Surface = PLAIN
    labelled: bool = True

    @property
    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.half_size))


def _axis_angle(axis, angle: float) -> np.ndarray:
    """Rotation matrix about `axis` (normalised here) by `angle` radians (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _lerp(a, b, t: float) -> np.ndarray:
    return (1.0 - t) * np.asarray(a, dtype=np.float64) + t * np.asarray(b, dtype=np.float64)


def scene_objects(scene: str, t: float) -> list[Sphere | Box]:
    """The objects of `scene` at time `t` in [0, 1].

    Each scene has an object named ``"still"`` (never moves), ``"mover"`` (translates) and
    ``"spinner"`` (a box rotating about a fixed axis through its centre), plus one more moving
    object. Colours are distinct hues so tests can tell the objects apart in an image.
    """
    t = float(t)
    if scene == "spheres":
        return [
            Sphere("still", np.array([-0.5, -0.45, -0.4]), 0.42, (0.2, 0.75, 0.25)),
            Sphere("mover", _lerp([-0.8, 0.7, 0.05], [0.8, 0.45, 0.55], t), 0.3, (0.9, 0.15, 0.15)),
            Box("spinner", np.array([0.45, -0.35, -0.35]), np.array([0.5, 0.16, 0.3]),
                _axis_angle([0.0, 0.0, 1.0], math.pi * t), (0.2, 0.35, 0.95)),
            Sphere("bouncer", np.array([0.0, 0.15, -0.45 + 1.1 * abs(math.sin(2.0 * math.pi * t))]),
                   0.2, (0.95, 0.8, 0.15)),
        ]
    if scene == "boxes":
        return [
            Box("still", np.array([-0.55, -0.5, -0.45]), np.array([0.35, 0.3, 0.3]),
                _axis_angle([0.0, 0.0, 1.0], 0.4), (0.2, 0.75, 0.25)),
            Box("mover", _lerp([0.6, -0.8, -0.6], [0.3, 0.8, 0.2], t), np.array([0.22, 0.22, 0.22]),
                _axis_angle([1.0, 0.0, 0.0], 0.3), (0.9, 0.15, 0.15)),
            Box("spinner", np.array([0.35, 0.35, 0.1]), np.array([0.45, 0.25, 0.12]),
                _axis_angle([1.0, 1.0, 1.0], 2.0 * math.pi * t), (0.2, 0.35, 0.95)),
            Sphere("ball", np.array([-0.6 + 0.35 * math.cos(2.0 * math.pi * t),
                                     0.55 + 0.35 * math.sin(2.0 * math.pi * t), 0.6]),
                   0.22, (0.75, 0.3, 0.85)),
        ]
    raise ValueError(f"scene: unknown synthetic scene {scene!r}; expected one of {', '.join(SCENES)}")


def orbit_camera_to_world(azimuth: float, elevation: float, radius: float = 4.0,
                          target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera-to-world (Blender/OpenGL axes) of a camera on a sphere looking at `target`.

    Angles in radians; the world is z-up, elevation is measured from the xy plane.
    """
    target = np.asarray(target, dtype=np.float64)
    pos = target + radius * np.array([math.cos(elevation) * math.cos(azimuth),
                                      math.cos(elevation) * math.sin(azimuth),
                                      math.sin(elevation)])
    back = pos - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, pos
    return c2w


def _screen_window(obj, camera: Camera, w2c: np.ndarray):
    """Pixel rectangle [v0, v1) x [u0, u1) that contains the object's image (conservative)."""
    r = obj.bounding_radius
    pc = w2c[:3, :3] @ obj.centre + w2c[:3, 3]
    if pc[2] - r <= _NEAR:  # object reaches behind the camera: test every pixel
        return 0, camera.height, 0, camera.width
    # The image of the sphere lies in the image of its camera-aligned bounding cube, whose
    # projection is the convex hull of its 8 projected corners (all in front of the camera).
    corners = pc + r * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    u = camera.fx * corners[:, 0] / corners[:, 2] + camera.cx
    v = camera.fy * corners[:, 1] / corners[:, 2] + camera.cy
    u0 = int(np.clip(math.floor(u.min()) - 1, 0, camera.width))
    u1 = int(np.clip(math.ceil(u.max()) + 1, 0, camera.width))
    v0 = int(np.clip(math.floor(v.min()) - 1, 0, camera.height))
    v1 = int(np.clip(math.ceil(v.max()) + 1, 0, camera.height))
    return v0, v1, u0, u1


def _intersect(obj, origin: np.ndarray, d: np.ndarray):
    """Ray parameter (inf on a miss) and world normal for rays ``origin + s d``; d: (h, w, 3)."""
    if isinstance(obj, Sphere):
        oc = origin - obj.centre
        a = np.einsum("hwc,hwc->hw", d, d)
        b = d @ oc
        disc = b * b - a * (oc @ oc - obj.radius ** 2)
        hit = disc >= 0.0
        s = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0.0))) / a, np.inf)
        s = np.where(s > _NEAR, s, np.inf)
        s_hit = np.where(np.isfinite(s), s, 0.0)
        normal = (origin + s_hit[..., None] * d - obj.centre) / obj.radius
        return s, normal
    # Oriented box: slab test in the box frame.
    rot = obj.rotation
    o_l = rot.T @ (origin - obj.centre)
    d_l = d @ rot
    d_l = np.where(np.abs(d_l) < 1e-12, 1e-12, d_l)
    inv = 1.0 / d_l
    t1 = (-obj.half_size - o_l) * inv
    t2 = (obj.half_size - o_l) * inv
    tn = np.minimum(t1, t2)
    tmin = tn.max(axis=-1)
    tmax = np.maximum(t1, t2).min(axis=-1)
    hit = (tmax >= tmin) & (tmin > _NEAR)
    s = np.where(hit, tmin, np.inf)
    axis = tn.argmax(axis=-1)
    sign = -np.sign(np.take_along_axis(d_l, axis[..., None], axis=-1))  # (h, w, 1)
    normal = rot.T[axis] * sign  # rot.T[axis] = world direction of the entered face's axis
    return s, normal


def _surface_colour(obj, points: np.ndarray) -> np.ndarray:
    """Colour of `obj` at world surface `points` (..., 3): (3,) for a plain surface, else
    (..., 3) from the pattern in the object's own frame (so the pattern turns with it)."""
    surf = obj.surface
    base = np.asarray(obj.colour, dtype=np.float64)
    if surf.pattern is None:
        return base
    rot = obj.rotation if obj.rotation is not None else np.eye(3)
    local = (points - obj.centre) @ rot  # = rot.T (p - c), row-wise
    n = int(surf.cells)
    if surf.pattern == "noise":
        return _noise_colour(obj, local, n, base, np.asarray(surf.second_colour, dtype=np.float64))
    if isinstance(obj, Sphere):
        u = (np.arctan2(local[..., 1], local[..., 0]) + math.pi) / (2.0 * math.pi)  # [0, 1]
        v = np.arccos(np.clip(local[..., 2] / max(obj.radius, 1e-12), -1.0, 1.0)) / math.pi
        if surf.pattern == "stripes":
            parity = np.floor(u * n)
        else:
            parity = np.floor(u * n) + np.floor(v * max(n // 2, 1))
    else:
        rel = (local / obj.half_size + 1.0) * 0.5  # [0, 1] across each box axis
        if surf.pattern == "stripes":
            parity = np.floor(rel[..., 0] * n)
        else:
            parity = np.floor(rel * n).sum(axis=-1)
    odd = (parity.astype(np.int64) % 2 == 1)[..., None]
    return np.where(odd, np.asarray(surf.second_colour, dtype=np.float64), base)


def _cell_hash(cells: np.ndarray) -> np.ndarray:
    """A value in [0, 1) per integer cell (..., 3), the same for the same cell (splitmix64)."""
    c = cells.astype(np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        x = (c[..., 0] * np.uint64(0x9E3779B97F4A7C15) ^ c[..., 1] * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ c[..., 2] * np.uint64(0x165667B19E3779F9))
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) / float(2 ** 53)


def _noise_colour(obj, local: np.ndarray, n: int, base: np.ndarray,
                  second: np.ndarray) -> np.ndarray:
    """The ``"noise"`` pattern (see Surface) at object-frame points `local` (..., 3)."""
    if isinstance(obj, Sphere):
        size = np.full(3, 2.0 * obj.radius)
    else:
        size = 2.0 * np.asarray(obj.half_size, dtype=np.float64)
    cell = np.max(size) / max(n, 1)  # square cells of one size on every face
    fine = np.floor(local / cell)
    mix = _cell_hash(fine)[..., None]
    shade = 0.35 + 0.65 * _cell_hash(np.floor(fine / 5.0) + 7919.0)[..., None]
    return shade * ((1.0 - mix) * base + mix * second)


def label_mask(objects, coverage: np.ndarray) -> np.ndarray:
    """uint8 label mask (MuJoCo layout: 0 = background, k = the k-th labelled object, in list
    order) from :func:`render_view`'s per-object coverage: a pixel takes the id of the object
    that covers most of it, when that object covers at least half of it and is labelled."""
    h, w = coverage.shape[:2]
    if not objects:
        return np.zeros((h, w), dtype=np.uint8)
    ids = np.zeros(len(objects), dtype=np.uint8)
    next_id = 1
    for k, obj in enumerate(objects):
        if obj.labelled:
            ids[k] = next_id
            next_id += 1
    front = coverage.argmax(axis=-1)
    most = np.take_along_axis(coverage, front[..., None], axis=-1)[..., 0]
    return np.where(most >= 0.5, ids[front], 0).astype(np.uint8)


def class_mapping(objects) -> dict[str, str]:
    """``class_mapping.json``'s content for `objects` (ids as :func:`label_mask` gives them)."""
    names = {"0": "background"}
    for obj in objects:
        if obj.labelled:
            names[str(len(names))] = obj.name
    return names


def _sample_directions(camera: Camera, c2w_rot: np.ndarray, window, s_: int) -> np.ndarray:
    """World directions (h, w, 3) of the supersample rays of the pixel `window` = (v0, v1, u0,
    u1). Camera-space direction (dx, dy, 1): the ray parameter equals the view depth z."""
    v0, v1, u0, u1 = window
    us = u0 + (np.arange((u1 - u0) * s_) + 0.5) / s_
    vs = v0 + (np.arange((v1 - v0) * s_) + 0.5) / s_
    dx = (us - camera.cx) / camera.fx
    dy = (vs - camera.cy) / camera.fy
    return (dx[None, :, None] * c2w_rot[:, 0] + dy[:, None, None] * c2w_rot[:, 1]
            + c2w_rot[:, 2])


def _shaded_colour(obj, s: np.ndarray, normal: np.ndarray, origin: np.ndarray,
                   d: np.ndarray) -> np.ndarray:
    """Colour of `obj` where the rays ``origin + s d`` hit it: its surface colour lit by the
    light and the ambient term (unlit surfaces unshaded)."""
    if obj.surface.unlit:
        shade = np.ones(s.shape)
    else:
        shade = _AMBIENT + (1.0 - _AMBIENT) * np.clip(normal @ _LIGHT, 0.0, None)
    points = origin + np.where(np.isfinite(s), s, 0.0)[..., None] * d
    return shade[..., None] * _surface_colour(obj, points)


def _draw_object(k: int, obj, camera: Camera, w2c: np.ndarray, s_: int, buffers):
    """Ray-cast object `k` into the supersample `buffers` (depth, colour, ids) where it is in
    front of what is there. Returns its pixel window (v0, v1, u0, u1), or None when it drew
    nothing."""
    depth, colour, ids = buffers
    window = _screen_window(obj, camera, w2c)
    v0, v1, u0, u1 = window
    if v0 >= v1 or u0 >= u1:
        return None
    d = _sample_directions(camera, w2c[:3, :3].T, window, s_)
    origin = camera.centre
    s, normal = _intersect(obj, origin, d)
    win = (slice(v0 * s_, v1 * s_), slice(u0 * s_, u1 * s_))
    closer = s < depth[win]
    if not closer.any():
        return None
    rgb = _shaded_colour(obj, s, normal, origin, d)
    depth[win] = np.where(closer, s, depth[win])
    colour[win] = np.where(closer[..., None], rgb, colour[win])
    ids[win] = np.where(closer, k, ids[win])
    return window


def _average_samples(colour: np.ndarray, ids: np.ndarray, box, h: int, w: int,
                     s_: int) -> np.ndarray:
    """(h, w, 4) premultiplied RGBA: the supersamples averaged, only inside the pixel
    rectangle `box` that something was drawn in (uncovered samples count as 0)."""
    rgba = np.zeros((h, w, 4), dtype=np.float32)
    v0, v1, u0, u1 = box
    if v0 < v1 and u0 < u1:
        hh, ww = v1 - v0, u1 - u0
        win = (slice(v0 * s_, v1 * s_), slice(u0 * s_, u1 * s_))
        hit = (ids[win] >= 0).astype(np.float32)[..., None]
        both = np.concatenate([colour[win], hit], axis=-1)
        rgba[v0:v1, u0:u1] = both.reshape(hh, s_, ww * s_, 4).sum(axis=1, dtype=np.float64).reshape(
            hh, ww, s_, 4).sum(axis=2) / (s_ * s_)
    return rgba


def _coverage(ids: np.ndarray, n_objects: int, h: int, w: int, s_: int) -> np.ndarray:
    """float32 (h, w, n_objects): the fraction of each pixel's samples where object k is in
    front."""
    ids4 = ids.reshape(h, s_, w, s_)
    coverage = np.stack([(ids4 == k).mean(axis=(1, 3)) for k in range(n_objects)], axis=-1)
    if not n_objects:
        coverage = np.zeros((h, w, 0))
    return coverage.astype(np.float32)


def new_buffers(camera: Camera, supersample: int = 3):
    """Empty supersample buffers (depth, colour, object ids) of a `camera` image, for
    :func:`draw_objects`."""
    s_ = int(supersample)
    if s_ < 1:
        raise ValueError(f"supersample: expected an integer >= 1, got {supersample!r}")
    h, w = camera.height, camera.width
    return (np.full((h * s_, w * s_), np.inf), np.zeros((h * s_, w * s_, 3), dtype=np.float32),
            np.full((h * s_, w * s_), -1, dtype=np.int16))


def copy_buffers(buffers):
    """An independent copy of :func:`new_buffers`' tuple (a drawn backdrop reused per frame)."""
    return tuple(b.copy() for b in buffers)


def draw_objects(objects, camera: Camera, buffers, supersample: int = 3,
                 first_id: int = 0) -> list[int]:
    """Ray-cast `objects` into `buffers` (:func:`new_buffers`) where they are in front of what
    is there; object k gets id ``first_id + k``. Returns the pixel rectangle [v0, v1, u0, u1]
    they touched (empty when v0 >= v1)."""
    s_ = int(supersample)
    h, w = camera.height, camera.width
    w2c = np.asarray(camera.world_to_camera, dtype=np.float64)
    box = [h, 0, w, 0]
    for k, obj in enumerate(objects):
        drawn = _draw_object(first_id + k, obj, camera, w2c, s_, buffers)
        if drawn is not None:
            v0, v1, u0, u1 = drawn
            box = [min(box[0], v0), max(box[1], v1), min(box[2], u0), max(box[3], u1)]
    return box


def resolve_buffers(buffers, camera: Camera, supersample: int = 3, n_objects: int = 0,
                    box=None, return_coverage: bool = False):
    """:func:`render_view`'s result from drawn `buffers`; `box` limits the averaging to the
    rectangle something was drawn in (None: the whole image)."""
    s_ = int(supersample)
    h, w = camera.height, camera.width
    rgba = _average_samples(buffers[1], buffers[2], box or (0, h, 0, w), h, w, s_)
    if not return_coverage:
        return rgba
    return rgba, _coverage(buffers[2], n_objects, h, w, s_)


def render_view(objects, camera: Camera, supersample: int = 3, return_coverage: bool = False):
    """Ray-cast `objects` from `camera` (a :class:`~nehad.runtime.cameras.Camera`, OpenCV axes).

    Each pixel is sampled on a ``supersample x supersample`` grid (pixel (i, j) spans
    [i, i+1) x [j, j+1), docs/design.md section 3). Returns float32 (H, W, 4) with *premultiplied* colour
    (the mean over all samples, background samples counting as 0) and alpha = fraction of samples
    that hit an object; uncovered pixels are (0, 0, 0, 0). Premultiplied is the in-memory RGBA
    convention of ``nehad.runtime.images`` (OpenImageIO's associated alpha): ``write_image``
    stores straight colour in the PNG, as D-NeRF files hold it, and over a background ``bg`` the
    image is ``rgb + bg (1 - alpha)``. With ``return_coverage`` also returns float32
    (H, W, n_objects), the fraction of each pixel's samples in which object k is the front one.
    """
    buffers = new_buffers(camera, supersample)
    box = draw_objects(objects, camera, buffers, supersample)
    return resolve_buffers(buffers, camera, supersample, len(objects), box, return_coverage)


def _surface_points(objects, n: int, rng: np.random.Generator):
    """`n` points spread over the objects' surfaces (area-weighted) and their uint8 colours."""
    areas = []
    for obj in objects:
        if isinstance(obj, Sphere):
            areas.append(4.0 * math.pi * obj.radius ** 2)
        else:
            hx, hy, hz = obj.half_size
            areas.append(8.0 * (hx * hy + hy * hz + hx * hz))
    counts = rng.multinomial(n, np.asarray(areas) / sum(areas))
    pts, cols = [], []
    for obj, m in zip(objects, counts):
        if isinstance(obj, Sphere):
            v = rng.normal(size=(m, 3))
            p = obj.centre + obj.radius * v / np.linalg.norm(v, axis=1, keepdims=True)
        else:
            hs = obj.half_size
            face_area = np.array([hs[1] * hs[2], hs[0] * hs[2], hs[0] * hs[1]])
            axis = rng.choice(3, size=m, p=face_area / face_area.sum())
            local = rng.uniform(-1.0, 1.0, size=(m, 3))
            local[np.arange(m), axis] = rng.choice([-1.0, 1.0], size=m)
            p = obj.centre + (local * hs) @ obj.rotation.T
        pts.append(p)
        cols.append(np.tile(np.round(np.asarray(obj.colour) * 255), (m, 1)))
    return np.concatenate(pts).astype(np.float32), np.concatenate(cols).astype(np.uint8)


def write_frame(root: Path, split: str, name: str, objects, camera: Camera,
                supersample: int = 3) -> None:
    """Ray cast `objects` and write ``root/split/name.png`` (RGBA) and its label mask
    ``root/split/masks/name.png`` (the MuJoCo layout, :func:`label_mask`)."""
    rgba, coverage = render_view(objects, camera, supersample=supersample, return_coverage=True)
    write_image(root / split / f"{name}.png", rgba, bit_depth=8)
    (root / split / "masks").mkdir(exist_ok=True)
    write_image(root / split / "masks" / f"{name}.png",
                label_mask(objects, coverage).astype(np.float32) / 255.0, bit_depth=8)


def _check_synth_args(scene: str, resolution, frames, fixed_time, fov_deg):
    """(resolution, frames, fixed_time) of :func:`synthesize_scene` as int, int and float (or
    None); ValueError naming the first invalid argument."""
    if scene not in SCENES:
        raise ValueError(f"scene: unknown synthetic scene {scene!r}; expected one of {', '.join(SCENES)}")
    resolution, frames = int(resolution), int(frames)
    if resolution < 4:
        raise ValueError(f"resolution: expected an integer >= 4, got {resolution}")
    if frames < 1:
        raise ValueError(f"frames: expected an integer >= 1, got {frames}")
    if fixed_time is not None:
        fixed_time = float(fixed_time)
        if not 0.0 <= fixed_time <= 1.0:
            raise ValueError(f"fixed_time: expected a time in [0, 1], got {fixed_time}")
    if not 1.0 <= fov_deg <= 170.0:
        raise ValueError(f"fov_deg: expected 1..170 degrees, got {fov_deg}")
    return resolution, frames, fixed_time


@dataclass(frozen=True)
class _Shoot:
    """What every view of a :func:`synthesize_scene` call shares."""

    out: Path
    scene: str
    resolution: int
    focal: float
    angle_x: float
    digits: int  # of the frame numbers in the file names
    supersample: int
    fixed_time: float | None
    progress: object


def _write_view(job: _Shoot, split: str, k: int, azimuth: float, elevation: float,
                t: float) -> dict:
    """Render and write view `k` of `split` from the orbit camera at (azimuth, elevation);
    returns its ``frames`` record of the transforms file."""
    c2w = orbit_camera_to_world(azimuth, elevation)
    cam = Camera.from_camera_to_world(c2w, job.resolution, job.resolution, job.focal, job.focal,
                                      time=t)
    name = f"r_{k:0{job.digits}d}"
    write_frame(job.out, split, name, scene_objects(job.scene, t), cam, job.supersample)
    if job.progress is not None:
        job.progress()
    return {"file_path": f"./{split}/{name}", "time": t,
            "transform_matrix": [[float(x) for x in row] for row in c2w]}


def _write_split(job: _Shoot, split: str, rng: np.random.Generator, times, n: int) -> None:
    """The `n` views of `split` and ``transforms_<split>.json``: random azimuth, elevation
    10-60 degrees; `times` None draws sorted uniform times (all `fixed_time` when set)."""
    azimuth = rng.uniform(0.0, 2.0 * math.pi, size=n)
    elevation = np.radians(rng.uniform(10.0, 60.0, size=n))
    if times is None:
        times = np.sort(rng.uniform(0.0, 1.0, size=n)).tolist()
    if job.fixed_time is not None:
        times = [job.fixed_time] * n
    (job.out / split).mkdir(exist_ok=True)
    records = [_write_view(job, split, k, float(azimuth[k]), float(elevation[k]), float(times[k]))
               for k in range(n)]
    doc = {"camera_angle_x": job.angle_x, "frames": records}
    atomic_write_bytes(job.out / f"transforms_{split}.json",
                       (json.dumps(doc, indent=2) + "\n").encode("utf-8"))


def synthesize_scene(out_dir, scene: str = "spheres", resolution: int = 64, frames: int = 50,
                     seed: int = 0, fixed_time: float | None = None, fov_deg: float = 45.0,
                     supersample: int = 3, points: int = 2000, progress=None,
                     test_frames: int | None = None) -> Path:
    """Write a synthetic dynamic scene in the D-NeRF layout to `out_dir` and return its path.
    `progress`, if given, is called once per image written.

    `resolution` is the square image size, `frames` the number of train frames (val and test get
    ``max(1, round(0.1 * frames))`` each; `test_frames`, if given, sets the test split's count
    alone). Train frame k has time ``k / (frames - 1)``; val and test
    times are drawn uniformly in [0, 1]. With `fixed_time` every frame of every split has that time
    (a static scene). Cameras: radius 4 around the origin, random azimuth, elevation 10-60 degrees,
    horizontal field of view `fov_deg`. `points` > 0 also writes ``points3d.ply`` with that many
    surface points at time 0.5 (or `fixed_time`). Same arguments give the same bytes.
    """
    resolution, frames, fixed_time = _check_synth_args(scene, resolution, frames, fixed_time,
                                                       fov_deg)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    angle_x = math.radians(fov_deg)
    focal = 0.5 * resolution / math.tan(0.5 * angle_x)
    rng_train, rng_val, rng_test, rng_pts = (
        np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(4))
    n_held = max(1, int(round(0.1 * frames)))
    if test_frames is not None and (isinstance(test_frames, bool) or int(test_frames) < 1):
        raise ValueError(f"test_frames: expected an integer >= 1, got {test_frames}")
    n_test = n_held if test_frames is None else int(test_frames)
    plan = {
        "train": (rng_train, [k / (frames - 1) if frames > 1 else 0.0 for k in range(frames)]),
        "val": (rng_val, None),
        "test": (rng_test, None),
    }
    job = _Shoot(out, scene, resolution, focal, angle_x, max(3, len(str(frames - 1))),
                 supersample, fixed_time, progress)
    counts = {"train": frames, "val": n_held, "test": n_test}
    for split, (rng, times) in plan.items():
        _write_split(job, split, rng, times, counts[split])
    atomic_write_bytes(out / "class_mapping.json", (json.dumps(
        class_mapping(scene_objects(scene, 0.0)), indent=2) + "\n").encode("utf-8"))
    if points > 0:
        t_pts = 0.5 if fixed_time is None else fixed_time
        pts, cols = _surface_points(scene_objects(scene, t_pts), int(points), rng_pts)
        atomic_write_bytes(out / "points3d.ply", points_ply_bytes(pts, cols))
    return out

