"""D-NeRF reader (nehad.data.dnerf): round trip with the synthetic scene, conventions, errors, real data."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from nehad.data.dnerf import DatasetError, DNeRFScene, load_dnerf
from nehad.data.synth import Box, render_view, scene_objects, synthesize_scene
from nehad.runtime.cameras import Camera
from nehad.runtime.images import read_image, write_image

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
LEGO = SHARED_DATA / "dnerf_lego_100"
MUJOCO = SHARED_DATA / "mujoco" / "scene1_close_proximity"


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory):
    return synthesize_scene(tmp_path_factory.mktemp("dnerf") / "spheres", resolution=48, frames=20,
                            seed=3, points=500)


@pytest.fixture
def scene_copy(synth_root, tmp_path):
    """A writable copy of the synthetic scene for tests that corrupt it."""
    dst = tmp_path / "scene"
    shutil.copytree(synth_root, dst)
    return dst


def _project(cam: Camera, point) -> tuple[float, float, float]:
    """u, v, depth of a world point, written out from docs/design.md section 3 (not via the library)."""
    x = cam.world_to_camera[:3, :3] @ np.asarray(point, dtype=np.float64) + cam.world_to_camera[:3, 3]
    return cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy, x[2]


def _edit_json(root: Path, split: str, fn) -> Path:
    path = root / f"transforms_{split}.json"
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))
    return path


# --------------------------------------------------------------------------------------------
# round trip with the synthetic scene


def test_round_trip_projects_object_centres_onto_their_colours(synth_root):
    """The camera read back, projecting each object's centre (at the frame's time), lands on a
    pixel of that object's colour: checks the OpenGL->OpenCV axes, intrinsics and time end to end."""
    scene = load_dnerf(synth_root)
    checked = matched = flipped_matched = 0
    for split, frames in scene.frames.items():
        for fr in frames:
            assert fr.image.shape == (48, 48, 3) and fr.alpha.shape == (48, 48)
            for obj in scene_objects("spheres", fr.time):
                u, v, z = _project(fr.camera, obj.centre)
                assert z > 0
                i, j = int(math.floor(v)), int(math.floor(u))
                assert 0 <= i < 48 and 0 <= j < 48
                colour = np.asarray(obj.colour)

                def is_object(px, a):
                    s = px @ colour / (colour @ colour)
                    return a > 0.99 and 0.25 < s < 1.05 and np.abs(px - s * colour).max() < 0.05

                checked += 1
                matched += is_object(fr.image[i, j], fr.alpha[i, j])
                flipped_matched += is_object(fr.image[47 - i, j], fr.alpha[47 - i, j])
    assert checked == 4 * 24
    assert matched >= 0.85 * checked  # the rest are occluded by another object
    assert flipped_matched < 0.5 * checked  # the check can tell a flipped y axis


def test_round_trip_rerenders_the_same_images(synth_root):
    scene = load_dnerf(synth_root, background=(1.0, 1.0, 1.0))
    fx = 0.5 * 48 / math.tan(math.radians(45) / 2)
    for fr in scene.frames["train"][::5] + scene.frames["test"]:
        assert fr.camera.fx == pytest.approx(fx) and fr.camera.fy == pytest.approx(fx)
        assert (fr.camera.cx, fr.camera.cy) == (24.0, 24.0)
        assert np.linalg.norm(fr.camera.centre) == pytest.approx(4.0)
        rgba = render_view(scene_objects("spheres", fr.time), fr.camera)
        a = rgba[..., 3:]
        np.testing.assert_allclose(fr.image, rgba[..., :3] + (1 - a), atol=1.5 / 255)
        np.testing.assert_allclose(fr.alpha, rgba[..., 3], atol=0.5 / 255)


