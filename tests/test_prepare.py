"""`nehad prepare` (issue 30): made-up captures posed by COLMAP against their true cameras, the
scene it writes read back by the training reader, and one clean error per bad input.

The captures are drawn by the project's ray caster (nehad.data.synth_capture) at test size:
8 cameras x 5 frames at 256x256 for a rig (SfM on 16 images, seconds). The figures at the
issue's size (12 videos of 60 frames at 400x400) are bench/prepare.py's.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("pycolmap")

from clean_errors import one_error as _one_error  # noqa: E402
from nehad.cli.main import main  # noqa: E402
from nehad.data.synth import orbit_camera_to_world  # noqa: E402
from nehad.data.synth_capture import pose_errors, synthesize_capture  # noqa: E402
from nehad.runtime.mp4 import encode  # noqa: E402

pytestmark = pytest.mark.slow


def _invoke(*args):
    return CliRunner().invoke(main, ["prepare", *map(str, args), "--threads", "1"])


def _nothing_left(scene: Path) -> None:
    assert not scene.exists() or not any(scene.iterdir()), sorted(scene.iterdir())
    leftovers = [p.name for p in scene.parent.iterdir()
                 if p.name.startswith(f".{scene.name}.") and p.name.endswith(".tmp")]
    assert not leftovers, leftovers


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    return synthesize_capture(tmp_path_factory.mktemp("rig"), "rig", resolution=256, frames=5,
                              cameras=8)


@pytest.fixture(scope="module")
def rig_scene(rig, tmp_path_factory):
    scene = tmp_path_factory.mktemp("prepared") / "scene"
    res = _invoke(rig / "videos", "-o", scene, "--instants", "2")
    assert res.exit_code == 0, (res.output, res.exception)
    return scene


def test_rig_cameras_posed_within_the_issue_bounds(rig, rig_scene):
    """Every camera registers; after a similarity alignment to the true cameras, rotations
    within 0.5 degree and centres within 1% of the scene's extent (issue 30)."""
    err = pose_errors(rig_scene, rig / "truth.json")
    assert err["cameras"] == 8
    assert err["rotation_max_deg"] <= 0.5, err
    assert err["position_max"] <= 0.01, err
    record = json.loads((rig_scene / "prepare.json").read_text())
    assert record["registered_images"] == record["sfm_images"] == 16
    assert record["dropped"] == [] and record["kind"] == "rig"
    assert set(record["seconds"]) == {"decode", "features", "matching", "mapping", "write"}
    assert not (rig_scene.parent / ".scene.prepare").exists()  # work folder gone after success


def test_rig_scene_reads_back_with_times_and_a_held_out_camera(rig, rig_scene):
    from nehad.data.dnerf import load_dnerf

    scene = load_dnerf(rig_scene, splits=("train", "test"))
    train, test = scene.frames["train"], scene.frames["test"]
    assert len(train) == 7 * 5 and len(test) == 5
    assert {Path(f.camera.name).name.split("_")[0] for f in test} == {"cam04"}  # the middle one
    assert sorted({round(f.time, 6) for f in test}) == [0.0, 0.25, 0.5, 0.75, 1.0]
    # normalised: cameras at a mean distance of 4 from the centre, z up
    centres = np.array([f.camera.centre for f in train + test])
    assert abs(np.linalg.norm(centres, axis=1).mean() - 4.0) < 1e-3
    # each camera's elevation (its view's angle below the horizon) as the truth has it
    truth = json.loads((rig / "truth.json").read_text())
    for f in test + train[::5]:
        cam = Path(f.camera.name).name.split("_")[0]
        true_back = np.asarray(truth["cameras"][cam]["camera_to_world"])[:3, 2]
        back = f.camera.camera_to_world[:3, :3] @ [0.0, 0.0, -1.0]  # OpenCV z forward
        assert back[2] == pytest.approx(true_back[2], abs=0.01)
    assert scene.initial_points is not None and len(scene.initial_points) > 100


def test_monocular_video_sampled_at_fps(tmp_path):
    """One orbiting video of 24 frames at 30 fps kept at 15 fps: 12 frames, each posed within
    issue 30's 1 degree and 2% of the extent, every 4th a test frame. The capture is the same
    bytes every run (nehad.data.synth_capture; before, its largest rotation error spread over
    0.07-1.23 degrees in nine runs) and poses within 0.51 degree (2026-11-28)."""
    cap = synthesize_capture(tmp_path / "orbit", "orbit", resolution=200, frames=24,
                             orbit_degrees=60.0)
    scene = tmp_path / "scene"
    res = _invoke(cap / "orbit.mp4", "-o", scene, "--fps", "15", "--test-every", "4")
    assert res.exit_code == 0, (res.output, res.exception)
    err = pose_errors(scene, cap / "truth.json")
    assert err["cameras"] == 12
    assert err["rotation_max_deg"] <= 1.0 and err["position_max"] <= 0.02, err
    record = json.loads((scene / "prepare.json").read_text())
    assert record["splits"] == {"train": 9, "test": 3} and record["kind"] == "monocular"
    times = [f["time"] for f in json.loads((scene / "transforms_train.json").read_text())["frames"]]
    assert times[0] == 0.0 and max(times) <= 1.0 and times == sorted(times)


