"""Rasterizer threads that follow the machine's load while frames are drawn (docs/performance.md#threads).

The rasterizer splits each frame's stages between its threads in equal shares (numba's OpenMP
layer schedules parallel loops statically). When another process takes a core, the thread
sharing that core runs at about half speed and the frame waits for its share: on this 2-core
machine a 100k/800x800 frame took 100.9 ms with 2 threads beside a busy loop where one thread
took 84.6 ms (docs/performance.md#threads). `nehad` chooses its thread count from the idle
cores when it starts (cli/threads.py), but a video or a batch runs for minutes and the load
changes under it.

So before each frame the runtime asks `frame_threads()`: at most every `SAMPLE_SECONDS` it reads
how much CPU the machine spent (/proc/stat) minus what this process spent (os.times) over the
last interval: the cores other processes used. It draws with the usable cores minus those
(rounded up from 0.3: a CPU-bound process that shares a core with this one's threads obtains
only 1/3 to 1/2 of it, and counts as one), at least one, and at most the count the calling
thread had at its first frame or last set itself with numba.set_num_threads (it cannot tell
when the caller sets exactly the count this module chose last). Where /proc/stat is missing
that count stays. NEHAD_ADAPT_THREADS=0 turns this off; a caller that fixes the count
(`--threads`) passes adapt_threads=False.
"""

from __future__ import annotations

import math
import os
import threading
import time

SAMPLE_SECONDS = 0.2
_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_ticks() -> tuple[float, float] | None:
    """(idle + iowait, all) clock ticks of all CPUs since boot from /proc/stat (steal counted as
    busy), or None where there is none. The one reader of the machine's load (the CLI's thread
    defaults use it too)."""
    try:
        with open("/proc/stat") as f:
            fields = [float(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    if len(fields) < 8:
        return None
    return fields[3] + fields[4], sum(fields)


def _machine_busy_seconds() -> float | None:
    """CPU seconds all cores spent outside idle/iowait since boot (steal included), or None."""
    ticks = cpu_ticks()
    return None if ticks is None else (ticks[1] - ticks[0]) / _CLOCK_TICKS


def _own_seconds() -> float:
    t = os.times()
    return t.user + t.system


def threads_for(others: float, usable: int, ceiling: int) -> int:
    """Threads when other processes use `others` cores: the usable cores minus those (0.3 of
    a core or more counts as one), between 1 and `ceiling`."""
    free = usable - math.floor(others + 0.7)
    return max(1, min(ceiling, free))


class _Governor:
    def __init__(self):
        self.lock = threading.Lock()
        self.sample = None  # (wall, machine busy, own) at the last decision
        self.threads = None

    def decide(self, ceiling: int, usable: int) -> int:
        with self.lock:
            now = time.monotonic()
            if self.sample is not None and now - self.sample[0] < SAMPLE_SECONDS:
                return min(self.threads, ceiling)
            busy = _machine_busy_seconds()
            own = _own_seconds()
            if busy is None:
                self.threads = ceiling
            elif self.sample is None:
                self.threads = ceiling if self.threads is None else self.threads
            else:
                wall = now - self.sample[0]
                others = max(0.0, (busy - self.sample[1]) - (own - self.sample[2])) / wall
                self.threads = threads_for(others, usable, ceiling)
            self.sample = (now, busy if busy is not None else 0.0, own)
            return min(self.threads, ceiling)


_GOVERNOR = _Governor()
_THREAD = threading.local()  # per calling thread: its ceiling and the count set for it last


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def frame_threads() -> int:
    """Set numba's thread count (for the calling thread) for the next frame from the machine's
    current load, and return it (module doc). Returns numba's count unchanged when turned off."""
    import numba

    current = numba.get_num_threads()
    if os.environ.get("NEHAD_ADAPT_THREADS", "1") == "0":
        return current
    if getattr(_THREAD, "last_set", None) != current:  # first frame, or the caller set a count
        _THREAD.ceiling = current
    if _THREAD.ceiling <= 1:
        _THREAD.last_set = current
        return current
    threads = _GOVERNOR.decide(_THREAD.ceiling, usable_cores())
    numba.set_num_threads(threads)
    _THREAD.last_set = threads
    return threads


def prefer_passive_openmp(environ=os.environ) -> bool:
    """Let the rasterizer's idle OpenMP workers sleep at once (OMP_WAIT_POLICY=PASSIVE) in a
    process that alternates onnxruntime's deformation with the rasterizer, unless the user set
    the policy or numba's threads have started (OpenMP reads it once, when numba's threading
    layer loads). By default they spin after each parallel stage and take a core from
    onnxruntime's pool for the next frame's deformation: a 15k-Gaussian scene8 model's
    deformation took 11.3-15.4 ms per 800x800 frame that way and 9.5-10.4 ms with PASSIVE (its
    time alone), while the rasterizer's frames alone were equal either way (docs/performance.md,
    "Frames in a sequence"). Returns whether the policy is now PASSIVE."""
    if "OMP_WAIT_POLICY" in environ:
        return environ["OMP_WAIT_POLICY"].upper() == "PASSIVE"
    try:
        from numba.np.ufunc import parallel
    except ImportError:
        return False
    if getattr(parallel, "_is_initialized", True):
        return False
    environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True
