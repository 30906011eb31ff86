"""Videos (nehad.runtime.video and `nehad video`, issue 5): the mp4 read back with PyAV, the
OpenCV fallback, frame folders and --resume after SIGINT / SIGKILL, side by side with ground
truth, and one-line errors for bad inputs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime.distribute import SerialBackend
from nehad.runtime.images import read_image, write_image
from nehad.runtime.paths import PathError
from nehad.runtime.video import (
    MANIFEST,
    VideoError,
    VideoJob,
    encode_video,
    plan_video,
    probe_video,
    run_video,
)
from torch_blocker import blocked_torch_env
from video_model import build_tiny_export

av = pytest.importorskip("av")


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_tiny_export(tmp_path_factory)


def test_video_reads_back_with_pyav(model, tmp_path):
    onnx, _ = model
    out = tmp_path / "orbit.mp4"
    job = VideoJob(model=onnx, output=out, path="orbit", frames=24, fps=25, size=(48, 32))
    rep = run_video(job, SerialBackend(), progress=False)
    assert (rep.frames, rep.rendered, rep.skipped) == (24, 24, 0)
    info = probe_video(out)
    assert info == {"codec": "h264", "pix_fmt": "yuv420p", "fps": 25.0, "width": 48,
                    "height": 32, "frames": 24}
    assert not (tmp_path / "orbit.mp4.frames").exists()  # the work folder is removed
    assert [p.name for p in tmp_path.iterdir()] == ["orbit.mp4"]  # no temporary files left


def test_ntsc_rate_and_frame_content(model, tmp_path):
    onnx, _ = model
    out = tmp_path / "v.mp4"
    job = VideoJob(model=onnx, output=out, path="orbit", frames=6, fps=29.97, size=(32, 32),
                   frames_dir=tmp_path / "frames", crf=0)
    run_video(job, SerialBackend(), progress=False)
    assert probe_video(out)["fps"] == pytest.approx(30000 / 1001)
    # the decoded video is the frames (crf 0; yuv420p chroma subsampling and rounding aside)
    with av.open(str(out)) as c:
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    for k, img in enumerate(decoded):
        png = np.round(read_image(tmp_path / "frames" / f"frame_{k:05d}.png") * 255)
        assert np.abs(img.astype(float) - png).mean() < 6
    # frames differ from one another (the camera moves)
    assert np.abs(decoded[0].astype(float) - decoded[3]).mean() > 1


def test_opencv_fallback_when_pyav_is_missing(model, tmp_path, monkeypatch):
    import nehad.runtime.mp4 as mp4

    frames = [np.full((16, 24, 3), k / 10, np.float32) for k in range(5)]
    monkeypatch.setattr(mp4, "_have_pyav", lambda: False)
    used = encode_video(frames, tmp_path / "cv.mp4", fps=12)
    assert used == "mp4v (OpenCV)"
    info = probe_video(tmp_path / "cv.mp4")
    assert (info["codec"], info["frames"], info["width"], info["height"]) == ("mpeg4", 5, 24, 16)
    assert info["fps"] == pytest.approx(12)


def test_frames_dir_exr_and_resume_refuses_other_settings(model, tmp_path):
    onnx, _ = model
    fd = tmp_path / "seq"
    job = VideoJob(model=onnx, output=None, frames_dir=fd, frames=4, size=(16, 16),
                   frame_format="exr")
    rep = run_video(job, SerialBackend(), progress=False)
    assert rep.kept_frames and sorted(p.name for p in fd.iterdir()) == sorted([
        MANIFEST, "frame_00000.exr", "frame_00001.exr", "frame_00002.exr", "frame_00003.exr"])
    assert read_image(fd / "frame_00002.exr").dtype == np.float32
    manifest = json.loads((fd / MANIFEST).read_text())
    assert manifest["frames"] == 4 and manifest["width"] == 16
    again = run_video(job, SerialBackend(), resume=True, progress=False)
    assert (again.rendered, again.skipped) == (0, 4)
    other = VideoJob(model=onnx, output=None, frames_dir=fd, frames=4, size=(16, 16),
                     frame_format="exr", time="0.5")
    with pytest.raises(VideoError, match="plan_sha256 differ"):
        run_video(other, SerialBackend(), resume=True, progress=False)
    # without --resume the old frames are replaced
    assert run_video(other, SerialBackend(), progress=False).rendered == 4


def test_side_by_side_with_ground_truth(model, tmp_path):
    onnx, scene = model
    fd = tmp_path / "sbs"
    job = VideoJob(model=onnx, output=tmp_path / "sbs.mp4", path=f"{scene}:test",
                   side_by_side=True, frames_dir=fd)
    rep = run_video(job, SerialBackend(), progress=False)
    test = json.loads((scene / "transforms_test.json").read_text())["frames"]
    assert rep.frames == len(test) == 2 and (rep.width, rep.height) == (64, 32)
    for k, fr in enumerate(test):
        img = read_image(fd / f"frame_{k:05d}.png")
        gt = read_image(scene / (fr["file_path"] + ".png"))
        over_white = gt[:, :, :3] + (1 - gt[:, :, 3:])  # the model's background is white
        assert np.abs(img[:, 32:] - over_white).max() <= 1 / 255 + 1e-6
        assert np.abs(img[:, :32] - img[:, 32:]).mean() < 0.2  # the render resembles it
    with pytest.raises(VideoError, match="needs a dataset path"):
        plan_video(VideoJob(model=onnx, output=tmp_path / "x.mp4", side_by_side=True))


def test_static_ply_video(tmp_path):
    from nehad.runtime.gaussians import GaussianCloud
    from nehad.runtime.ply import write_gaussian_ply

    rng = np.random.default_rng(0)
    n = 50
    cloud = GaussianCloud(rng.uniform(-0.5, 0.5, (n, 3)), np.full((n, 3), 0.05),
                          np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.8),
                          rng.uniform(0, 1, (n, 1, 3)))
    write_gaussian_ply(tmp_path / "s.ply", cloud)
    job = VideoJob(model=tmp_path / "s.ply", output=tmp_path / "s.mp4",
                   path="orbit:centre=[0,0,0],radius=3,fov=40", frames=4, size=(32, 32),
                   frames_dir=tmp_path / "f")
    run_video(job, SerialBackend(), progress=False)
    img = read_image(tmp_path / "f" / "frame_00000.png")
    assert img.max() > 0.2 and img[0, 0].max() == 0  # something drawn, black background


@pytest.mark.parametrize("args, message", [
    (["--path", "orbit:radus=2"], "Error: --path orbit:radus=2: unknown key 'radus'"),
    (["--path", "nowhere:test"], "Error: --path nowhere:test: not a path kind"),
    (["--time", "0:3"], "Error: --time 0:3: time 3 is outside the trained time range"),
    (["--fps", "30", "--frames-dir", "no/such/dir"], "Error: --frames-dir no/such/dir: parent"),
])
def test_cli_bad_inputs_are_one_line_errors(model, tmp_path, args, message):
    onnx, _ = model
    out = tmp_path / "x.mp4"
    res = CliRunner().invoke(main, ["video", str(onnx), "-o", str(out), "--workers", "1",
                                    "--quiet", *args])
    assert res.exit_code == 1, res.output
    assert res.output.startswith(message), res.output
    assert res.output.count("\n") == 1 and "Traceback" not in res.output
    assert list(tmp_path.iterdir()) == []


def test_cli_option_conflicts(model, tmp_path):
    onnx, _ = model
    res = CliRunner().invoke(main, ["video", str(onnx), "-o", str(tmp_path / "x.mp4"),
                                    "--workers", "2", "--scheduler", "tcp://h:8786"])
    assert res.exit_code == 2 and "exclude each other" in res.output
    res = CliRunner().invoke(main, ["video", str(onnx)])
    assert res.exit_code == 1 and "give an output video" in res.output


def _start(args, env):
    return subprocess.Popen([sys.executable, "-m", "nehad.cli.main", "video", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)


def _wait_for_frames(folder: Path, count: int, proc, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if folder.is_dir() and len(list(folder.glob("frame_*.png"))) >= count:
            return
        if proc.poll() is not None:
            raise AssertionError(f"the video finished before it could be interrupted: "
                                 f"{proc.communicate()}")
        time.sleep(0.01)
    raise AssertionError("no frames appeared")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
def test_interrupted_video_resumes_with_only_the_missing_frames(model, tmp_path, sig):
    """Run `nehad video` (torch blocked), interrupt it once a few frames exist, re-run with
    --resume: the frames already there are kept untouched and only the others are rendered."""
    onnx, _ = model
    env = blocked_torch_env(tmp_path)
    env.update(NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out, folder = tmp_path / "v.mp4", tmp_path / "v.mp4.frames"
    n = 150
    args = [str(onnx), "-o", str(out), "--frames", str(n), "--size", "64x64", "--workers", "1",
            "--quiet"]
    proc = _start(args, env)
    _wait_for_frames(folder, 3, proc)
    os.killpg(proc.pid, sig)
    stdout, stderr = proc.communicate(timeout=60)
    if sig == signal.SIGINT:
        assert proc.returncode == 130, stderr
        assert stderr.startswith("interrupted: ") and "--resume" in stderr
        assert "Traceback" not in stderr
    else:
        assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    kept = {p.name: p.stat().st_mtime_ns for p in folder.glob("frame_*.png")}
    assert 3 <= len(kept) < n
    proc = _start([*args, "--resume"], env)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    assert f"rendered {n - len(kept)} frames" in stdout
    assert f"{len(kept)} already there kept" in stdout
    assert probe_video(out)["frames"] == n
    assert not folder.exists()


def test_resumed_frames_are_not_rewritten(model, tmp_path):
    """--resume keeps the existing frame files as they are (same inode and time stamp)."""
    onnx, _ = model
    fd = tmp_path / "f"
    job = VideoJob(model=onnx, output=tmp_path / "v.mp4", frames=6, size=(16, 16), frames_dir=fd)
    run_video(job, SerialBackend(), progress=False)
    (fd / "frame_00002.png").unlink()
    (fd / "frame_00004.png").unlink()
    (fd / ".frame_00004.abc.tmp.png").write_bytes(b"half")  # left by a killed write
    before = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in fd.glob("frame_*")}
    seen = []
    rep = run_video(job, SerialBackend(), resume=True, progress=False,
                    on_result=lambda r: seen.append(r.index))
    assert sorted(seen) == [2, 4] and (rep.rendered, rep.skipped) == (2, 4)
    after = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in fd.glob("frame_*")}
    assert all(after[k] == v for k, v in before.items())
    assert not list(fd.glob(".*tmp*"))


def test_encode_checks_frame_sizes(tmp_path):
    frames = [np.zeros((16, 16, 3)), np.zeros((18, 16, 3))]
    with pytest.raises(VideoError, match="frame 1 is 16x18"):
        encode_video(frames, tmp_path / "x.mp4")
    assert list(tmp_path.iterdir()) == []  # atomic: nothing left behind
    # an odd size is padded to even by one repeated row (runtime/mp4.py), the one rule
    write_image(tmp_path / "a.png", np.zeros((15, 16, 3)))
    encode_video([tmp_path / "a.png"], tmp_path / "x.mp4")
    assert (probe_video(tmp_path / "x.mp4")["width"], probe_video(tmp_path / "x.mp4")["height"]) \
        == (16, 16)


def test_path_errors_name_the_option(model, tmp_path):
    onnx, _ = model
    # the runtime names the input as a placeholder; the CLI shows its option, a jobs.yaml its key
    from nehad.cli.errors import OPTION_NAMES

    with pytest.raises(PathError, match="^path orbit:from=nothere: from=nothere") as e:
        plan_video(VideoJob(model=onnx, output=tmp_path / "x.mp4", path="orbit:from=nothere"))
    assert e.value.message(OPTION_NAMES).startswith("--path orbit:from=nothere: from=nothere")
    assert "--" not in str(e.value)
    with pytest.raises(PathError, match="^path orbit:turns=x"):
        plan_video(VideoJob(model=onnx, output=tmp_path / "x.mp4", path="orbit:turns=x",
                            name="job"))


def test_video_defaults_have_one_owner():
    """VideoJob owns fps, crf and the frame format; the CLI's help states them and passes
    nothing when an option is left out."""
    import re

    from nehad.cli.video import video as video_command
    from nehad.runtime.video import VideoJob

    job = VideoJob(model=Path("m.onnx"))
    helps = {p.name: getattr(p, "help", None) for p in video_command.params}
    assert re.search(rf"\[default: {job.fps:g}\]", helps["fps"])
    assert re.search(rf"\[default: {job.crf}\]", helps["crf"])
    assert re.search(rf"\[default: {job.frame_format}\]", helps["frame_format"])
    assert {p.name: p.default for p in video_command.params}["fps"] is None
