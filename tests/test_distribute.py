"""Frames as tasks (nehad.runtime.distribute, issue 5): the per-process model cache, skipping
frames already written, a local pool and a real Dask cluster (`dask scheduler` + two `dask worker`
processes started here, torch blocked in them) giving frames bitwise identical to one process,
and runs that survive a worker killed mid-run."""

from __future__ import annotations

import contextlib
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
from nehad.runtime.distribute import (
    DaskBackend,
    FrameTask,
    PoolBackend,
    RenderError,
    SerialBackend,
    cached_scene,
    render_frame_task,
)
from nehad.runtime.images import read_image
from nehad.runtime.video import VideoJob, plan_video, probe_video, run_video
from torch_blocker import blocked_torch_env
from video_model import build_tiny_export

N = 24


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_tiny_export(tmp_path_factory)  # made once per session


@pytest.fixture(scope="module")
def reference(model, tmp_path_factory):
    """The 24-frame orbit rendered in this process: {frame name: pixels}."""
    onnx, _ = model
    fd = tmp_path_factory.mktemp("reference")
    run_video(VideoJob(model=onnx, frames_dir=fd, frames=N, size=(40, 32)), SerialBackend(),
              progress=False)
    return {p.name: read_image(p) for p in sorted(fd.glob("frame_*.png"))}


def same_frames(folder: Path, reference: dict) -> bool:
    names = sorted(p.name for p in folder.glob("frame_*.png"))
    return names == sorted(reference) and all(
        np.array_equal(read_image(folder / n), reference[n]) for n in names)


def task(model, folder, index=0, **kw):
    plan = plan_video(VideoJob(model=model, frames_dir=folder, frames=N, size=(40, 32)))
    t = plan.tasks[index]
    return FrameTask(**{**t.__dict__, "output": str(Path(folder) / Path(t.output).name), **kw})


def test_frame_task_writes_skips_and_names_missing_inputs(model, tmp_path):
    onnx, _ = model
    t = task(onnx, tmp_path, 3)
    r = render_frame_task(t)
    assert (r.index, r.path, r.skipped) == (3, t.output, False) and os.path.isfile(r.path)
    assert render_frame_task(t).skipped  # a re-run skips what exists
    assert not render_frame_task(FrameTask(**{**t.__dict__, "skip_existing": False})).skipped
    with pytest.raises(RenderError, match="frame 3: the folder .* does not exist on"):
        render_frame_task(task(onnx, tmp_path / "nowhere", 3))
    with pytest.raises(RenderError, match="frame 3: the model .* does not exist on"):
        render_frame_task(FrameTask(**{**t.__dict__, "model": str(tmp_path / "gone.onnx"),
                                        "skip_existing": False}))


def test_threads_per_frame(monkeypatch):
    import socket

    from nehad.runtime.distribute import _task_threads

    t = FrameTask("m.onnx", 0, None, 0.0, (0, 0, 0), "f.png")
    monkeypatch.delenv("NEHAD_THREADS", raising=False)
    assert _task_threads(t) is None
    here = FrameTask(**{**t.__dict__, "host_threads": ((socket.gethostname(), 3), ("x", 9))})
    assert _task_threads(here) == 3
    monkeypatch.setenv("NEHAD_THREADS", "2")  # set on a worker, it wins over the share
    assert _task_threads(here) == 2
    assert _task_threads(FrameTask(**{**here.__dict__, "threads": 5})) == 5
    monkeypatch.setenv("NEHAD_THREADS", "two")
    with pytest.raises(RenderError, match="NEHAD_THREADS='two'"):
        _task_threads(t)


def test_model_is_loaded_once_per_process(model, tmp_path):
    onnx, _ = model
    copy = tmp_path / "m.onnx"
    copy.write_bytes(onnx.read_bytes())
    a = cached_scene(copy, 1)
    assert cached_scene(copy, 1) is a
    assert cached_scene(copy, 2) is not a  # another thread count is another session
    os.utime(copy, ns=(1, 1))  # a rewritten file is loaded again
    assert cached_scene(copy, 1) is not a


def test_local_pool_is_bitwise_identical_and_survives_a_killed_worker(model, reference, tmp_path):
    onnx, _ = model
    killed = []
    with PoolBackend(2) as pool:
        def on_result(r):
            if not killed:
                pids = pool.processes()
                if len(pids) == 2:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])

        rep = run_video(VideoJob(model=onnx, output=tmp_path / "p.mp4", frames=N, size=(40, 32),
                                 frames_dir=tmp_path / "f"), pool, progress=False,
                        on_result=on_result)
        assert killed and pool.restarts >= 1
    assert rep.rendered == N
    assert same_frames(tmp_path / "f", reference)
    assert probe_video(tmp_path / "p.mp4")["frames"] == N


