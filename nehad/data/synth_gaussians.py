"""A 3DGS Gaussian cloud that approximates a synthetic scene of :mod:`nehad.data.synth`.

It gives the quickstart something to render before any training exists (``nehad synth`` writes it
as ``gaussians.ply``): small flat Gaussians laid on the analytic object surfaces at one time, each
oriented with its surface (the rotated z axis is the outward normal, the scale along it is thin),
opacity 0.9, and a degree-0 SH colour equal to the object's colour times the same baked Lambert
term the ray caster shades with. It is a hand-made approximation, not a fit: edges look slightly
soft and the shading is constant over each Gaussian.

Sampling is regular rather than random so the surfaces are covered without holes: a Fibonacci
lattice on each sphere, a rectangular grid on each box face; the number of Gaussians per object is
proportional to its area. Numpy only, deterministic (no random numbers at all).
"""

from __future__ import annotations

import math

import numpy as np

from nehad.runtime.gaussians import SH_C0, GaussianCloud

from .synth import _AMBIENT, _LIGHT, Box, Sphere, scene_objects

__all__ = ["scene_gaussians", "surface_gaussians", "rotation_to_quat"]

#: Tangent standard deviation as a fraction of the sample spacing: large enough that neighbouring
#: Gaussians overlap into an opaque surface, small enough to keep edges crisp.
TANGENT_SIGMA = 0.6
#: Standard deviation along the normal as a fraction of the tangent one (flat discs).
NORMAL_FLATNESS = 0.05
OPACITY = 0.9


def rotation_to_quat(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices (N, 3, 3) (Shepperd's method), w >= 0."""
    r = np.asarray(rot, dtype=np.float64).reshape(-1, 3, 3)
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    trace = m00 + m11 + m22
    cand = np.stack([trace, m00, m11, m22], axis=1)
    pick = cand.argmax(axis=1)
    q = np.empty((len(r), 4))
    for k in range(4):
        sel = pick == k
        if not sel.any():
            continue
        a = r[sel]
        if k == 0:
            s = 2.0 * np.sqrt(1.0 + trace[sel])
            q[sel] = np.stack([0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s,
                               (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s], 1)
        elif k == 1:
            s = 2.0 * np.sqrt(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2])
            q[sel] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / s, 0.25 * s,
                               (a[:, 0, 1] + a[:, 1, 0]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s], 1)
        elif k == 2:
            s = 2.0 * np.sqrt(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2])
            q[sel] = np.stack([(a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 0, 1] + a[:, 1, 0]) / s,
                               0.25 * s, (a[:, 1, 2] + a[:, 2, 1]) / s], 1)
        else:
            s = 2.0 * np.sqrt(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1])
            q[sel] = np.stack([(a[:, 1, 0] - a[:, 0, 1]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s,
                               (a[:, 1, 2] + a[:, 2, 1]) / s, 0.25 * s], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q


def _frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) whose third column is the given unit normal (tangents arbitrary)."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def _area(obj) -> float:
    if isinstance(obj, Sphere):
        return 4.0 * math.pi * obj.radius ** 2
    hx, hy, hz = obj.half_size
    return float(8.0 * (hx * hy + hy * hz + hx * hz))


def _sphere_samples(obj: Sphere, count: int):
    """Fibonacci lattice: centres, rotations (z = outward normal), tangent sigmas (x, y)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    rho = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    normals = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    centres = obj.centre + obj.radius * normals
    spacing = math.sqrt(4.0 * math.pi * obj.radius ** 2 / count)
    sig = np.full((count, 2), TANGENT_SIGMA * spacing)
    return centres, _frames_from_normals(normals), sig


def _box_samples(obj: Box, count: int):
    """A grid on each face (count shared by face area); rotations aligned with the face axes."""
    hs = np.asarray(obj.half_size, dtype=np.float64)
    rot = np.asarray(obj.rotation, dtype=np.float64)
    faces = []  # (normal axis, tangent axes u, v)
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        faces.append((axis, u, v))
    face_area = np.array([4.0 * hs[u] * hs[v] for _, u, v in faces])  # one face of each pair
    per_face = count * face_area / (2.0 * face_area.sum())
    centres, rots, sigmas = [], [], []
    for (axis, u, v), m in zip(faces, per_face):
        nu = max(1, int(round(math.sqrt(m * hs[u] / hs[v]))))
        nv = max(1, int(round(m / nu)))
        gu = (np.arange(nu) + 0.5) / nu * 2.0 - 1.0
        gv = (np.arange(nv) + 0.5) / nv * 2.0 - 1.0
        uu, vv = np.meshgrid(gu * hs[u], gv * hs[v], indexing="ij")
        k = uu.size
        for sign in (1.0, -1.0):
            local = np.zeros((k, 3))
            local[:, u], local[:, v], local[:, axis] = uu.ravel(), vv.ravel(), sign * hs[axis]
            centres.append(obj.centre + local @ rot.T)
            # columns: tangent u, tangent v, outward normal (flip u with the normal to keep det +1)
            nrm = sign * rot[:, axis]
            tu = rot[:, u] * (1.0 if _det3(rot[:, u], rot[:, v], nrm) > 0 else -1.0)
            frame = np.stack([tu, rot[:, v], nrm], axis=1)
            rots.append(np.broadcast_to(frame, (k, 3, 3)))
            sigmas.append(np.broadcast_to([TANGENT_SIGMA * 2.0 * hs[u] / nu,
                                           TANGENT_SIGMA * 2.0 * hs[v] / nv], (k, 2)))
    return np.concatenate(centres), np.concatenate(rots), np.concatenate(sigmas)


def _det3(a, b, c) -> float:
    return float(np.dot(np.cross(a, b), c))


def surface_gaussians(objects, count: int = 5000) -> GaussianCloud:
    """About `count` flat Gaussians covering the surfaces of `objects` (Sphere/Box list)."""
    count = int(count)
    if count < 1:
        raise ValueError(f"count: expected a positive number of Gaussians, got {count}")
    if not objects:
        raise ValueError("objects: the scene holds no objects")
    areas = np.array([_area(o) for o in objects])
    share = np.maximum(1, np.round(count * areas / areas.sum()).astype(int))
    means, scales, quats, colours = [], [], [], []
    for obj, m in zip(objects, share):
        if isinstance(obj, Sphere):
            c, r, sig = _sphere_samples(obj, int(m))
        else:
            c, r, sig = _box_samples(obj, int(m))
        normals = r[:, :, 2]
        lambert = np.clip(normals @ _LIGHT, 0.0, None)
        shade = _AMBIENT + (1.0 - _AMBIENT) * lambert
        means.append(c)
        scales.append(np.concatenate([sig, NORMAL_FLATNESS * sig.min(axis=1, keepdims=True)], 1))
        quats.append(rotation_to_quat(r))
        colours.append(shade[:, None] * np.asarray(obj.colour, dtype=np.float64))
    means, scales = np.concatenate(means), np.concatenate(scales)
    quats, rgb = np.concatenate(quats), np.concatenate(colours)
    n = len(means)
    sh = ((rgb - 0.5) / SH_C0).reshape(n, 1, 3)  # rgb = SH_C0 * dc + 0.5 (degree 0)
    return GaussianCloud(means=means, scales=scales, quats=quats,
                         opacities=np.full(n, OPACITY), sh=sh)


def scene_gaussians(scene: str = "spheres", t: float = 0.5, count: int = 5000) -> GaussianCloud:
    """Gaussians approximating synthetic `scene` at time `t` (see :func:`surface_gaussians`)."""
    return surface_gaussians(scene_objects(scene, t), count)
