"""Cameras and the `--view` file (docs/design.md sections 3 and 3.1)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from nehad.runtime.cameras import (Camera, CameraError, camera_to_dict, load_view, parse_camera,
                                   save_view)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


# A generic pose: OpenGL camera-to-world (Blender axes), rotated about a skew axis, off origin.
C2W_GL = np.eye(4)
C2W_GL[:3, :3] = _rot([0.3, -0.5, 0.8], 0.9)
C2W_GL[:3, 3] = [1.5, -2.0, 3.25]
C2W_CV = C2W_GL @ GL_TO_CV
W2C_CV = np.linalg.inv(C2W_CV)
W2C_GL = np.linalg.inv(C2W_GL)

CANONICAL = {"width": 640, "height": 480, "fx": 500.0, "fy": 510.0, "cx": 320.5, "cy": 239.5,
             "camera_to_world": C2W_GL.tolist(), "convention": "opengl", "time": 0.25}


def _same(a: Camera, b: Camera):
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, rtol=0, atol=1e-9)
    assert a.isclose(b)


def test_canonical_pose_and_projection():
    cam = parse_camera(CANONICAL)
    np.testing.assert_allclose(cam.world_to_camera, W2C_CV, atol=1e-12)
    np.testing.assert_allclose(cam.centre, C2W_GL[:3, 3], atol=1e-12)
    assert cam.time == 0.25
    # OpenGL cameras look along -z of their frame: a point 3 units straight ahead -> principal point
    ahead = C2W_GL[:3, 3] - 3.0 * C2W_GL[:3, 2]
    uv, z = cam.project(ahead)
    np.testing.assert_allclose(uv[0], [320.5, 239.5], atol=1e-9)
    np.testing.assert_allclose(z, [3.0], atol=1e-12)
    # OpenGL +y (up) of the camera maps to smaller v (up in the image), +x to larger u
    uv2, _ = cam.project(ahead + 0.3 * C2W_GL[:3, 1] + 0.1 * C2W_GL[:3, 0])
    np.testing.assert_allclose(uv2[0], [320.5 + 500.0 * 0.1 / 3, 239.5 - 510.0 * 0.3 / 3], atol=1e-9)


def test_spec_example_camera():
    cam = parse_camera({"width": 800, "height": 800, "fx": 1111.1, "fy": 1111.1,
                        "camera_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]})
    assert (cam.cx, cam.cy) == (400.0, 400.0)  # default W/2, H/2
    assert cam.time is None
    uv, z = cam.project([0.0, 0.0, 0.0])  # the origin is 4 units in front
    np.testing.assert_allclose(uv[0], [400, 400])
    np.testing.assert_allclose(z, [4.0])


@pytest.mark.parametrize("variant", ["w2c_gl", "c2w_cv", "w2c_cv", "c2w_3x4", "w2c_3x4_cv"])
def test_alternative_matrix_forms(variant):
    ref = parse_camera(CANONICAL)
    d = dict(CANONICAL)
    del d["camera_to_world"]
    if variant == "w2c_gl":
        d["world_to_camera"] = W2C_GL.tolist()
    elif variant == "c2w_cv":
        d["camera_to_world"], d["convention"] = C2W_CV.tolist(), "opencv"
    elif variant == "w2c_cv":
        d["world_to_camera"], d["convention"] = W2C_CV.tolist(), "opencv"
    elif variant == "c2w_3x4":
        d["camera_to_world"] = C2W_GL[:3].tolist()
        del d["convention"]  # opengl is the default
    elif variant == "w2c_3x4_cv":
        d["world_to_camera"], d["convention"] = W2C_CV[:3].tolist(), "OpenCV"
    _same(parse_camera(d), ref)


def test_fov_forms():
    d = dict(CANONICAL)
    del d["fx"], d["fy"]
    fov_x = 2 * math.atan(640 / (2 * 500.0))
    cam = parse_camera(dict(d, fov_x=fov_x))
    assert cam.fx == pytest.approx(500.0, abs=1e-9) and cam.fy == pytest.approx(500.0, abs=1e-9)
    assert cam.fov_x == pytest.approx(fov_x, abs=1e-12)
    fov_y = 2 * math.atan(480 / (2 * 510.0))
    _same(parse_camera(dict(d, fov_x=fov_x, fov_y=fov_y)), parse_camera(CANONICAL))
    cam = parse_camera(dict(d, fov_y=fov_y))
    assert cam.fx == pytest.approx(510.0, abs=1e-9) and cam.fy == pytest.approx(510.0, abs=1e-9)
    # explicit focal and field of view together must agree
    parse_camera(dict(CANONICAL, fov_x=fov_x))
    with pytest.raises(CameraError, match="fov_x"):
        parse_camera(dict(CANONICAL, fov_x=fov_x * 1.01))


def test_3dgs_cameras_json_entry(tmp_path):
    entry = {"id": 7, "img_name": "r_007", "width": 640, "height": 480,
             "position": C2W_CV[:3, 3].tolist(), "rotation": C2W_CV[:3, :3].tolist(),
             "fx": 500.0, "fy": 510.0}
    ref = parse_camera({k: v for k, v in CANONICAL.items() if k not in ("cx", "cy", "time")})
    cam = parse_camera(entry)
    _same(cam, ref)
    assert cam.name == "r_007"
    # the 3DGS file is a list of entries
    f = tmp_path / "cameras.json"
    f.write_text(json.dumps([entry, dict(entry, id=8, img_name="r_008")]))
    cams = load_view(f)
    assert isinstance(cams, list) and len(cams) == 2
    _same(cams[1], ref)
    assert load_view(f"{f}:1").name == "r_008"
    assert load_view(f, frame=0).name == "r_007"


def test_camera_path_and_roundtrip(tmp_path):
    ref = parse_camera(CANONICAL)
    d = camera_to_dict(ref)
    assert d["convention"] == "opengl" and d["time"] == 0.25
    np.testing.assert_allclose(d["camera_to_world"], C2W_GL, atol=1e-12)
    _same(parse_camera(d), ref)
    one = save_view(tmp_path / "cam.json", ref)
    _same(load_view(one), ref)
    assert oct(os.stat(one).st_mode & 0o777) != oct(0o600)  # ordinary permissions, not mkstemp's
    moved = Camera(ref.width, ref.height, ref.fx, ref.fy, ref.cx, ref.cy,
                   W2C_CV @ np.linalg.inv(np.block([[_rot([1, 2, 3], 0.4), np.ones((3, 1))],
                                                    [np.zeros((1, 3)), np.ones((1, 1))]])),
                   0.75, "second")
    path = save_view(tmp_path / "path.json", [ref, moved])
    cams = load_view(path)
    assert len(cams) == 2 and cams[1].time == 0.75 and cams[1].name == "second"
    _same(load_view(f"{path}#1"), moved)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam.json", "path.json"]  # no temp files


def _transforms(tmp_path, with_size=True, per_frame=False):
    frames = []
    for i, t in enumerate([0.0, 0.5, 1.0]):
        m = C2W_GL.copy()
        m[0, 3] += i
        fr = {"file_path": f"./test/r_{i:03d}", "time": t, "transform_matrix": m.tolist()}
        if per_frame:
            fr.update(fl_x=500.0, fl_y=510.0, cx=320.5, cy=239.5, w=640, h=480)
        frames.append(fr)
    doc = {"camera_angle_x": 2 * math.atan(640 / (2 * 500.0)), "frames": frames}
    if with_size:
        doc.update(w=640, h=480)
    f = tmp_path / "transforms_test.json"
    f.write_text(json.dumps(doc))
    return f


def test_transforms_file(tmp_path):
    f = _transforms(tmp_path)
    cam = load_view(f, frame=2)
    ref = parse_camera(dict(CANONICAL, fy=500.0, cx=320, cy=240, time=1.0))
    assert cam.time == 1.0
    np.testing.assert_allclose(cam.centre, C2W_GL[:3, 3] + [2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(cam.world_to_camera[:3, :3], ref.world_to_camera[:3, :3], atol=1e-12)
    assert (cam.width, cam.height, cam.cx, cam.cy) == (640, 480, 320, 240)
    assert cam.fx == pytest.approx(500.0, abs=1e-9) and cam.fy == pytest.approx(500.0, abs=1e-9)
    _same(load_view(f"{f}:2"), cam)
    assert len(load_view(f)) == 3
    # nerfstudio-style per-frame intrinsics
    g = _transforms(tmp_path, with_size=False, per_frame=True)
    cam = load_view(g, frame=0)
    _same(cam, parse_camera(dict(CANONICAL, time=0.0)))


def test_transforms_size_from_image_header(tmp_path):
    from nehad.runtime.images import write_image

    f = _transforms(tmp_path, with_size=False)
    (tmp_path / "test").mkdir()
    write_image(tmp_path / "test" / "r_001.png", np.zeros((48, 64, 3), np.float32))
    cam = load_view(f, frame=1)
    assert (cam.width, cam.height) == (64, 48)
    assert cam.fx == pytest.approx(0.5 * 64 / math.tan(0.5 * 2 * math.atan(640 / 1000.0)))
    with pytest.raises(CameraError, match=r"frames\[0\]\.file_path"):
        load_view(f, frame=0)  # its image is absent and the file gives no w/h


@pytest.mark.skipif(not DATA.is_dir(), reason="shared evaluation data not present")
def test_real_dnerf_frame():
    f = DATA / "dnerf_lego_100" / "transforms_test.json"
    doc = json.loads(f.read_text())
    cam = load_view(f"{f}:3")
    fr = doc["frames"][3]
    assert (cam.width, cam.height) == (100, 100)
    assert cam.fx == pytest.approx(50.0 / math.tan(doc["camera_angle_x"] / 2), rel=1e-12)
    assert cam.fy == cam.fx and (cam.cx, cam.cy) == (50.0, 50.0)
    assert cam.time == pytest.approx(fr["time"])
    c2w = np.array(fr["transform_matrix"])
    np.testing.assert_allclose(cam.world_to_camera, np.linalg.inv(c2w @ GL_TO_CV), atol=1e-6)
    uv, z = cam.project(c2w[:3, 3] - 2.0 * c2w[:3, 2])
    np.testing.assert_allclose(uv[0], [50, 50], atol=1e-5)
    assert z[0] == pytest.approx(2.0, abs=1e-6)
    # the scene centre (origin) is in front of every lego test camera
    for c in load_view(f):
        assert c.project([0, 0, 0])[1][0] > 0


BAD = [
    ({"width": None}, "width"),
    ({"width": "640"}, "width"),
    ({"width": 0}, "width"),
    ({"height": -5}, "height"),
    ({"height": 480.5}, "height"),
    ({"fx": -1.0}, "fx"),
    ({"fx": float("nan")}, "fx"),
    ({"fy": float("inf")}, "fy"),
    ({"fy": True}, "fy"),
    ({"cx": float("nan")}, "cx"),
    ({"time": float("nan")}, "time"),
    ({"convention": "directx"}, "convention"),
    ({"camera_to_world": (C2W_GL * np.diag([2, 1, 1, 1.0])).tolist()},
     "rotation of camera_to_world is not orthonormal"),
    ({"camera_to_world": (C2W_GL @ np.diag([1, 1, -1, 1.0])).tolist()}, "camera_to_world"),
    ({"camera_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 1, 1]]}, "bottom row"),
    ({"camera_to_world": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "camera_to_world"),
    ({"camera_to_world": [[1, 0, 0, "a"], [0, 1, 0, 0], [0, 0, 1, 4]]}, "camera_to_world"),
    ({"camera_to_world": [[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 4]]}, "camera_to_world"),
    ({"world_to_camera": np.eye(4).tolist()}, "not both"),
]


@pytest.mark.parametrize("change,field", BAD)
def test_invalid_cam_json(change, field):
    d = dict(CANONICAL)
    d.update(change)
    d = {k: v for k, v in d.items() if v is not None}
    with pytest.raises(CameraError, match=field.replace("(", r"\(")) as e:
        parse_camera(d, source="cam.json")
    assert str(e.value).startswith("cam.json: ")


@pytest.mark.parametrize("drop,field", [("width", "width"), ("height", "height"), ("fy", "fy"),
                                        ("camera_to_world", "camera_to_world")])
def test_missing_field(drop, field):
    d = {k: v for k, v in CANONICAL.items() if k != drop}
    with pytest.raises(CameraError, match=f"{field}: missing field"):
        parse_camera(d)


@pytest.mark.parametrize("fov", [0.0, -0.5, math.pi, 4.0, float("nan")])
def test_invalid_fov(fov):
    d = {k: v for k, v in CANONICAL.items() if k not in ("fx", "fy")}
    with pytest.raises(CameraError, match="fov_x"):
        parse_camera(dict(d, fov_x=fov))


def test_invalid_3dgs_entry():
    entry = {"id": 0, "img_name": "a", "width": 64, "height": 48, "position": [0, 0, 0],
             "rotation": (2 * np.eye(3)).tolist(), "fx": 50.0, "fy": 50.0}
    with pytest.raises(CameraError, match="rotation of rotation is not orthonormal"):
        parse_camera(entry)
    with pytest.raises(CameraError, match="position"):
        parse_camera(dict(entry, rotation=np.eye(3).tolist(), position=[0, 0]))


def test_file_errors(tmp_path):
    with pytest.raises(CameraError, match="no such camera file"):
        load_view(tmp_path / "absent.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"width": 64,')
    with pytest.raises(CameraError, match=r"bad\.json: malformed JSON"):
        load_view(bad)
    one = save_view(tmp_path / "one.json", parse_camera(CANONICAL))
    with pytest.raises(CameraError, match="frame index 1 out of range"):
        load_view(one, frame=1)
    f = _transforms(tmp_path)
    with pytest.raises(CameraError, match="frame index 3 out of range"):
        load_view(f"{f}:3")
    with pytest.raises(CameraError, match="given twice"):
        load_view(f"{f}:1", frame=2)
    doc = json.loads(f.read_text())
    doc["frames"][1]["transform_matrix"][0][0] = 3.0
    f.write_text(json.dumps(doc))
    load_view(f, frame=0)  # other frames are fine on their own
    with pytest.raises(CameraError, match=r"frames\[1\]\.transform_matrix: rotation of"):
        load_view(f, frame=1)
    with pytest.raises(CameraError, match=r"frames\[1\]\.transform_matrix"):
        load_view(f)  # the whole path is refused, not rendered half-valid
    lst = tmp_path / "list.json"
    lst.write_text(json.dumps([CANONICAL, dict(CANONICAL, fx=-1)]))
    with pytest.raises(CameraError, match=r"list\.json\[1\]: fx"):
        load_view(lst)
