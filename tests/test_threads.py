"""The thread counts `nehad` chooses before torch and numba load (nehad/cli/threads.py,
docs/training.md#threads)."""

from __future__ import annotations

import os

import pytest

from nehad.cli.threads import VARIABLES, apply_thread_defaults, choose_threads, idle_cores


@pytest.mark.parametrize("idle, usable, expected", [
    (2.0, 2, 2),    # an idle 2-core machine: both cores
    (1.8, 2, 2),    # background noise does not cost a core
    (1.0, 2, 1),    # one core taken by another process: one thread
    (0.6, 2, 1),
    (0.0, 2, 1),    # everything busy: still one thread
    (7.9, 4, 4),    # never more than the usable cores
    (5.74, 8, 5),   # a core counts when at least 3/4 of it is free
    (5.76, 8, 6),
])
def test_threads_follow_the_idle_cores(idle, usable, expected):
    assert choose_threads(idle, usable) == expected


def test_a_busy_machine_gets_one_thread_for_every_library():
    env: dict[str, str] = {}
    applied = apply_thread_defaults(env, idle=0.4)
    assert applied == {name: "1" for name in VARIABLES}
    assert env == applied


@pytest.mark.parametrize("user", ["OMP_NUM_THREADS", "NUMBA_NUM_THREADS"])
def test_the_users_choice_wins(user):
    env = {user: "3", "MKL_NUM_THREADS": "2"}
    assert apply_thread_defaults(env, idle=0.0) == {}
    assert env == {user: "3", "MKL_NUM_THREADS": "2"}


def test_a_set_mkl_count_is_kept():
    env = {"MKL_NUM_THREADS": "2"}
    applied = apply_thread_defaults(env, idle=0.0)
    assert "MKL_NUM_THREADS" not in applied and env["MKL_NUM_THREADS"] == "2"
    assert env["OMP_NUM_THREADS"] == env["NUMBA_NUM_THREADS"] == "1"


def test_idle_cores_reads_the_idle_share_between_two_samples(monkeypatch):
    """idle_cores = cores x (idle + iowait ticks) / all ticks between two /proc/stat readings,
    and the load average where there is no /proc/stat."""
    from nehad.cli import threads as ct

    readings = iter([(100, 400), (150, 600)])  # (idle + iowait, all) ticks: 50 of 200 idle
    monkeypatch.setattr(ct, "cpu_ticks", lambda: next(readings))
    monkeypatch.setattr(ct.os, "cpu_count", lambda: 4)
    assert idle_cores(sample_seconds=0.0) == pytest.approx(1.0)
    monkeypatch.setattr(ct, "cpu_ticks", lambda: None)
    monkeypatch.setattr(ct.os, "getloadavg", lambda: (2.5, 0.0, 0.0))
    assert idle_cores(sample_seconds=0.0) == pytest.approx(1.5)
    monkeypatch.setattr(ct.os, "getloadavg", lambda: (9.0, 0.0, 0.0))
    assert idle_cores(sample_seconds=0.0) == 0.0  # more load than cores: none idle


# --- the rasterizer's thread count while frames are drawn (nehad/runtime/threads.py) ---

from nehad.runtime import threads as rt  # noqa: E402


@pytest.mark.parametrize("others, usable, ceiling, expected", [
    (0.0, 2, 2, 2),   # nobody else: every thread the process started with
    (0.2, 2, 2, 2),   # background noise does not cost a thread
    (0.35, 2, 2, 1),  # a spinning process sharing a core with our threads gets 1/3 to 1/2 of it
    (0.5, 2, 2, 1),
    (1.0, 2, 2, 1),   # ... and once we yield the core it takes all of it: stay at one
    (3.0, 2, 2, 1),   # never below one
    (1.0, 8, 4, 4),   # never above what the process started with
    (5.4, 8, 8, 2),
])
def test_frame_threads_leave_the_cores_others_use(others, usable, ceiling, expected):
    assert rt.threads_for(others, usable, ceiling) == expected


