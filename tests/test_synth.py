"""Synthetic D-NeRF scene generator (nehad.data.synth): layout, determinism, motion, antialiasing."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nehad.data.synth import (BOUND, SCENES, Box, Sphere, orbit_camera_to_world, render_view,
                              scene_objects, synthesize_scene)
from nehad.runtime.cameras import Camera
from nehad.runtime.images import read_image


def _camera(az=0.7, el=0.5, size=64, fov=math.radians(45), t=None):
    f = 0.5 * size / math.tan(fov / 2)
    return Camera.from_camera_to_world(orbit_camera_to_world(az, el), size, size, f, f, time=t)


def _by_name(objects):
    return {o.name: o for o in objects}


def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return synthesize_scene(tmp_path_factory.mktemp("syn") / "scene", resolution=32, frames=12, seed=0)


def test_layout_and_transforms(small_scene):
    root = small_scene
    for split, n in (("train", 12), ("val", 1), ("test", 1)):
        doc = json.loads((root / f"transforms_{split}.json").read_text())
        assert doc["camera_angle_x"] == pytest.approx(math.radians(45))
        assert len(doc["frames"]) == n
        for k, fr in enumerate(doc["frames"]):
            assert fr["file_path"] == f"./{split}/r_{k:03d}"  # no extension, as D-NeRF
            assert (root / (fr["file_path"] + ".png")).is_file()
            m = np.array(fr["transform_matrix"])
            assert m.shape == (4, 4)
            np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
            assert np.linalg.norm(m[:3, 3]) == pytest.approx(4.0)
            elevation = math.degrees(math.asin(m[2, 3] / 4.0))
            assert 10.0 <= elevation <= 60.0
            # camera looks at the origin: OpenGL -z axis points from the centre to the origin
            np.testing.assert_allclose(-m[:3, 2], -m[:3, 3] / 4.0, atol=1e-12)
            assert 0.0 <= fr["time"] <= 1.0
        if split == "train":
            np.testing.assert_allclose([fr["time"] for fr in doc["frames"]], np.arange(12) / 11)
    img = read_image(root / "train" / "r_000.png")
    assert img.shape == (32, 32, 4)
    assert (root / "points3d.ply").is_file()


def test_deterministic_for_a_seed(tmp_path):
    a = synthesize_scene(tmp_path / "a", resolution=24, frames=6, seed=5, points=300)
    b = synthesize_scene(tmp_path / "b", resolution=24, frames=6, seed=5, points=300)
    c = synthesize_scene(tmp_path / "c", resolution=24, frames=6, seed=6, points=300)
    fa, fb, fc = _files(a), _files(b), _files(c)
    assert fa.keys() == fb.keys() == fc.keys()
    assert fa == fb
    assert fa["transforms_train.json"] != fc["transforms_train.json"]
    assert sum(fa[k] != fc[k] for k in fa) >= len(fa) - 2  # nearly every file differs


def test_fixed_time_is_static(tmp_path):
    root = synthesize_scene(tmp_path / "s", resolution=16, frames=5, seed=1, fixed_time=0.25, points=0)
    for split in ("train", "val", "test"):
        doc = json.loads((root / f"transforms_{split}.json").read_text())
        assert {fr["time"] for fr in doc["frames"]} == {0.25}
    assert not (root / "points3d.ply").exists()


def test_test_frames_sets_the_test_split_alone(tmp_path):
    """`test_frames` writes that many test views and leaves the other splits as they were."""
    plain = synthesize_scene(tmp_path / "a", resolution=16, frames=10, seed=3, points=0)
    more = synthesize_scene(tmp_path / "b", resolution=16, frames=10, seed=3, points=0,
                            test_frames=7)
    counts = {}
    for root in (plain, more):
        counts[root.name] = {s: len(json.loads((root / f"transforms_{s}.json").read_text())["frames"])
                             for s in ("train", "val", "test")}
    assert counts["a"] == {"train": 10, "val": 1, "test": 1}
    assert counts["b"] == {"train": 10, "val": 1, "test": 7}
    assert len(list((more / "test").glob("r_*.png"))) == 7
    for name in ("transforms_train.json", "transforms_val.json"):
        assert (plain / name).read_bytes() == (more / name).read_bytes()
    with pytest.raises(ValueError, match="test_frames"):
        synthesize_scene(tmp_path / "c", resolution=16, frames=10, points=0, test_frames=0)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="teapot"):
        synthesize_scene(tmp_path / "x", scene="teapot")
    with pytest.raises(ValueError, match="teapot"):
        scene_objects("teapot", 0.0)
    with pytest.raises(ValueError, match="fixed_time"):
        synthesize_scene(tmp_path / "x", fixed_time=1.5)


@pytest.mark.parametrize("scene", SCENES)
def test_objects_stay_in_the_dnerf_cube(scene):
    names = set()
    for t in np.linspace(0.0, 1.0, 41):
        for obj in scene_objects(scene, t):
            names.add(obj.name)
            if isinstance(obj, Sphere):
                lo, hi = obj.centre - obj.radius, obj.centre + obj.radius
            else:
                corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
                pts = obj.centre + (corners * obj.half_size) @ obj.rotation.T
                lo, hi = pts.min(axis=0), pts.max(axis=0)
            assert (lo >= -BOUND).all() and (hi <= BOUND).all(), (scene, t, obj.name)
    assert {"still", "mover", "spinner"} <= names


@pytest.mark.parametrize("scene", SCENES)
def test_still_object_pixels_identical_across_time(scene):
    cam = _camera(az=3.9, el=0.4, size=48)  # looking from the still object's side
    objs0, objs1 = scene_objects(scene, 0.0), scene_objects(scene, 1.0)
    k = [o.name for o in objs0].index("still")
    rgba0, cov0 = render_view(objs0, cam, return_coverage=True)
    rgba1, cov1 = render_view(objs1, cam, return_coverage=True)
    mask = (cov0[..., k] == 1.0) & (cov1[..., k] == 1.0)
    assert mask.sum() > 30
    np.testing.assert_array_equal(rgba0[mask], rgba1[mask])
    # the scene as a whole does change
    assert np.abs(rgba0 - rgba1).max() > 0.5


@pytest.mark.parametrize("scene", SCENES)
def test_spinner_rotates_and_mover_translates(scene):
    o0, o1 = _by_name(scene_objects(scene, 0.0)), _by_name(scene_objects(scene, 0.4))
    spin0, spin1 = o0["spinner"], o1["spinner"]
    assert isinstance(spin0, Box)
    np.testing.assert_array_equal(spin0.centre, spin1.centre)  # rotates in place
    assert not np.allclose(spin0.rotation, spin1.rotation)
    assert np.linalg.norm(o0["mover"].centre - o1["mover"].centre) > 0.2
    cam = _camera(az=2.0, el=0.8, size=48)
    a0 = render_view([spin0], cam)[..., 3]
    a1 = render_view([spin1], cam)[..., 3]
    assert np.abs(a0 - a1).mean() > 0.01  # its silhouette changes


def test_render_view_alpha_is_soft_coverage():
    cam = _camera(size=40)
    rgba = render_view(scene_objects("spheres", 0.3), cam, supersample=3)
    alpha = rgba[..., 3]
    assert rgba.dtype == np.float32 and rgba.shape == (40, 40, 4)
    assert alpha[0, 0] == 0.0 and (rgba[alpha == 0, :3] == 0).all()  # transparent background
    assert (alpha == 1.0).sum() > 50
    edge = (alpha > 0) & (alpha < 1)
    assert edge.sum() > 20
    assert set(np.round(alpha[edge] * 9).astype(int)) - {0, 9}  # multiples of 1/9
    hard = render_view(scene_objects("spheres", 0.3), cam, supersample=1)[..., 3]
    assert set(np.unique(hard)) <= {0.0, 1.0}


def test_render_view_matches_projection_of_a_single_sphere():
    # A sphere of radius r at distance D has angular radius asin(r/D): check the silhouette size.
    size, fov = 81, math.radians(40)
    cam = _camera(az=0.3, el=0.4, size=size, fov=fov)
    r = 0.5
    rgba = render_view([Sphere("s", np.zeros(3), r, (1.0, 1.0, 1.0))], cam, supersample=4)
    area = rgba[..., 3].sum()
    f = cam.fx
    expected_radius_px = f * math.tan(math.asin(r / 4.0))
    assert area == pytest.approx(math.pi * expected_radius_px ** 2, rel=0.03)
    ys, xs = np.nonzero(rgba[..., 3] > 0.5)
    assert xs.mean() + 0.5 == pytest.approx(cam.cx, abs=0.5)
    assert ys.mean() + 0.5 == pytest.approx(cam.cy, abs=0.5)
