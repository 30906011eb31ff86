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


def test_idle_cores_is_a_share_of_the_machine():
    idle = idle_cores(sample_seconds=0.05)
    assert 0.0 <= idle <= (os.cpu_count() or 1) + 1e-6