def test_scene_fields(synth_root):
    scene = load_dnerf(synth_root)
    assert isinstance(scene, DNeRFScene)
    assert {k: len(v) for k, v in scene.frames.items()} == {"train": 20, "val": 2, "test": 2}
    np.testing.assert_allclose(scene.times("train"), np.arange(20) / 19)
    assert scene.time_range == (0.0, 1.0)
    assert scene.background == (1.0, 1.0, 1.0)
    assert scene.frames["train"][3].path == synth_root / "train" / "r_003.png"
    assert scene.frames["train"][3].camera.name == "train/r_003"
    assert scene.extent == pytest.approx(1.1 * max(np.linalg.norm(
        np.stack([c.centre for c in scene.cameras()]) - np.mean([c.centre for c in scene.cameras()], axis=0),
        axis=1)))
    # points3d.ply: surface points of the scene at t = 0.5 with the objects' colours
    assert scene.initial_points.shape == (500, 3) and scene.initial_colors.shape == (500, 3)
    assert np.abs(scene.initial_points).max() <= 1.3
    palette = np.round(np.array([o.colour for o in scene_objects("spheres", 0.5)]) * 255) / 255
    d = np.abs(scene.initial_colors[:, None, :] - palette[None]).max(axis=-1).min(axis=1)
    assert d.max() < 1e-6
    lo, hi = scene.bounds
    np.testing.assert_allclose(lo, scene.initial_points.min(axis=0), rtol=1e-6)
    # surface points: each lies on the surface of some object at t = 0.5
    objs = scene_objects("spheres", 0.5)
    spheres = [o for o in objs if not isinstance(o, Box)]
    on_sphere = np.min([np.abs(np.linalg.norm(scene.initial_points - o.centre, axis=1) - o.radius)
                        for o in spheres], axis=0)
    box = next(o for o in objs if isinstance(o, Box))
    local = (scene.initial_points - box.centre) @ box.rotation
    on_box = np.abs(np.abs(local) - box.half_size).min(axis=1)
    inside_box = (np.abs(local) <= box.half_size + 1e-5).all(axis=1)
    assert (np.minimum(on_sphere, np.where(inside_box, on_box, np.inf)) < 1e-5).all()


def test_background_and_single_split(synth_root):
    black = load_dnerf(synth_root, splits=("val",), background=(0.0, 0.0, 0.0))
    white = load_dnerf(synth_root, splits="val", background=1.0)
    assert list(black.frames) == ["val"]
    fb, fw = black.frames["val"][0], white.frames["val"][0]
    np.testing.assert_allclose(fw.image - fb.image, np.repeat(1 - fb.alpha[..., None], 3, axis=2), atol=1e-6)
    assert fb.image[0, 0].tolist() == [0.0, 0.0, 0.0]


def test_downscale_halves_size_and_focal(synth_root):
    full = load_dnerf(synth_root, splits=("train",))
    half = load_dnerf(synth_root, splits=("train",), downscale=2)
    for a, b in zip(full.frames["train"][:4], half.frames["train"]):
        assert b.image.shape == (24, 24, 3) and b.alpha.shape == (24, 24)
        assert (b.camera.width, b.camera.height) == (24, 24)
        assert b.camera.fx == pytest.approx(a.camera.fx / 2) and b.camera.fy == pytest.approx(a.camera.fy / 2)
        assert (b.camera.cx, b.camera.cy) == (12.0, 12.0)
        np.testing.assert_array_equal(b.camera.world_to_camera, a.camera.world_to_camera)
        assert b.time == a.time
        np.testing.assert_allclose(b.image, a.image.reshape(24, 2, 24, 2, 3).mean(axis=(1, 3)), atol=1e-6)
    for bad in (0, 1.5, -2):
        with pytest.raises(ValueError, match="downscale"):
            load_dnerf(synth_root, downscale=bad)


def test_downscale_with_remainder_crops(tmp_path):
    root = synthesize_scene(tmp_path / "odd", resolution=21, frames=2, seed=0, points=0)
    full = load_dnerf(root, splits=("train",)).frames["train"][0]
    third = load_dnerf(root, splits=("train",), downscale=2).frames["train"][0]
    assert third.image.shape == (10, 10, 3)
    assert third.camera.fx == pytest.approx(full.camera.fx / 2)
    assert third.camera.cx == pytest.approx(full.camera.cx / 2)


def test_times_outside_unit_interval_are_normalised(scene_copy):
    for split in ("train", "val", "test"):
        _edit_json(scene_copy, split, lambda d: [fr.update(time=10 + 40 * fr["time"]) for fr in d["frames"]])
    # train spans [10, 50]; val/test fall inside it: all normalise with the same (10, 50) map
    ref = json.loads((scene_copy / "transforms_val.json").read_text())
    scene = load_dnerf(scene_copy, splits=("val",))
    assert scene.source_time_range == (10.0, 50.0)
    np.testing.assert_allclose(scene.times("val"), [(fr["time"] - 10) / 40 for fr in ref["frames"]])
    full = load_dnerf(scene_copy)
    np.testing.assert_allclose(full.times("train"), np.arange(20) / 19, atol=1e-12)


