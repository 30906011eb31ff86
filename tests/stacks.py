"""Subprocesses of the tests that may hang: before one is killed, it prints its stacks (issue 26).

The `nehad` executable registers ``faulthandler`` for SIGUSR1 (cli/main.py): every thread's
Python stack goes to its stderr and it goes on. :func:`run` is ``subprocess.run`` for such a
process: when the timeout passes, it sends SIGUSR1, waits a moment, kills the process and fails
the test showing where it was, so a hang explains itself instead of ending as a bare timeout.
:data:`DUMP_ON_USR1` is the line a ``python -c`` script puts first to get the same.
"""

from __future__ import annotations

import signal
import subprocess
import time

import pytest

DUMP_ON_USR1 = ("import faulthandler, signal; "
                "faulthandler.register(signal.SIGUSR1, all_threads=True)\n")


def kill_with_stacks(proc: subprocess.Popen, why: str) -> None:
    """SIGUSR1 (stacks to stderr), then SIGKILL; fail the test with `why` and the stacks."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2)
        proc.kill()
    try:
        _, err = proc.communicate(timeout=30)
    except (subprocess.TimeoutExpired, ValueError):
        err = ""
    pytest.fail(f"{why}; its stacks:\n{(err or '')[-6000:]}")


def run(args, timeout: float, **kw) -> subprocess.CompletedProcess:
    """subprocess.run(args, capture_output=True, text=True, timeout=timeout, **kw), with the
    stacks of a process that does not finish in time (module doc)."""
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill_with_stacks(proc, f"{' '.join(map(str, args[:4]))} ... still running after "
                               f"{timeout:g} s")
    return subprocess.CompletedProcess(args, proc.returncode, out, err)
