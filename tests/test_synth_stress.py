"""The stress suite (nehad.data.synth_stress): the MuJoCo protocol, label masks that agree with
the geometry, and each scene showing the failure class it is meant to probe."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nehad.data.synth import Sphere, label_mask, render_view
from nehad.data.synth_stress import (STRESS_SCENES, rig_camera, rig_cameras, stress_objects,
                                     stress_plan, synthesize_stress_scene)
from nehad.runtime.cameras import Camera
from nehad.viz.masks import read_label_mask


def _camera(cam_id: int, size: int = 64, t: float = 0.0) -> Camera:
    return rig_camera(cam_id, size, time=t)


def test_plan_is_the_mujoco_protocol():
    plan = stress_plan(120)
    assert [len(plan[s]) for s in ("train", "test", "val")] == [84, 18, 18]
    # blocks of 20 timestamps: 14 train, then 3 test, then 3 val
    assert [k for k, _, _ in plan["test"][:3]] == [14, 15, 16]
    assert [k for k, _, _ in plan["val"][:3]] == [17, 18, 19]
    for entries in plan.values():
        for k, t, cam in entries:
            assert t == pytest.approx(k / 119)
    # one camera per timestamp, cycling through all 12 fixed cameras
    assert sorted({cam for _, _, cam in plan["train"][:12]}) == list(range(12))
    positions = np.array([c[:3, 3] for c in rig_cameras()])
    assert len(np.unique(positions.round(6), axis=0)) == 12


def test_written_scene_layout_and_masks(tmp_path):
    root = synthesize_stress_scene(tmp_path / "occ", "occluder", resolution=40, frames=40,
                                   points=500)
    names = json.loads((root / "class_mapping.json").read_text())
    assert names == {"0": "background", "1": "wall", "2": "sphere"}  # the floor is background
    doc = json.loads((root / "transforms_train.json").read_text())
    assert len(doc["frames"]) == 28
    for f in doc["frames"][:5]:
        stem = f["file_path"].split("/")[-1]
        m = read_label_mask(root / "train" / "masks" / f"{stem}.png")
        assert m.shape == (40, 40) and set(np.unique(m)) <= {0, 1, 2}
    # the initial cloud is MuJoCo's: random points in a cube, not on the surfaces
    assert (root / "fused.ply").stat().st_size > 500 * 15


def test_a_scene_of_given_objects_is_written_like_the_suite(tmp_path):
    """`objects=` draws a caller's scene (bench/variant_scenes.py) in the suite's protocol: its
    names in the class mapping, and a frame's pixels those of the objects at its time."""
    from nehad.data.synth_stress import FLOOR
    from nehad.runtime.images import read_image

    def objects(t):
        return [FLOOR, Sphere("ball", np.array([0.3 * t, 0.0, 0.3]), 0.3, (0.9, 0.1, 0.1))]

    root = synthesize_stress_scene(tmp_path / "v", "any name", resolution=24, frames=20,
                                   points=0, supersample=1, objects=objects)
    assert json.loads((root / "class_mapping.json").read_text()) == {"0": "background",
                                                                     "1": "ball"}
    frame = json.loads((root / "transforms_train.json").read_text())["frames"][3]
    cam = rig_camera(frame["camera"], 24, time=frame["time"])
    stem = frame["file_path"].split("/")[-1]
    ours = read_image(root / "train" / f"{stem}.png")
    np.testing.assert_allclose(ours, render_view(objects(frame["time"]), cam, supersample=1),
                               atol=1 / 255)


def test_label_mask_follows_coverage():
    """Against an independent count: each pixel of a lone sphere's mask is a pixel whose centre
    ray hits the sphere, up to the pixels on its outline."""
    cam = _camera(0, size=48)
    sphere = Sphere("s", np.array([0.0, 0.0, 0.4]), 0.5, (1.0, 0.0, 0.0))
    _, cov = render_view([sphere], cam, supersample=4, return_coverage=True)
    mask = label_mask([sphere], cov)
    hard = render_view([sphere], cam, supersample=1)[..., 3] > 0.5
    assert mask.max() == 1
    assert abs(int((mask == 1).sum()) - int(hard.sum())) <= 0.15 * hard.sum()