def test_per_frame_intrinsics_take_precedence(scene_copy):
    def add(d):
        d["frames"][0].update(fl_x=50.0, fl_y=55.0, cx=20.0, cy=26.0, w=48, h=48)
    _edit_json(scene_copy, "train", add)
    scene = load_dnerf(scene_copy, splits=("train",), downscale=2)
    cam = scene.frames["train"][0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (25.0, 27.5, 10.0, 13.0)
    other = scene.frames["train"][1].camera
    assert other.fx == pytest.approx(0.5 * 24 / math.tan(math.radians(45) / 2))


def test_rgb_images_are_used_as_they_are(scene_copy):
    img = read_image(scene_copy / "train" / "r_000.png")
    write_image(scene_copy / "train" / "r_000.png", img[..., :3])
    scene = load_dnerf(scene_copy, splits=("train",), background=(1.0, 1.0, 1.0))
    fr = scene.frames["train"][0]
    assert fr.alpha is None
    np.testing.assert_allclose(fr.image, img[..., :3], atol=0.5 / 255 + 1e-7)  # background ignored
    assert fr.image[0, 0].tolist() == [0.0, 0.0, 0.0]


def test_ascii_ply_and_extra_properties(scene_copy):
    (scene_copy / "points3d.ply").unlink()
    (scene_copy / "points3D.ply").write_text(
        "ply\nformat ascii 1.0\ncomment test\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float nx\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 1 255 0 0\n1 2 3 0 0 255 0\n-1 0.5 0.25 0 0 0 255\n3 0 1 2\n")
    scene = load_dnerf(scene_copy, splits=("val",))
    np.testing.assert_allclose(scene.initial_points, [[0, 0, 0], [1, 2, 3], [-1, 0.5, 0.25]])
    np.testing.assert_allclose(scene.initial_colors, np.eye(3))
    assert scene.points_path.name == "points3D.ply"


def test_binary_ply_with_normals_and_no_colours(scene_copy):
    rec = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
    rec["x"] = [1, 2, 3, 4]
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nend_header\n")
    (scene_copy / "fused.ply").write_bytes(header.encode() + rec.tobytes())  # preferred over points3d.ply
    scene = load_dnerf(scene_copy, splits=("val",))
    assert scene.points_path.name == "fused.ply"
    np.testing.assert_array_equal(scene.initial_points[:, 0], [1, 2, 3, 4])
    assert scene.initial_colors is None
    (scene_copy / "fused.ply").write_bytes(header.encode() + rec.tobytes()[:-5])
    with pytest.raises(DatasetError, match=r"fused\.ply.*truncated"):
        load_dnerf(scene_copy, splits=("val",))


def test_no_point_cloud(scene_copy):
    (scene_copy / "points3d.ply").unlink()
    scene = load_dnerf(scene_copy, splits=("val",))
    assert scene.initial_points is None and scene.initial_colors is None
    lo, hi = scene.bounds
    np.testing.assert_array_equal(hi, [1.3, 1.3, 1.3])


# --------------------------------------------------------------------------------------------
# errors name the file and the field


def _set(k, key, value):
    def fn(d):
        d["frames"][k][key] = value
    return fn


def _drop(k, key):
    def fn(d):
        del d["frames"][k][key]
    return fn


@pytest.mark.parametrize("edit, field", [
    (_drop(3, "time"), r"frames\[3\]\.time"),
    (_drop(2, "transform_matrix"), r"frames\[2\]\.transform_matrix"),
    (_set(1, "transform_matrix", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), r"frames\[1\]\.transform_matrix.*4x4"),
    (_set(4, "transform_matrix", [[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     r"frames\[4\]\.transform_matrix.*NaN"),
    (_set(0, "time", float("nan")), r"frames\[0\]\.time"),
    (_set(0, "time", "soon"), r"frames\[0\]\.time"),
    (_set(5, "w", 64), r"frames\[5\]\.w.*64"),
    (_set(5, "fl_x", -3.0), r"frames\[5\]\.fl_x"),
    (_set(6, "file_path", 7), r"frames\[6\]\.file_path"),
    (lambda d: d.pop("camera_angle_x"), r"camera_angle_x"),
    (lambda d: d.pop("frames"), r"'frames'"),
])
def test_bad_transforms_fields(scene_copy, edit, field):
    path = _edit_json(scene_copy, "train", edit)
    with pytest.raises(DatasetError, match=field) as info:
        load_dnerf(scene_copy)
    assert str(path) in str(info.value)


def test_missing_transforms_file(scene_copy):
    (scene_copy / "transforms_test.json").unlink()
    with pytest.raises(DatasetError, match=r"transforms_test\.json.*not found"):
        load_dnerf(scene_copy)
    assert len(load_dnerf(scene_copy, splits=("train", "val")).frames["val"]) == 2
    with pytest.raises(DatasetError, match="scene folder"):
        load_dnerf(scene_copy / "nope")


def test_malformed_json(scene_copy):
    (scene_copy / "transforms_val.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    with pytest.raises(DatasetError, match=r"transforms_val\.json.*malformed JSON"):
        load_dnerf(scene_copy, splits=("train",))  # val takes part in the time range, so it is read


def test_missing_image(scene_copy):
    (scene_copy / "train" / "r_007.png").unlink()
    with pytest.raises(DatasetError, match=r"r_007\.png.*not found.*transforms_train\.json frames\[7\]\.file_path"):
        load_dnerf(scene_copy)


def test_unreadable_image(scene_copy):
    (scene_copy / "val" / "r_001.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"r_001\.png") as e:
        load_dnerf(scene_copy, splits=("val",))
    assert str(e.value).count("cannot read image") == 1, str(e.value)  # it was said twice
    assert "frames[1].file_path" in str(e.value)


def test_bad_ply(scene_copy):
    (scene_copy / "points3d.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n0\n1\n")
    with pytest.raises(DatasetError, match=r"points3d\.ply.*'y'"):
        load_dnerf(scene_copy, splits=("val",))


# --------------------------------------------------------------------------------------------
# the real data in ../shared/data (skipped when absent)


@pytest.mark.skipif(not LEGO.is_dir(), reason="shared data dnerf_lego_100 not available")
def test_real_lego():
    scene = load_dnerf(LEGO, background=(0.0, 0.0, 0.0))
    assert {k: len(v) for k, v in scene.frames.items()} == {"train": 50, "val": 11, "test": 20}
    assert scene.time_range == (0.0, 1.0)
    fr = scene.frames["train"][0]
    assert fr.image.shape == (100, 100, 3) and fr.alpha is None
    doc = json.loads((LEGO / "transforms_train.json").read_text())
    assert fr.camera.fx == pytest.approx(50 / math.tan(doc["camera_angle_x"] / 2))
    assert scene.initial_points is None
    # every camera looks at the model at the origin: the origin projects onto a non-black pixel,
    # while most of each image is black background
    for frames in scene.frames.values():
        for fr in frames:
            u, v, z = _project(fr.camera, np.zeros(3))
            assert z > 0 and fr.image[int(v), int(u)].max() > 0.05
    assert np.mean([(f.image.max(axis=-1) > 0.05).mean() for f in scene.frames["train"]]) < 0.5


@pytest.mark.skipif(not MUJOCO.is_dir(), reason="shared data mujoco/scene1_close_proximity not available")
def test_real_mujoco_val_downscaled():
    scene = load_dnerf(MUJOCO, splits=("val",), downscale=2)
    frames = scene.frames["val"]
    doc = json.loads((MUJOCO / "transforms_val.json").read_text())
    assert len(frames) == len(doc["frames"]) == 21
    for fr, raw in zip(frames, doc["frames"]):
        assert fr.image.shape == (400, 400, 3) and fr.alpha.shape == (400, 400)
        assert fr.camera.fx == pytest.approx(raw["fl_x"] / 2)  # per-frame intrinsics win
        assert fr.camera.cx == pytest.approx(raw["cx"] / 2)
        assert fr.time == raw["time"]  # already in [0, 1]: kept
    assert 0.0 < frames[0].alpha.mean() < 1.0
    assert scene.initial_points.shape == (100000, 3) and scene.initial_colors is not None


def test_image_io_alpha_convention_the_reader_relies_on(tmp_path):
    """nehad.runtime.images keeps RGBA premultiplied in memory (OpenImageIO associated alpha) and
    straight in PNG files. load_dnerf and synthesize_scene rely on it: if this changes, change
    dnerf._load_image (compositing) and synth.render_view (what it hands to write_image)."""
    cv2 = pytest.importorskip("cv2")
    path = write_image(tmp_path / "a.png", np.array([[[0.4, 0.2, 0.1, 0.5]]], dtype=np.float32))
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[0, 0, [2, 1, 0, 3]]
    # straight in the file (to within the 8-bit rounding of the premultiplied values)
    np.testing.assert_allclose(stored.astype(int), [204, 102, 51, 128], atol=1)
    np.testing.assert_allclose(read_image(path)[0, 0], [0.4, 0.2, 0.1, 0.5], atol=1 / 255)
