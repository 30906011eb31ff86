"""The hand-made Gaussian PLY of a synthetic scene (nehad.data.synth_gaussians)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nehad.data.synth import Sphere, orbit_camera_to_world, render_view, scene_objects
from nehad.data.synth_gaussians import rotation_to_quat, scene_gaussians
from nehad.runtime.cameras import Camera
from nehad.runtime.raster import render


def _quat_to_rot(q):
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def test_rotation_to_quat_roundtrip():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(500, 3, 3)))
    q *= np.sign(np.linalg.det(q))[:, None, None]
    q[:3] = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]  # trace -1 cases
    np.testing.assert_allclose(_quat_to_rot(rotation_to_quat(q)), q, atol=1e-12)


@pytest.mark.parametrize("scene", ["spheres", "boxes"])
def test_gaussians_lie_on_surfaces_facing_out(scene):
    objects = scene_objects(scene, 0.5)
    cloud = scene_gaussians(scene, 0.5, 3000)
    assert 2800 <= len(cloud) <= 3200
    mu = cloud.means.astype(np.float64)
    normal = _quat_to_rot(cloud.quats.astype(np.float64))[:, :, 2]
    on_some = np.zeros(len(cloud), bool)
    for obj in objects:
        if isinstance(obj, Sphere):
            d = mu - obj.centre
            on = np.abs(np.linalg.norm(d, axis=1) - obj.radius) < 1e-5
            outward = np.einsum("ij,ij->i", normal[on], d[on] / obj.radius)
        else:
            local = (mu - obj.centre) @ obj.rotation / obj.half_size
            on = (np.abs(np.abs(local).max(axis=1) - 1.0) < 1e-5)
            axis = np.abs(local[on]).argmax(axis=1)
            face = obj.rotation.T[axis] * np.sign(local[on][np.arange(on.sum()), axis])[:, None]
            outward = np.einsum("ij,ij->i", normal[on], face)
        assert on.sum() > 50, obj.name
        np.testing.assert_allclose(outward, 1.0, atol=1e-5)
        on_some |= on
    assert on_some.all()
    assert (cloud.scales[:, 2] < 0.1 * cloud.scales[:, :2].min(axis=1)).all()  # flat discs
    assert scene_gaussians(scene, 0.5, 3000).means.tobytes() == cloud.means.tobytes()


@pytest.mark.parametrize("scene", ["spheres", "boxes"])
def test_render_resembles_the_ray_caster(scene):
    """At 128 px the splats match the analytic image (same time) up to soft edges."""
    size = 128
    f = 0.5 * size / math.tan(math.radians(45) / 2)
    cloud = scene_gaussians(scene, 0.5, 5000)
    for az, el in ((0.3, 0.4), (2.5, 0.9)):
        cam = Camera.from_camera_to_world(orbit_camera_to_world(az, el), size, size, f, f)
        truth = render_view(scene_objects(scene, 0.5), cam)
        ours = render(cloud, cam, background=(0.0, 0.0, 0.0))
        mse = float(np.mean((ours.rgb - truth[:, :, :3]) ** 2))
        psnr = -10 * math.log10(mse)
        inter = ((ours.alpha > 0.5) & (truth[:, :, 3] > 0.5)).sum()
        union = ((ours.alpha > 0.5) | (truth[:, :, 3] > 0.5)).sum()
        assert psnr > 20.0, (scene, az, psnr)
        assert inter / union > 0.85, (scene, az, inter / union)