def test_resume_reuses_frames_and_database(rig, tmp_path):
    """A work folder kept from an earlier run (--keep-work here; a failed run keeps it too,
    test_a_camera_that_does_not_register) is reused by --resume: no decoding or feature
    extraction again."""
    scene = tmp_path / "scene"
    res = _invoke(rig / "videos", "-o", scene, "--instants", "2", "--keep-work")
    assert res.exit_code == 0
    shutil.rmtree(scene)
    res = _invoke(rig / "videos", "-o", scene, "--instants", "2", "--resume")
    assert res.exit_code == 0, (res.output, res.exception)
    record = json.loads((scene / "prepare.json").read_text())
    assert record["seconds"]["features"] < 0.5 and record["seconds"]["decode"] < 0.5, record


def test_rig_of_image_folders(rig, tmp_path):
    """The same rig as folders of JPEG images, one per camera: the same cameras posed."""
    import cv2

    folders = tmp_path / "images"
    for video in sorted((rig / "videos").glob("*.mp4")):
        (folders / video.stem).mkdir(parents=True)
        for k, frame in enumerate(_frames_of(video)):
            cv2.imwrite(str(folders / video.stem / f"frame{k}.jpg"), frame[:, :, ::-1],
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
    scene = tmp_path / "scene"
    res = _invoke(folders, "-o", scene, "--instants", "2")
    assert res.exit_code == 0, (res.output, res.exception)
    record = json.loads((scene / "prepare.json").read_text())
    assert record["kind"] == "rig" and record["cameras"] == 8 and record["frames_per_camera"] == 5
    err = pose_errors(scene, rig / "truth.json")
    assert err["cameras"] == 8 and err["rotation_max_deg"] <= 0.5 and err["position_max"] <= 0.01


# -- bad input: one `Error:` line each, nothing left in SCENE --------------------------------


def test_nothing_found(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("x")
    _one_error(_invoke(tmp_path / "empty", "-o", tmp_path / "s"), "no video", "found, neither in it nor")
    _nothing_left(tmp_path / "s")


def _frames_of(video: Path) -> list[np.ndarray]:
    import av

    with av.open(str(video)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


def test_videos_of_different_lengths_and_rates(rig, tmp_path):
    videos = tmp_path / "videos"
    shutil.copytree(rig / "videos", videos)
    frames = _frames_of(videos / "cam03.mp4")
    encode(frames[:4], videos / "cam03.mp4", 30.0)
    _one_error(_invoke(videos, "-o", tmp_path / "s"), "cam03.mp4 (4)", "--trim")
    _nothing_left(tmp_path / "s")
    from nehad.data.capture_inputs import find_sources

    kind, sources, n = find_sources(videos, trim=True)
    assert kind == "rig" and n == 4 and len(sources) == 8
    encode(frames, videos / "cam03.mp4", 25.0)
    _one_error(_invoke(videos, "-o", tmp_path / "s", "--trim"), "cam03.mp4 (25 fps)", "rates")
    _nothing_left(tmp_path / "s")


def test_too_few_features(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    flat = [np.full((256, 256, 3), 120 + k, np.uint8) for k in range(4)]
    for c in range(4):
        encode(flat, videos / f"cam{c}.mp4", 30.0)
    _one_error(_invoke(videos, "-o", tmp_path / "s"), "too few features")
    _nothing_left(tmp_path / "s")


def test_a_camera_that_does_not_register(rig, tmp_path):
    """One camera films something else (noise): named; --min-registered goes on without it."""
    videos = tmp_path / "videos"
    shutil.copytree(rig / "videos", videos)
    rng = np.random.default_rng(0)
    noise = [np.repeat(np.repeat(rng.integers(0, 256, (64, 64, 3), np.uint8), 4, 0), 4, 1)
             for _ in range(5)]
    encode(noise, videos / "cam06.mp4", 30.0)
    _one_error(_invoke(videos, "-o", tmp_path / "s", "--instants", "2"), "failed to register",
               "cam06", "--min-registered 7")
    _nothing_left(tmp_path / "s")
    res = _invoke(videos, "-o", tmp_path / "s", "--instants", "2", "--min-registered", "7",
                  "--resume")
    assert res.exit_code == 0, (res.output, res.exception)
    record = json.loads((tmp_path / "s" / "prepare.json").read_text())
    assert record["dropped"] == [{"camera": "cam06",
                                  "reason": "not registered by structure from motion"}]
    assert "cam06" not in (tmp_path / "s" / "transforms_train.json").read_text()


def test_cameras_that_coincide(tmp_path):
    """Six cameras at one point, turned by 16 degrees each: no parallax."""
    base = orbit_camera_to_world(math.radians(-90.0), math.radians(15.0), 4.0)
    rig_ = []
    for k in range(6):
        a = math.radians(-40.0 + 16.0 * k)
        turn = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                         [0.0, 0.0, 1.0]])
        m = base.copy()
        m[:3, :3] = turn @ base[:3, :3]
        rig_.append(m)
    cap = synthesize_capture(tmp_path / "cap", "rig", resolution=200, frames=4, rig=rig_)
    _one_error(_invoke(cap / "videos", "-o", tmp_path / "s", "--instants", "2"), "no parallax")
    _nothing_left(tmp_path / "s")


def test_scene_folder_not_empty(rig, tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "keep.txt").write_text("mine")
    _one_error(_invoke(rig / "videos", "-o", tmp_path / "s"), "not an empty folder")
    assert (tmp_path / "s" / "keep.txt").read_text() == "mine"
