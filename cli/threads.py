"""Thread counts the `nehad` command chooses before torch or numba load (docs/training.md#threads).

torch's CPU wheel and numba each bring an OpenMP runtime with one worker per core, whose idle
workers spin before they sleep. In one process that alternates torch (the field, the loss) and
numba (the rasterizer) this is the fastest setting on an idle machine, and it collapses when
another process wants the cores: every parallel region then waits for a worker the scheduler
has parked. Issue 13 measured a demo at 23.8 min that way against 2.8 min with one thread each.
``bench/threads.py`` measured the alternatives (docs/training.md#threads): one thread for both
libraries is never far from the best and does not slow down on a busy machine, while
``OMP_WAIT_POLICY=PASSIVE`` (workers sleep at once) was slower than one thread both idle and busy.

So the command counts the cores that are idle when it starts (CPU time over a short sample of
``/proc/stat``) and gives torch and numba that many threads: all cores on an idle machine, one
thread when the cores are taken. It only fills in what the user has not set:
``OMP_NUM_THREADS`` or ``NUMBA_NUM_THREADS`` in the environment wins. The variables are read
when the runtimes load, so this runs before any command imports torch or numba.
"""

from __future__ import annotations

import math
import os
import time

from nehad.runtime.threads import cpu_ticks, usable_cores

#: the variables the choice writes (bench/threads.py removes them for its `library` row)
VARIABLES = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS")


def idle_cores(sample_seconds: float = 0.15) -> float:
    """How many of the machine's cores were idle over a short sample (falls back to the load
    average where /proc/stat is missing)."""
    cores = os.cpu_count() or 1
    first = cpu_ticks()
    if first is not None:
        time.sleep(sample_seconds)
        second = cpu_ticks()
        if second is not None and second[1] > first[1]:
            return cores * (second[0] - first[0]) / (second[1] - first[1])
    try:
        return max(0.0, cores - os.getloadavg()[0])
    except OSError:
        return float(cores)


def choose_threads(idle: float, usable: int) -> int:
    """Threads for an idle-core count: the idle cores (a core counts when at least 3/4 of it
    is free), at least 1, at most the usable cores."""
    return max(1, min(usable, math.floor(idle + 0.25)))


def apply_thread_defaults(environ=os.environ, idle: float | None = None) -> dict[str, str]:
    """Set the thread variables the user has not set; return the ones set (empty when the user
    chose, by setting ``OMP_NUM_THREADS`` or ``NUMBA_NUM_THREADS``)."""
    if "OMP_NUM_THREADS" in environ or "NUMBA_NUM_THREADS" in environ:
        return {}
    usable = usable_cores()
    threads = choose_threads(idle_cores() if idle is None else idle, usable)
    applied = {name: str(threads) for name in VARIABLES if name not in environ}
    environ.update(applied)
    return applied
