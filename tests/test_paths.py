"""Camera paths and time schedules (nehad.runtime.paths, issue 5): the --path / --time syntaxes,
orbit geometry derived from reference cameras, and frame planning."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nehad.runtime.cameras import Camera, camera_to_dict
from nehad.runtime.paths import (
    PathError,
    Reference,
    look_at,
    orbit_cameras,
    orbit_params_from_cameras,
    parse_path_spec,
    parse_time_spec,
    plan_frames,
    spiral_cameras,
)


def ring(centre, radius, elevation_deg, up=(0, 0, 1), n=6, size=(40, 30), f=35.0, times=None):
    """Cameras on a circle around `centre`, looking at it (as a training rig is)."""
    up = np.asarray(up, float)
    a = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = a - up * (a @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    el = math.radians(elevation_deg)
    cams = []
    for k in range(n):
        az = 2 * math.pi * k / n + 0.3
        eye = np.asarray(centre) + radius * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2)
                                             + math.sin(el) * up)
        t = None if times is None else times[k]
        cams.append(Camera(size[0], size[1], f, f, size[0] / 2, size[1] / 2,
                           look_at(eye, centre, up), t, f"cam{k}"))
    return cams


def test_look_at_centres_the_target_and_keeps_up_up():
    w2c = look_at([0, -4, 1], [0, 0, 0], [0, 0, 1])
    cam = Camera(64, 48, 50, 50, 32, 24, w2c)
    uv, z = cam.project([[0, 0, 0], [0, 0, 0.3], [0.3, 0, 0]])
    assert np.allclose(uv[0], [32, 24]) and z[0] > 0
    assert uv[1, 1] < 24  # a point above the target is higher in the image (v grows downwards)
    assert uv[2, 0] > 32  # +x is to the right seen from -y
    assert np.allclose(cam.centre, [0, -4, 1])
    with pytest.raises(PathError, match="parallel"):
        look_at([0, 0, 4], [0, 0, 0], [0, 0, 1])


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 1, 0), (0, -1, 0)])
def test_orbit_parameters_are_recovered_from_a_camera_rig(up):
    centre = np.array([0.3, -0.2, 0.5])
    p = orbit_params_from_cameras(ring(centre, 4.0, 25.0, up=up))
    assert np.allclose(p.centre, centre, atol=1e-9)
    assert np.allclose(p.up, up, atol=1e-9)
    assert p.radius == pytest.approx(4.0) and p.elevation == pytest.approx(25.0)
    assert (p.width, p.height, p.fx) == (40, 30, 35.0)


def test_one_reference_camera_orbits_the_point_of_its_axis_nearest_the_box():
    cam = ring([0, 0, 0], 4.0, 30.0, n=1)[0]
    aabb = np.array([[-1, -1, -1], [1, 1, 1.0]])
    p = orbit_params_from_cameras([cam], aabb)
    assert np.allclose(p.centre, 0, atol=1e-9)
    assert np.allclose(p.up, [0, 0, 1])
    assert p.radius == pytest.approx(4.0) and p.elevation == pytest.approx(30.0)
    # frame 0 of the orbit is the reference camera itself
    c0 = orbit_cameras(p, 8)[0]
    assert np.allclose(c0.world_to_camera, cam.world_to_camera, atol=1e-9)


def test_orbit_cameras_circle_the_centre_and_look_at_it():
    p = orbit_params_from_cameras(ring([1, 2, 3], 3.0, 10.0))
    cams = orbit_cameras(p, 12, turns=1)
    centres = np.stack([c.centre for c in cams])
    assert np.allclose(np.linalg.norm(centres - [1, 2, 3], axis=1), 3.0)
    heights = (centres - [1, 2, 3]) @ np.array([0, 0, 1.0])
    assert np.allclose(heights, 3.0 * math.sin(math.radians(10)))
    for c in cams:
        uv, z = c.project([[1, 2, 3]])
        assert np.allclose(uv[0], [c.cx, c.cy]) and z[0] > 0
    # evenly spaced over one closed loop: the step from the last back to the first is a step
    steps = np.linalg.norm(np.roll(centres, -1, axis=0) - centres, axis=1)
    assert np.allclose(steps, steps[0])


def test_spiral_swings_elevation_and_radius():
    p = orbit_params_from_cameras(ring([0, 0, 0], 4.0, 20.0))
    cams = spiral_cameras(p, 40, turns=2, amplitude=10, zoom=0.25)
    d = np.array([np.linalg.norm(c.centre) for c in cams])
    assert d.min() == pytest.approx(3.0, rel=0.02) and d.max() == pytest.approx(5.0, rel=0.02)
    el = np.degrees(np.arcsin([c.centre[2] / np.linalg.norm(c.centre) for c in cams]))
    assert el.min() == pytest.approx(10, abs=0.5) and el.max() == pytest.approx(30, abs=0.5)


def test_path_spec_syntax():
    s = parse_path_spec("orbit:radius=3,elevation=20,centre=[0,0.5,1],up=-y,turns=2")
    assert s.kind == "orbit" and s.options["radius"] == 3 and s.options["turns"] == 2
    assert np.allclose(s.options["centre"], [0, 0.5, 1]) and np.allclose(s.options["up"], [0, -1, 0])
    assert parse_path_spec("spiral").kind == "spiral" and parse_path_spec("default").kind == "default"
    assert parse_path_spec("orbit:center=1 2 3").options["centre"].tolist() == [1, 2, 3]


@pytest.mark.parametrize("spec, match", [
    ("orbit:radus=3", "unknown key 'radus'"),
    ("orbit:radius=-1", "radius=-1: must be positive"),
    ("orbit:radius=abc", "radius=abc: not a number"),
    ("orbit:elevation=95", "elevation=95"),
    ("orbit:centre=[1,2]", "centre=\\[1,2\\]: expected three numbers"),
    ("orbit:centre=[1,2,3", "unbalanced"),
    ("orbit:radius", "not key=value"),
    ("orbit:radius=1,radius=2", "given twice"),
    ("spiral:zoom=2", "zoom=2"),
    ("orbit:amplitude=3", "unknown key 'amplitude' for orbit"),
    ("nowhere.json", "not a path kind"),
    ("", "empty camera path"),
])
def test_bad_path_specs_name_the_key(spec, match):
    with pytest.raises(PathError, match=match):
        parse_path_spec(spec)


def test_dataset_and_file_specs(tmp_path):
    (tmp_path / "data").mkdir()
    s = parse_path_spec(f"{tmp_path / 'data'}:test")
    assert s.kind == "dataset" and s.split == "test"
    with pytest.raises(PathError, match="unknown split 'tst'"):
        parse_path_spec(f"{tmp_path / 'data'}:tst")
    with pytest.raises(PathError, match="needs a split"):
        parse_path_spec(str(tmp_path / "data"))
    f = tmp_path / "cams.json"
    f.write_text("[]")
    assert parse_path_spec(str(f)).kind == "file"
    assert parse_path_spec(f"{f}:2").file == f"{f}:2"


def test_time_specs():
    assert parse_time_spec("0.2:0.8") == parse_time_spec(" 0.2:0.8 ").__class__("0.2:0.8", "sweep", 0.2, 0.8)
    t = parse_time_spec("0.5")
    assert (t.mode, t.start) == ("freeze", 0.5)
    assert parse_time_spec("own").mode == "own"
    for bad in ("a:b", "x", "nan", "0:inf"):
        with pytest.raises(PathError):
            parse_time_spec(bad)


def reference():
    cam = ring([0, 0, 0], 4.0, 30.0, n=1, size=(32, 32))[0]
    return Reference(cam, np.array([[-1, -1, -1], [1, 1, 1.0]]), (0.0, 1.0))


def test_plan_orbit_sweeps_the_time_range_and_resizes():
    frames = plan_frames("orbit", None, 5, (64, 48), reference())
    assert [f.index for f in frames] == list(range(5))
    assert [f.time for f in frames] == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    assert all((f.camera.width, f.camera.height) == (64, 48) for f in frames)
    assert frames[0].camera.fx == pytest.approx(reference().default_camera.fx * 2)
    frozen = plan_frames("orbit", "0.3", 4, None, reference())
    assert [f.time for f in frozen] == [0.3] * 4  # bullet time
    part = plan_frames("spiral", "0.2:0.4", 3, None, reference())
    assert [f.time for f in part] == pytest.approx([0.2, 0.3, 0.4])


def test_plan_frozen_camera_sweeps_time(tmp_path):
    cam = ring([0, 0, 0], 4, 10, n=1)[0]
    f = tmp_path / "cam.json"
    f.write_text(json.dumps(camera_to_dict(cam)))
    frames = plan_frames(str(f), "0:1", 3, None, reference())
    assert [x.time for x in frames] == pytest.approx([0, 0.5, 1])
    assert all(np.allclose(x.camera.world_to_camera, cam.world_to_camera) for x in frames)
    assert len(plan_frames("default", None, None, None, reference())) == 120
    assert len(plan_frames("default", "0.5", None, None, reference())) == 1


def test_plan_camera_list_uses_own_times(tmp_path):
    cams = ring([0, 0, 0], 4, 10, n=4, times=[0.1, 0.4, 0.2, 0.9])
    f = tmp_path / "path.json"
    f.write_text(json.dumps([camera_to_dict(c) for c in cams]))
    frames = plan_frames(str(f), None, None, None, reference())
    assert [x.time for x in frames] == pytest.approx([0.1, 0.4, 0.2, 0.9])
    assert [x.time for x in plan_frames(str(f), "0.5", None, None, reference())] == [0.5] * 4
    with pytest.raises(PathError, match="holds 4 cameras; frames 3"):
        plan_frames(str(f), None, 3, None, reference())
    # one camera of the list, frozen, swept over time
    frames = plan_frames(f"{f}:1", "0:1", 2, None, reference())
    assert [x.time for x in frames] == [0.0, 1.0]


def test_plan_checks_times_and_static_scenes_have_none():
    with pytest.raises(PathError, match="time 1.5 is outside the trained time range"):
        plan_frames("orbit", "0:1.5", 4, None, reference())
    assert plan_frames("orbit", "0:1.5", 4, None, reference(), extrapolate=True)[-1].time == 1.5
    static = Reference(reference().default_camera, None, None)
    assert [f.time for f in plan_frames("orbit", None, 3, None, static)] == [None] * 3
    with pytest.raises(PathError, match="no default camera"):
        plan_frames("orbit", None, 3, None, Reference(None, None, (0, 1)))
    explicit = plan_frames("orbit:centre=[0,0,0],radius=2,fov=60", None, 2, None,
                           Reference(None, None, (0, 1)))
    assert np.linalg.norm(explicit[0].camera.centre) == pytest.approx(2)


def test_plan_orbit_from_a_dataset_and_its_split(tmp_path):
    from nehad.data.synth import synthesize_scene

    data = synthesize_scene(tmp_path / "scene", resolution=16, frames=20, points=50)
    frames = plan_frames(f"orbit:from={data}", None, 6, None, Reference(None, None, (0, 1)))
    assert len(frames) == 6 and frames[0].camera.width == 16
    test = json.loads((data / "transforms_test.json").read_text())["frames"]
    frames = plan_frames(f"{data}:test", None, None, None, reference())
    assert len(frames) == len(test) == 2
    assert [f.time for f in frames] == pytest.approx([fr["time"] for fr in test])
    assert all(f.ground_truth and f.ground_truth.endswith(".png") for f in frames)
    # the same cameras and images as the training package's dataset reader
    from nehad.data.dnerf import load_dnerf

    scene = load_dnerf(data, splits=("test",))
    for planned, frame in zip(frames, scene.frames["test"]):
        assert planned.ground_truth == str(frame.path)
        np.testing.assert_allclose(planned.camera.world_to_camera,
                                   frame.camera.world_to_camera, atol=1e-12)
        assert (planned.camera.fx, planned.camera.cx) == pytest.approx(
            (frame.camera.fx, frame.camera.cx))
