"""HyperNeRF and DyNeRF readers and writers (issue 7): round trip against the D-NeRF twin of the
same synthetic views, the file conventions written out independently of the readers, image scales,
lens distortion, frame caching and stride, layout detection and bad data."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from nehad.data.dnerf import DatasetError, load_dnerf
from nehad.data.loader import detect_format, load_dataset
from nehad.data.synth import scene_objects
from nehad.data.synth_formats import HYPERNERF_CENTER, HYPERNERF_SCALE, synthesize_format

BLACK = (0.0, 0.0, 0.0)
SIZE = (28, 20)  # non-square on purpose


@pytest.fixture(scope="module")
def hyper(tmp_path_factory):
    root = tmp_path_factory.mktemp("hyper")
    synthesize_format(root / "scene", "hypernerf", resolution=SIZE, frames=9, seed=4, points=300,
                      twin=root / "twin")
    return root / "scene", root / "twin"


@pytest.fixture(scope="module")
def dyn(tmp_path_factory):
    root = tmp_path_factory.mktemp("dyn")
    synthesize_format(root / "scene", "dynerf", resolution=SIZE, frames=5, cameras=3, seed=5,
                      points=300, twin=root / "twin")
    return root / "scene", root / "twin"


@pytest.fixture
def hyper_copy(hyper, tmp_path):
    shutil.copytree(hyper[0], tmp_path / "h")
    return tmp_path / "h"


@pytest.fixture
def dyn_copy(dyn, tmp_path):
    """A writable copy of the DyNeRF scene as written: videos, no frame cache."""
    src = dyn[0]
    shutil.copytree(src, tmp_path / "d", ignore=lambda d, names: [
        n for n in names if Path(d) == src and (src / n).is_dir()])
    return tmp_path / "d"


def _cam_error(a, b) -> float:
    return max(float(np.abs(a.world_to_camera - b.world_to_camera).max()),
               float(np.abs(np.array([a.fx, a.fy, a.cx, a.cy]) - [b.fx, b.fy, b.cx, b.cy]).max()),
               abs(a.time - b.time), abs(a.width - b.width), abs(a.height - b.height))


def _compare(scene, twin, split):
    fa, fb = scene.frames[split], twin.frames[split]
    assert len(fa) == len(fb) > 0
    cam = max(_cam_error(x.camera, y.camera) for x, y in zip(fa, fb))
    img = max(float(np.abs(x.image - y.image).max()) for x, y in zip(fa, fb))
    return cam, img


# --------------------------------------------------------------------------------------------
# round trip: each format read back equals the D-NeRF twin of the same views


@pytest.mark.parametrize("which", ["hyper", "dyn"])
def test_round_trip_equals_dnerf_twin(which, request):
    root, twin_root = request.getfixturevalue(which)
    scene = load_dataset(root, splits=("train", "test", "val"), background=BLACK)
    twin = load_dnerf(twin_root, splits=("train", "test", "val"), background=BLACK)
    for split in ("train", "test", "val"):
        cam, img = _compare(scene, twin, split)
        print(f"{which} {split}: {len(scene.frames[split])} frames, camera error {cam:.2g}, "
              f"image error {img:.2g}")
        assert cam <= 1e-6
        assert img == 0.0  # the same 8-bit values
    assert scene.frames["train"][0].image.shape == (SIZE[1], SIZE[0], 3)
    # the images are not trivially empty: the objects cover part of every frame
    for f in scene.frames["train"]:
        assert 0.05 < float((f.image.max(axis=2) > 0.05).mean()) < 0.95
    assert np.abs(scene.initial_points - twin.initial_points).max() <= 1e-6
    assert scene.extent == pytest.approx(twin.extent, abs=1e-9)
    assert scene.time_range == (0.0, 1.0)


def test_hypernerf_times_splits_and_layout(hyper):
    root, _ = hyper
    scene = load_dataset(root, splits=("train", "test"))
    assert detect_format(root) == "hypernerf" and scene.format == "hypernerf"
    times = scene.times("train")
    assert np.allclose(times, np.arange(9) / 8.0, atol=0, rtol=0)  # warp_id / max(warp_id)
    assert [f.camera.name for f in scene.frames["test"]] == [
        "test/right_000000", "test/right_000004", "test/right_000008"]
    assert np.allclose(scene.times("test"), [0.0, 0.5, 1.0])
    cam = scene.frames["train"][0].camera
    assert (cam.cx, cam.cy) == pytest.approx((0.53 * SIZE[0], 0.48 * SIZE[1]))  # off-centre kept
    assert scene.near == pytest.approx(1.7) and scene.far == pytest.approx(6.3)
    # raw files are in another frame than the scene: the normalisation was exercised
    raw = json.loads((root / "camera" / "left_000000.json").read_text())["position"]
    assert np.allclose((np.array(raw) - HYPERNERF_CENTER) * HYPERNERF_SCALE, cam.centre, atol=1e-12)
    assert np.linalg.norm(cam.centre) == pytest.approx(4.0)


def test_hypernerf_camera_convention_written_out(hyper_copy):
    """A hand-written nerfies camera (orientation = world-to-camera, projection
    u = f x + skew y + px, v = f a y + py, pixel centres at i + 0.5) against Camera.project."""
    root = hyper_copy
    rot = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # a proper rotation
    pos = np.array([3.0, -1.0, 2.0])
    doc = {"orientation": rot.tolist(), "position": pos.tolist(), "focal_length": 30.0,
           "principal_point": [13.0, 11.0], "skew": 0.0, "pixel_aspect_ratio": 1.25,
           "radial_distortion": [0.0, 0.0, 0.0], "tangential_distortion": [0.0, 0.0],
           "image_size": list(SIZE)}
    (root / "camera" / "left_000000.json").write_text(json.dumps(doc))
    cam = load_dataset(root, splits=("train",)).frames["train"][0].camera
    world = np.array([[5.0, -1.5, 1.0], [4.0, 0.5, 3.0], [6.0, -2.0, 2.5]])
    local = (world - pos) @ rot.T
    u = 30.0 * local[:, 0] / local[:, 2] + 13.0
    v = 30.0 * 1.25 * local[:, 1] / local[:, 2] + 11.0
    normalised = (world - HYPERNERF_CENTER) * HYPERNERF_SCALE  # the reader's world frame
    uv, z = cam.project(normalised)
    assert np.allclose(uv, np.stack([u, v], 1), atol=1e-9)
    assert (z > 0).all()


def test_hypernerf_image_scale_folder_and_fallback(hyper, tmp_path):
    root, twin_root = hyper
    half = load_dataset(root, splits=("train",), downscale=2)  # reads rgb/2x
    twin_half = load_dnerf(twin_root, splits=("train",), background=BLACK, downscale=2)
    cam, img = _compare(half, twin_half, "train")
    print(f"rgb/2x vs twin downscaled: camera error {cam:.2g}, image error {img:.3g}")
    assert half.frames["train"][0].image.shape == (SIZE[1] // 2, SIZE[0] // 2, 3)
    assert half.frames["train"][0].path.parent.name == "2x"
    assert cam <= 1e-6 and img <= 1.0 / 255 + 1e-6  # q8(mean) vs mean(q8)
    # without rgb/2x the reader averages rgb/1x itself, exactly as the D-NeRF reader does
    copy = tmp_path / "no2x"
    shutil.copytree(root, copy)
    shutil.rmtree(copy / "rgb" / "2x")
    own = load_dataset(copy, splits=("train",), downscale=2)
    cam, img = _compare(own, twin_half, "train")
    assert cam <= 1e-6 and img <= 1e-6
    with pytest.raises(DatasetError, match=r"rgb/4x.*1x"):
        shutil.rmtree(copy / "rgb" / "1x")
        load_dataset(copy, splits=("train",), downscale=4)


def test_hypernerf_interp_split_without_val_ids(hyper_copy):
    path = hyper_copy / "dataset.json"
    doc = json.loads(path.read_text())
    doc["val_ids"] = []
    path.write_text(json.dumps(doc))
    scene = load_dataset(hyper_copy, splits=("train", "test"))
    ids = doc["ids"]  # 9 left + 3 right = 12 images: train 0, 4, 8; test 2, 6 (4DGS)
    assert [f.camera.name.split("/")[1] for f in scene.frames["train"]] == [ids[0], ids[4], ids[8]]
    assert [f.camera.name.split("/")[1] for f in scene.frames["test"]] == [ids[2], ids[6]]


def test_hypernerf_lens_distortion_undistorted_or_refused(tmp_path):
    k = (-0.3, 0.08, 0.0, 0.01, -0.008)
    synthesize_format(tmp_path / "s", "hypernerf", resolution=(64, 48), frames=3, points=0,
                      twin=tmp_path / "t", distortion=k, skew=3.0, fov_deg=60.0)
    scene = load_dataset(tmp_path / "s", splits=("train",))
    truth = load_dnerf(tmp_path / "t", splits=("train",), background=BLACK)
    from nehad.data.common import read_rgb

    for f, g in zip(scene.frames["train"], truth.frames["train"]):
        raw = read_rgb(f.path, np.zeros(3))[0]
        p_und = -10 * math.log10(float(np.mean((f.image - g.image) ** 2)))
        p_raw = -10 * math.log10(float(np.mean((raw - g.image) ** 2)))
        print(f"{f.path.name}: undistorted {p_und:.1f} dB, as stored {p_raw:.1f} dB vs pinhole truth")
        assert p_und > 36.0 and p_und > p_raw + 3.0
        assert _cam_error(f.camera, g.camera) <= 1e-6  # the pinhole camera of the same K
    with pytest.raises(DatasetError, match=r"left_000000\.json: field 'radial_distortion'"):
        load_dataset(tmp_path / "s", splits=("train",), undistort=False)


# --------------------------------------------------------------------------------------------
# DyNeRF specifics


def test_dynerf_pose_convention_written_out(dyn):
    """Loaded cameras against the 4DGS formula for an LLFF row, written out here:
    R = [P1, -P0, P2]; R = -R; R[:, 0] = -R[:, 0]; T = -c . R; world-to-camera = [R^T | T]."""
    root, _ = dyn
    rows = np.load(root / "poses_bounds.npy")
    scene = load_dataset(root, splits=("train", "test"))
    by_cam = {f.camera.name.split("/")[1]: f.camera for fs in scene.frames.values() for f in fs}
    for i, row in enumerate(rows):
        p = row[:15].reshape(3, 5)
        r = np.stack([p[:, 1], -p[:, 0], p[:, 2]], 1)
        r = -r
        r[:, 0] = -r[:, 0]
        t = -p[:, 3] @ r
        cam = by_cam[f"cam{i:02d}"]
        assert np.allclose(cam.world_to_camera[:3, :3], r.T, atol=1e-12)
        assert np.allclose(cam.world_to_camera[:3, 3], t, atol=1e-12)
        h, w, focal = p[:, 4]
        assert (cam.width, cam.height, cam.fx, cam.cx) == (w, h, focal, w / 2)
        # the camera looks at the scene: the origin projects inside the image, in front
        uv, z = cam.project([[0.0, 0.0, 0.0]])
        assert z[0] > 0 and 0 < uv[0, 0] < w and 0 < uv[0, 1] < h
    assert scene.near == pytest.approx(1.7) and scene.far == pytest.approx(6.3)


def test_dynerf_objects_project_onto_their_colours(dyn):
    root, _ = dyn
    scene = load_dataset(root, splits=("test",))
    hits = 0
    for f in scene.frames["test"]:
        for obj in scene_objects("spheres", f.time):
            if obj.name != "mover":
                continue
            uv, z = f.camera.project([obj.centre])
            u, v = uv[0]
            assert z[0] > 0
            px = f.image[int(v), int(u)]
            assert px[0] > 0.3 and px[0] > 2 * px[1] and px[0] > 2 * px[2], (f.camera.name, px)
            hits += 1
    assert hits == 5


def test_dynerf_cache_stride_and_pre_extracted_frames(dyn_copy):
    root = dyn_copy
    assert not (root / "cam00" / "images").exists()
    test = load_dataset(root, splits=("test",))
    # only the loaded camera was decoded, into 4DGS's cache location, and nothing else was left
    assert sorted(p.name for p in (root / "cam00" / "images").iterdir()) == [
        f"{k:04d}.png" for k in range(5)]
    assert not (root / "cam01").exists()
    assert not [p for p in root.rglob(".*")]
    assert np.allclose(test.times("test"), np.arange(5) / 4)
    strided = load_dataset(root, splits=("train",), frame_stride=2)
    names = [f.camera.name for f in strided.frames["train"]]
    assert names == [f"train/cam0{c}/{k:04d}" for c in (1, 2) for k in (0, 2, 4)]
    assert np.allclose(strided.times("train"), [0.0, 0.5, 1.0] * 2)  # times of the full video
    # the cache is used as it is: without the videos the frames still load, identically
    full = load_dataset(root, splits=("train", "test"))
    for mp4 in root.glob("cam*.mp4"):
        mp4.unlink()
    again = load_dataset(root, splits=("train", "test"))
    for s in ("train", "test"):
        cam, img = _compare(full, again, s)
        assert cam == 0.0 and img == 0.0


def test_dynerf_png_frames_and_max_frames(tmp_path):
    synthesize_format(tmp_path / "s", "dynerf", resolution=SIZE, frames=4, cameras=2, points=0,
                      twin=tmp_path / "t", video="png")
    assert not list((tmp_path / "s").glob("*.mp4"))
    scene = load_dataset(tmp_path / "s", splits=("train", "test"))
    twin = load_dnerf(tmp_path / "t", splits=("train", "test"), background=BLACK)
    for s in ("train", "test"):
        cam, img = _compare(scene, twin, s)
        assert cam <= 1e-6 and img == 0.0
    short = load_dataset(tmp_path / "s", splits=("test",), max_frames=3)
    assert np.allclose(short.times("test"), [0.0, 0.5, 1.0])


# --------------------------------------------------------------------------------------------
# layout detection, presets


def test_detect_format(hyper, dyn, tmp_path):
    assert detect_format(hyper[1]) == "dnerf" and detect_format(dyn[0]) == "dynerf"
    with pytest.raises(DatasetError, match="not a dataset folder"):
        detect_format(tmp_path)
    (tmp_path / "cam00.mp4").write_bytes(b"x")
    with pytest.raises(DatasetError, match="poses_bounds.npy"):
        detect_format(tmp_path)
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "missing")


def test_presets_follow_spec_section_5():
    from nehad.config import build_config

    h, d = build_config("hypernerf"), build_config("dynerf")
    assert (h.field.out_dim, h.field.resolution, h.field.multires, h.field.width) == (
        16, (64, 64, 64, 150), (1, 2, 4), 128)
    assert (d.field.out_dim, d.field.resolution, d.field.multires, d.field.width) == (
        16, (64, 64, 64, 150), (1, 2), 128)
    assert d.field.deform_opacity_sh and not h.field.deform_opacity_sh
    assert h.data.downscale == 2 and d.data.downscale == 2
    assert (h.coarse.iterations, h.fine.iterations) == (3000, 20000)
    assert build_config("test", None, ["data.frame_stride=3"]).data.frame_stride == 3
    from nehad.configtools import ConfigError

    with pytest.raises(ConfigError, match="frame_stride"):
        build_config("test", None, ["data.frame_stride=0"])


# --------------------------------------------------------------------------------------------
# bad data: an error that names the file


def test_hypernerf_missing_camera_file(hyper_copy):
    (hyper_copy / "camera" / "left_000003.json").unlink()
    with pytest.raises(DatasetError, match=r"camera/left_000003\.json: camera file not found"):
        load_dataset(hyper_copy, splits=("train",))


@pytest.mark.parametrize("edit, needle", [
    (lambda r: (r / "rgb" / "1x" / "left_000002.png").unlink(), r"left_000002\.png: image file"),
    (lambda r: (r / "rgb" / "1x" / "left_000002.png").write_bytes(b"garbage"),
     r"left_000002\.png: cannot read image"),
    (lambda r: (r / "scene.json").write_text('{"center": [0, 0, 0]}'), r"scene\.json: field 'scale'"),
    (lambda r: (r / "metadata.json").write_text("{"), r"metadata\.json: malformed JSON"),
    (lambda r: (r / "metadata.json").write_text('{"left_000000": {"warp_id": 0}}'),
     r"metadata\.json: entry 'left_000001': missing"),
    (lambda r: _edit(r / "camera" / "left_000001.json", orientation=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]),
     r"left_000001\.json: field 'orientation': not a rotation"),
    (lambda r: _edit(r / "camera" / "left_000001.json", focal_length=-3),
     r"left_000001\.json: field 'focal_length'"),
    (lambda r: _edit(r / "camera" / "left_000001.json", image_size=[10, 10]),
     r"left_000001\.png: image is 28x20 but .*left_000001\.json"),
    (lambda r: _edit(r / "dataset.json", train_ids=["nope"]), r"dataset\.json: field 'train_ids'"),
    (lambda r: (r / "dataset.json").unlink(), r"not a dataset folder \(looks like HyperNeRF"),
])
def test_hypernerf_bad_data(hyper_copy, edit, needle):
    edit(hyper_copy)
    with pytest.raises(DatasetError, match=needle):
        load_dataset(hyper_copy, splits=("train",))


def _edit(path: Path, **fields):
    doc = json.loads(path.read_text())
    doc.update(fields)
    path.write_text(json.dumps(doc))


def test_dynerf_pose_count_not_matching_videos(dyn_copy):
    (dyn_copy / "cam02.mp4").unlink()
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy: holds 3 camera poses but .* 2 "
                                           r"camera videos.*cam00, cam01"):
        load_dataset(dyn_copy, splits=("train",))


def test_dynerf_unreadable_video_leaves_no_cache(dyn_copy):
    (dyn_copy / "cam01.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video")
    with pytest.raises(DatasetError, match=r"cam01\.mp4: cannot decode video"):
        load_dataset(dyn_copy, splits=("train",))
    assert not (dyn_copy / "cam01" / "images").exists()
    assert not [p for p in dyn_copy.rglob(".*")]


def test_dynerf_truncated_video(dyn_copy):
    video = dyn_copy / "cam02.mp4"
    data = video.read_bytes()
    video.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"cam02\.mp4"):
        load_dataset(dyn_copy, splits=("train",))
    assert not (dyn_copy / "cam02" / "images").exists()


@pytest.mark.parametrize("content, needle", [
    (None, r"poses_bounds\.npy: poses file not found"),
    (np.zeros((3, 15)), r"poses_bounds\.npy: expected an \(N, 17\) array"),
    (b"not npy", r"poses_bounds\.npy: cannot read"),
])
def test_dynerf_bad_poses_file(dyn_copy, content, needle):
    path = dyn_copy / "poses_bounds.npy"
    path.unlink()
    if isinstance(content, np.ndarray):
        np.save(path, content)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(DatasetError, match=needle):
        load_dataset(dyn_copy, splits=("train",), format="dynerf")


def test_dynerf_bad_pose_row(dyn_copy):
    path = dyn_copy / "poses_bounds.npy"
    rows = np.load(path)
    rows[1, :3] *= 2.0  # no longer a rotation
    np.save(path, rows)
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy: row 1 \(cam01\) rotation"):
        load_dataset(dyn_copy, splits=("test",))


def test_cli_reports_bad_data_in_one_line(dyn_copy, tmp_path):
    pytest.importorskip("torch")
    from click.testing import CliRunner

    from nehad.cli.main import main

    (dyn_copy / "cam01.mp4").write_bytes(b"garbage")
    res = CliRunner().invoke(main, ["train", str(dyn_copy), "-o", str(tmp_path / "run"),
                                    "--preset", "test", "--quiet"])
    assert res.exit_code == 1, res.output
    assert "Error:" in res.output and "cam01.mp4: cannot decode video" in res.output
    assert "Traceback" not in res.output


def test_frame_stride_on_dnerf_and_hypernerf(hyper):
    root, twin_root = hyper
    full = load_dataset(twin_root, splits=("train",), background=BLACK)
    every3 = load_dataset(twin_root, splits=("train",), background=BLACK, frame_stride=3)
    assert every3.format == "dnerf"
    assert [f.path for f in every3.frames["train"]] == [f.path for f in full.frames["train"][::3]]
    hyper3 = load_dataset(root, splits=("train",), frame_stride=3)
    assert np.allclose(hyper3.times("train"), [0.0, 3 / 8, 6 / 8])
    with pytest.raises(ValueError, match="frame_stride"):
        load_dataset(root, frame_stride=0)