def test_governor_samples_the_machine_minus_this_process(monkeypatch):
    """Other processes' CPU = the machine's busy seconds minus this process's, per wall
    second, re-sampled only every SAMPLE_SECONDS."""
    clock = {"wall": 100.0, "busy": 1000.0, "own": 10.0}
    monkeypatch.setattr(rt.time, "monotonic", lambda: clock["wall"])
    monkeypatch.setattr(rt, "_machine_busy_seconds", lambda: clock["busy"])
    monkeypatch.setattr(rt, "_own_seconds", lambda: clock["own"])
    gov = rt._Governor()
    assert gov.decide(2, 2) == 2  # no interval yet: the ceiling
    # 1 s: the machine spent 2 CPU seconds, we spent 1.2 -> others used 0.8 of a core
    clock.update(wall=101.0, busy=1002.0, own=11.2)
    assert gov.decide(2, 2) == 1
    # within SAMPLE_SECONDS nothing is re-read, even if the load is gone
    clock.update(wall=101.1, busy=1002.1, own=11.3)
    assert gov.decide(2, 2) == 1
    # the other process has ended: 1 s in which only we ran
    clock.update(wall=102.2, busy=1003.2, own=12.4)
    assert gov.decide(2, 2) == 2
    # no /proc/stat: the ceiling
    monkeypatch.setattr(rt, "_machine_busy_seconds", lambda: None)
    clock.update(wall=103.0)
    assert gov.decide(2, 2) == 2


def test_frame_threads_never_exceed_what_the_caller_set(monkeypatch):
    """A count the caller set with numba.set_num_threads is the ceiling: an idle machine does
    not raise it."""
    import numba

    import threading

    monkeypatch.setattr(rt.time, "monotonic", lambda: 0.0)
    monkeypatch.setattr(rt, "_GOVERNOR", rt._Governor())
    monkeypatch.setattr(rt, "_THREAD", threading.local())  # no earlier frame in this thread
    try:
        numba.set_num_threads(1)
        assert rt.frame_threads() == 1 == numba.get_num_threads()
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)  # the caller raises it again
        assert rt.frame_threads() == numba.config.NUMBA_NUM_THREADS
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def test_frame_threads_can_be_turned_off(monkeypatch):
    import numba

    numba.set_num_threads(1)
    monkeypatch.setenv("NEHAD_ADAPT_THREADS", "0")
    assert rt.frame_threads() == 1 == numba.get_num_threads()
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


@pytest.mark.skipif(rt.usable_cores() < 2 or not os.path.exists("/proc/stat"),
                    reason="needs 2 cores and /proc/stat")
def test_a_spinning_process_takes_a_thread_away():
    """With a process spinning on a core and this one idle, the next frame gets at most the
    usable cores minus one (real /proc/stat, real process)."""
    import subprocess
    import sys
    import time

    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        gov = rt._Governor()
        gov.decide(64, rt.usable_cores())
        time.sleep(1.0)
        assert gov.decide(64, rt.usable_cores()) <= max(1, rt.usable_cores() - 1)
    finally:
        spinner.kill()


def test_an_onnx_scene_lets_idle_openmp_workers_sleep(tmp_path):
    """Opening an exported model sets OMP_WAIT_POLICY=PASSIVE before numba's threads start
    (runtime/threads.py prefer_passive_openmp); the user's setting wins, and once numba's
    threads run the policy is left alone (OpenMP has read it)."""
    import subprocess
    import sys

    from test_runtime_onnx import fake_model

    path = fake_model(tmp_path / "m.onnx")
    script = ("import os, sys\n"
              "from nehad.runtime.scene import open_scene\n"
              "if sys.argv[1] == 'late':  # numba's threads started first\n"
              "    from numba.np.ufunc import parallel\n"
              "    parallel._launch_threads()\n"
              "open_scene(sys.argv[2])\n"
              "print(os.environ.get('OMP_WAIT_POLICY'))\n")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}

    def policy(mode, **extra):
        out = subprocess.run([sys.executable, "-c", script, mode, str(path)], env={**env, **extra},
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    assert policy("early") == "PASSIVE"
    assert policy("early", OMP_WAIT_POLICY="ACTIVE") == "ACTIVE"
    assert policy("late") == "None"