# ---------------------------------------------------------------------------------------------
# a Dask cluster of two workers, started with the commands README.md gives


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    pytest.importorskip("distributed")
    root = tmp_path_factory.mktemp("dask")
    env = blocked_torch_env(root)  # the workers render without torch
    env.update(NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", NEHAD_THREADS="1")
    sched_file = root / "scheduler.json"
    procs = []

    def start(*args):
        log = open(root / f"log{len(procs)}.txt", "w")
        p = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=log,
                             stderr=subprocess.STDOUT, env=env, cwd=root)
        procs.append(p)
        return p

    try:
        start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
              "--scheduler-file", str(sched_file))
        end = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < end:
            time.sleep(0.05)
        address = json.loads(sched_file.read_text())["address"]
        workers = [start("worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                         "--name", f"w{k}") for k in range(2)]
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=60)
            # warm both workers up (model, Numba kernels), so that both draw frames at once
            onnx, _ = build_tiny_export(tmp_path_factory)
            (root / "warm").mkdir()
            c.run(render_frame_task, task(onnx, root / "warm", 0))
        yield address, workers
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_dask_cluster_renders_identical_frames_and_survives_a_killed_worker(
        model, reference, cluster, tmp_path):
    """24 frames on two Dask workers; one is SIGKILLed after a few frames; the scheduler gives
    its frames to the other; the video is complete and every frame equals the single-process
    render bit for bit."""
    onnx, _ = model
    address, workers = cluster
    victim = workers[0]
    seen, killed_at = [], []

    def on_result(r):
        seen.append(r)
        drew = {int(x.worker.split(":")[1]) for x in seen}
        if not killed_at and drew == {w.pid for w in workers} and len(seen) >= 3:
            victim.send_signal(signal.SIGKILL)  # both have drawn frames: kill one mid-run
            victim.wait(timeout=10)
            killed_at.append(len(seen))

    with DaskBackend(address) as backend:
        rep = run_video(VideoJob(model=onnx, output=tmp_path / "d.mp4", frames=N, size=(40, 32),
                                 frames_dir=tmp_path / "f"), backend, progress=False,
                        on_result=on_result)
        assert victim.returncode == -signal.SIGKILL
        assert backend.workers == 1
    assert rep.rendered == N and len(seen) == N
    assert same_frames(tmp_path / "f", reference)
    info = probe_video(tmp_path / "d.mp4")
    assert (info["frames"], info["codec"], info["pix_fmt"]) == (N, "h264", "yuv420p")
    assert killed_at[0] <= N - 4  # at least 4 frames were still to come when it died


def test_dask_via_the_cli_and_rerun_skips_existing_frames(model, reference, cluster, tmp_path):
    onnx, _ = model
    address, _ = cluster
    args = ["video", str(onnx), "-o", str(tmp_path / "c.mp4"), "--frames", str(N), "--size",
            "40x32", "--frames-dir", str(tmp_path / "f"), "--scheduler", address, "--quiet"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert f"rendered {N} frames" in res.output and f"Dask at {address}" in res.output
    assert same_frames(tmp_path / "f", reference)
    res = CliRunner().invoke(main, [*args, "--resume"])
    assert res.exit_code == 0 and "rendered 0 frames" in res.output, res.output


def test_dask_task_errors_name_the_frame(model, cluster, tmp_path):
    onnx, _ = model
    address, _ = cluster
    with DaskBackend(address) as backend:
        with pytest.raises(RenderError, match="^frame 5: the folder .*missing does not exist on"):
            backend.run([task(onnx, tmp_path / "missing", 5)])


def test_unreachable_scheduler_is_a_one_line_error():
    pytest.importorskip("distributed")
    backend = DaskBackend("tcp://127.0.0.1:9", scheduler_timeout=1)
    with pytest.raises(RenderError, match="cannot reach the Dask scheduler at tcp://127.0.0.1:9"):
        backend.run([])


@pytest.fixture
def not_a_scheduler():
    """tcp://127.0.0.1:PORT of a server that answers every connection with bytes that are no
    Dask message."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))

    def answer():
        with contextlib.suppress(OSError):
            while True:
                conn, _ = server.accept()
                with conn:
                    conn.sendall(b"\xff" * 64)

    threading.Thread(target=answer, daemon=True).start()
    yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    server.close()


@pytest.mark.parametrize("kind", ["unknown scheme", "not a scheduler"])
def test_a_bad_scheduler_fails_at_once_without_a_traceback(model, not_a_scheduler, tmp_path,
                                                           kind):
    """--scheduler http://x (a scheme Dask does not know) and an address where something else
    answers: one Error line within seconds. Before, the half-made Dask client's __del__ waited
    60 s at exit for a stopped loop and printed a traceback."""
    pytest.importorskip("distributed")
    onnx, _ = model
    address = {"unknown scheme": "http://x", "not a scheduler": not_a_scheduler}[kind]
    start = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "nehad.cli.main", "video", str(onnx), "-o", str(tmp_path / "v.mp4"),
         "--frames", "2", "--size", "16x16", "--scheduler", address],
        capture_output=True, text=True, timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"})
    assert proc.returncode == 1, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: ") and address in lines[0], \
        proc.stderr
    assert time.monotonic() - start < 30
    assert list(tmp_path.iterdir()) == []