def test_occluder_hides_the_sphere_in_some_views_only():
    """The sphere is in front of the empty background, in front of the wall and behind it."""
    hidden = visible = 0
    for k, (t, cam_id) in enumerate([(k / 119, k % 12) for k in range(0, 120, 2)]):
        objs = stress_objects("occluder", t)
        cam = _camera(cam_id, t=t)
        _, cov = render_view(objs, cam, supersample=1, return_coverage=True)
        px = int((label_mask(objs, cov) == 2).sum())
        uv, z = cam.project(objs[2].centre[None])
        in_frame = 0 <= uv[0, 0] < 64 and 0 <= uv[0, 1] < 64
        if in_frame and px == 0:
            hidden += 1
        elif px > 0:
            visible += 1
    assert hidden >= 3 and visible >= 20


def test_fast_ball_is_seen_in_few_frames():
    seen = 0
    plan = stress_plan(120)["train"]
    for k, t, cam_id in plan:
        objs = stress_objects("fast_few_frames", t)
        _, cov = render_view(objs, _camera(cam_id, size=32, t=t), supersample=1,
                             return_coverage=True)
        seen += int((label_mask(objs, cov) == 2).sum() > 0)
    assert 5 <= seen <= 0.2 * len(plan)
    # and the test split sees it too, so the evaluation scores it
    in_test = 0
    for k, t, cam_id in stress_plan(120)["test"]:
        objs = stress_objects("fast_few_frames", t)
        _, cov = render_view(objs, _camera(cam_id, size=32, t=t), supersample=1,
                             return_coverage=True)
        in_test += int((label_mask(objs, cov) == 2).sum() > 0)
    assert in_test >= 2


def test_checker_sphere_shows_both_colours_and_turns():
    cam = _camera(0, size=64)
    a = render_view(stress_objects("spinning_textures", 0.0)[1:2], cam, supersample=1)
    b = render_view(stress_objects("spinning_textures", 0.05)[1:2], cam, supersample=1)
    on = a[..., 3] > 0.99
    chroma = a[..., :3][on] / a[..., :3][on].sum(-1, keepdims=True)
    assert (chroma[:, 2] > 0.4).any() and (chroma[:, 2] < 0.15).any()  # purple and yellow cells
    assert np.abs(a - b)[..., :3].max() > 0.3  # the pattern moved


@pytest.mark.parametrize("name", STRESS_SCENES)
def test_every_labelled_object_is_seen(name):
    """Each labelled object of each scene covers pixels in some frame of the rig."""
    objs0 = stress_objects(name, 0.0)
    labelled = [i + 1 for i in range(sum(o.labelled for o in objs0))]
    seen = set()
    for k, t, cam_id in stress_plan(120)["train"]:
        objs = stress_objects(name, t)
        _, cov = render_view(objs, _camera(cam_id, size=32, t=t), supersample=1,
                             return_coverage=True)
        seen |= set(np.unique(label_mask(objs, cov)).tolist())
    assert set(labelled) <= seen


def test_same_arguments_same_bytes(tmp_path):
    a = synthesize_stress_scene(tmp_path / "a", "thin_rod", resolution=16, frames=20, points=50)
    b = synthesize_stress_scene(tmp_path / "b", "thin_rod", resolution=16, frames=20, points=50)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files and all((a / f).read_bytes() == (b / f).read_bytes() for f in files)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="unknown stress scene"):
        synthesize_stress_scene(tmp_path / "x", "teapot")
    with pytest.raises(ValueError, match="frames"):
        synthesize_stress_scene(tmp_path / "x", "occluder", frames=10)
