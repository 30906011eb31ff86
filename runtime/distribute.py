"""Frames as independent tasks: one process, a local pool, or a Dask cluster (docs/design.md section 10).

Every frame of a video or batch is a :class:`FrameTask`: a model file, a camera, a time and the
file to write. :func:`render_frame_task` renders one and returns a :class:`FrameResult` (with the
path written); it is the same function in every mode, so the frames are bitwise identical
whichever backend drew them.

Backends (:func:`make_backend`):

* :class:`SerialBackend` -- this process (``--workers 1``).
* :class:`PoolBackend` -- a local pool of N spawned processes (``--workers N``), each drawing
  frames with cores/N threads. A worker that dies (killed, out of memory) breaks the pool; the
  unfinished frames are re-run on a new pool, up to :data:`MAX_ATTEMPTS` pools in all.
* :class:`DaskBackend` -- a Dask distributed cluster (``--scheduler tcp://HOST:8786``, started
  with ``dask scheduler`` and ``dask worker``). The scheduler re-runs the tasks of a worker that
  is lost; a task that still fails (``KilledWorker``) is submitted again, up to
  :data:`MAX_ATTEMPTS` times.

Workers load a model once per process (:func:`cached_scene`, the only module state: a small
per-process cache keyed by path, size, modification time and thread count), write frames
atomically into a folder that every worker can see (shared storage across servers), and return
paths. Threads per frame: ``--threads``, else $NEHAD_THREADS where the task runs, else for Dask
each server's cores divided by the task threads of its workers (so ``dask worker`` with its
defaults -- one process, a thread per core -- draws a frame per core, one thread each). A task
whose file already exists is skipped (``skip_existing``), so a re-run renders only what is
missing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import socket
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from .errors import InputProblem

__all__ = ["FrameTask", "FrameResult", "RenderError", "render_frame_task", "render_frame_image",
           "cached_scene", "SerialBackend", "PoolBackend", "DaskBackend", "make_backend",
           "MAX_ATTEMPTS"]

#: How many times a frame is tried when its worker dies before the run gives up.
MAX_ATTEMPTS = 3
#: zlib level of frame PNGs: 1 writes about twice as fast as the default for ~25% more bytes.
PNG_COMPRESSION = 1
#: Seconds to wait for at least one Dask worker.
CONNECT_TIMEOUT = 30.0
#: Seconds to wait for the Dask scheduler to answer (also the client's own timeout): one that
#: is up answers in well under a second, so an address where none listens fails this soon.
SCHEDULER_TIMEOUT = 10.0


class RenderError(InputProblem, RuntimeError):
    """A frame could not be rendered (after its retries); the message names the frame."""


@dataclass(frozen=True)
class FrameTask:
    """One frame to render (picklable: it travels to pool and Dask workers).

    `model`: absolute path of a scene (runtime/scene.py: an exported ``.onnx``, a static 3DGS
    ``.ply``, a split layers folder, or a run folder when `openers` can open it), the same path on
    every worker; `lod` keeps streaming layers 0..lod. `output`: the image to write (``.png`` 8-bit or ``.exr`` float); its folder must
    exist where the task runs. `ground_truth`: an image drawn to the right of the render
    (side by side), composited over `background` and resized to the render size. `threads`:
    onnxruntime and Numba threads for this frame (None: `host_threads` for this host, else
    $NEHAD_THREADS, else the libraries' defaults).
    """

    model: str
    index: int
    camera: object  # nehad.runtime.cameras.Camera
    time: float | None
    background: tuple
    output: str
    ground_truth: str | None = None
    threads: int | None = None
    skip_existing: bool = True
    host_threads: tuple = ()  # ((hostname, threads), ...): the Dask backend's per-host default
    lod: int | None = None
    openers: tuple = ()  # "module:function" scene openers (runtime/scene.py)


class FrameResult(NamedTuple):
    """What a task returns: the frame `index`, the `path` written, the seconds spent rendering
    and writing, whether it was `skipped` (the file existed), and the worker (host:pid)."""

    index: int
    path: str
    seconds: float
    skipped: bool
    worker: str


# ---------------------------------------------------------------------------------------------
# the per-process model cache


class _SceneCache:
    """Models loaded by this process, at most `size`, least recently used dropped first. Its lock
    guards the cache and, with Numba's workqueue threading layer, serialises the frames of a
    process (a Dask worker with several threads runs tasks concurrently)."""

    def __init__(self, size: int = 4):
        self.size = size
        self.lock = threading.RLock()
        self.scenes: OrderedDict = OrderedDict()
        self.loads = 0
        # Numba's workqueue threading layer aborts the process when two threads run parallel
        # kernels at once; omp and tbb allow it. Known after the first frame (drawn locked).
        self.concurrent_frames = False

    def get(self, path: str, threads: int | None, lod: int | None = None, openers: tuple = ()):
        st = os.stat(path)
        key = (os.path.abspath(path), st.st_size, st.st_mtime_ns, threads, lod, tuple(openers))
        with self.lock:
            scene = self.scenes.get(key)
            if scene is None:
                from .scene import open_scene

                scene = open_scene(path, lod=lod, threads=threads, openers=openers)
                self.loads += 1
                self.scenes[key] = scene
                while len(self.scenes) > self.size:
                    self.scenes.popitem(last=False)
            else:
                self.scenes.move_to_end(key)
            return scene


_CACHE = _SceneCache()


def cached_scene(path, threads: int | None = None, lod: int | None = None,
                 openers: tuple = ()):
    """This process's opened scene for `path` (runtime/scene.py)."""
    return _CACHE.get(str(path), threads, lod, openers)


def _task_threads(task: FrameTask) -> int | None:
    """Threads for `task`: its own, $NEHAD_THREADS, its host's share (Dask), or None."""
    if task.threads is not None:
        return int(task.threads)
    env = os.environ.get("NEHAD_THREADS")
    if env:
        from .values import MAX_THREADS

        try:
            count = max(1, int(env))
        except ValueError:
            raise RenderError(f"NEHAD_THREADS={env!r} on {_worker_name()}: not an integer") from None
        if count > MAX_THREADS:
            raise RenderError(f"NEHAD_THREADS={env!r} on {_worker_name()}: at most {MAX_THREADS}")
        return count
    if task.host_threads:
        mine = dict(task.host_threads).get(socket.gethostname())
        if mine:
            return int(mine)
    return None


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _ground_truth(path: str, background, width: int, height: int) -> np.ndarray:
    """A dataset image composited over `background`, at (height, width, 3)."""
    from .images import read_image

    img = read_image(path)
    if img.shape[2] in (2, 4):  # premultiplied colour + alpha (read_image's convention)
        a = img[:, :, -1:]
        rgb = img[:, :, :-1]
        if rgb.shape[2] == 1:
            rgb = np.repeat(rgb, 3, axis=2)
        img = rgb + np.asarray(background, np.float32) * (1.0 - a)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    img = img[:, :, :3]
    if img.shape[:2] != (height, width):
        import cv2

        interp = cv2.INTER_AREA if img.shape[1] > width else cv2.INTER_LINEAR
        img = cv2.resize(img, (width, height), interpolation=interp)
    return np.ascontiguousarray(img, np.float32)


def render_frame_image(task: FrameTask) -> np.ndarray:
    """The frame's image (H, W, 3) float32 (W doubled with a ground truth beside it)."""
    import numba

    from .render import render_view

    threads = _task_threads(task)
    scene = _CACHE.get(task.model, threads, task.lod, task.openers)
    with contextlib.nullcontext() if _CACHE.concurrent_frames else _CACHE.lock:
        if threads:  # per calling thread in Numba
            numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        rgb = render_view(scene, task.camera, task.time, task.background,
                          check_memory=f"frame {task.index} on {_worker_name()}",
                          out_width=task.camera.width * (2 if task.ground_truth else 1),
                          adapt_threads=not threads).image
        if not _CACHE.concurrent_frames:
            _CACHE.concurrent_frames = numba.threading_layer() in ("omp", "tbb")
    if task.ground_truth:
        gt = _ground_truth(task.ground_truth, task.background, rgb.shape[1], rgb.shape[0])
        rgb = np.concatenate([rgb, gt], axis=1)
    return rgb


def render_frame_task(task: FrameTask) -> FrameResult:
    """Render `task` and write its file atomically; skip it when the file exists and
    `task.skip_existing`. Runs in this process, a pool worker or a Dask worker alike."""
    start = time.perf_counter()
    if task.skip_existing and os.path.exists(task.output):
        return FrameResult(task.index, task.output, 0.0, True, _worker_name())
    folder = os.path.dirname(task.output) or "."
    if not os.path.isdir(folder):
        raise RenderError(f"frame {task.index}: the folder {folder} does not exist on "
                          f"{_worker_name()} (frames must go to storage every worker can see)")
    if not os.path.exists(task.model):
        raise RenderError(f"frame {task.index}: the model {task.model} does not exist on "
                          f"{_worker_name()} (the model must be at the same path on every worker)")
    image = render_frame_image(task)
    from .images import write_image

    # the frame folder's stale temporary files were swept once by prepare_frames
    write_image(task.output, image, png_compression=PNG_COMPRESSION, sweep=False)
    return FrameResult(task.index, task.output, time.perf_counter() - start, False, _worker_name())


# ---------------------------------------------------------------------------------------------
# backends

OnResult = Callable[[FrameResult], None]


def _ordered(results: dict) -> list[FrameResult]:
    return [results[k] for k in sorted(results)]


class SerialBackend:
    """Frames in this process, one after the other."""

    name = "1 process"
    workers = 1

    def __init__(self, threads: int | None = None):
        self.threads = threads

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        pass

    def run(self, tasks: list[FrameTask], on_result: OnResult | None = None) -> list[FrameResult]:
        results = {}
        for t in tasks:
            if self.threads is not None and t.threads is None:
                t = dataclasses.replace(t, threads=self.threads)
            r = render_frame_task(t)
            results[r.index] = r
            if on_result:
                on_result(r)
        return _ordered(results)


def _pool_init(parent: int):
    """Pool workers ignore Ctrl-C (the parent handles it and shuts the pool down) and exit when
    the parent dies (a SIGKILLed parent cannot shut them down, and they would otherwise wait on
    the task queue forever)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch():
        while os.getppid() == parent:
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=watch, name="nehad-parent-watch", daemon=True).start()


class PoolBackend:
    """A local pool of `workers` spawned processes, cores/workers threads each (unless `threads`).

    The pool starts on the first run and is reused by later runs (a batch); a broken pool (a
    worker died) is replaced and the unfinished frames are submitted again.
    """

    def __init__(self, workers: int, threads: int | None = None):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = int(workers)
        self.threads = threads if threads is not None else max(1, (os.cpu_count() or 1) // self.workers)
        self.name = f"local pool of {self.workers}"
        self._pool = None
        self.restarts = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _start(self):
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(self.workers, multiprocessing.get_context("spawn"),
                                             initializer=_pool_init, initargs=(os.getpid(),))
        return self._pool

    def processes(self) -> list[int]:
        """Pids of the pool's worker processes (empty before the first run)."""
        if self._pool is None:
            return []
        return [p.pid for p in (getattr(self._pool, "_processes", None) or {}).values()]

    def close(self, cancel: bool = False):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)
            self._pool = None

    def run(self, tasks: list[FrameTask], on_result: OnResult | None = None) -> list[FrameResult]:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        tasks = [t if t.threads is not None else dataclasses.replace(t, threads=self.threads)
                 for t in tasks]
        todo = {t.index: t for t in tasks}
        attempts = dict.fromkeys(todo, 0)
        results: dict[int, FrameResult] = {}
        try:
            while todo:
                pool = self._start()
                futures = {}
                for i, t in todo.items():
                    attempts[i] += 1
                    futures[pool.submit(render_frame_task, t)] = i
                broken = False
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        i = futures[f]
                        try:
                            r = f.result()
                        except BrokenProcessPool:
                            broken = True
                            continue
                        results[i] = r
                        todo.pop(i)
                        if on_result:
                            on_result(r)
                if broken:
                    self._pool.shutdown(wait=True, cancel_futures=True)
                    self._pool = None
                    self.restarts += 1
                    worst = min(todo)
                    if max(attempts[i] for i in todo) >= MAX_ATTEMPTS:
                        raise RenderError(f"frame {worst}: the local pool broke {self.restarts} "
                                          f"times (a worker process died: killed, or out of "
                                          f"memory); {len(todo)} frames are not rendered")
        except BaseException:
            self.close(cancel=True)
            raise
        return _ordered(results)


class DaskBackend:
    """Frames as tasks on a Dask distributed cluster.

    `address`: the scheduler (``tcp://HOST:8786``), or an existing ``distributed.Client`` as
    `client`. `threads` per frame (None: each server's cores shared out over the task threads of
    its workers, see :meth:`host_threads`; $NEHAD_THREADS set on a worker wins).
    `connect_timeout`: seconds to wait for a worker; `scheduler_timeout`: for the scheduler.
    """

    def __init__(self, address: str | None = None, threads: int | None = None, client=None,
                 connect_timeout: float = CONNECT_TIMEOUT,
                 scheduler_timeout: float = SCHEDULER_TIMEOUT):
        self.address = address
        self.threads = threads
        self._client = client
        self._own = client is None
        self.connect_timeout = connect_timeout
        self.scheduler_timeout = scheduler_timeout
        self.name = f"Dask at {address}" if address else "Dask"
        self.resubmitted = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def client(self):
        if self._client is None:
            try:
                from distributed import Client
            except ImportError:
                raise RenderError("{scheduler} needs Dask distributed: pip install "
                                  "'dask[distributed]'") from None
            # made in two steps so that a client whose connection failed can be closed here:
            # left to its __del__ at exit, it waited 2 x its timeout for a loop that had
            # stopped and printed a traceback
            client = Client.__new__(Client)
            try:
                client.__init__(self.address, timeout=self.scheduler_timeout,
                                set_as_default=False)
            except Exception as e:
                with contextlib.suppress(Exception):
                    client.close(timeout=2)
                why = " ".join(str(e).split())[:200]
                if isinstance(e, ValueError):  # an address Dask cannot parse
                    raise RenderError(f"{{scheduler}} {self.address}: {why}", "scheduler") \
                        from None
                # nothing listens there (OSError, TimeoutError), or something that is not a
                # Dask scheduler answers (its bytes read as a message: MemoryError, ...)
                if not isinstance(e, (OSError, TimeoutError)):
                    why = f"not a Dask scheduler? ({type(e).__name__}: {why})"
                raise RenderError(f"cannot reach the Dask scheduler at {self.address}: "
                                  f"{why}") from None
            self._client = client
        return self._client

    @property
    def workers(self) -> int:
        return len(self.client.scheduler_info().get("workers", {}))

    def close(self):
        if self._client is not None and self._own:
            self._client.close()
        self._client = None

    def _wait_for_workers(self):
        client = self.client
        if not client.scheduler_info().get("workers"):
            try:
                client.wait_for_workers(1, timeout=self.connect_timeout)
            except (TimeoutError, OSError):
                raise RenderError(f"no Dask worker is connected to {self.address or 'the scheduler'}"
                                  f" (start some: dask worker {self.address or 'tcp://HOST:8786'})"
                                  ) from None

    def host_threads(self) -> tuple:
        """((hostname, threads per frame), ...): each server's cores shared out over all the
        task threads of the Dask workers it runs ($NEHAD_THREADS on a worker still wins)."""
        client = self.client
        nthreads = {addr: int(w.get("nthreads", 1) or 1)
                    for addr, w in client.scheduler_info().get("workers", {}).items()}
        hosts = client.run(_host_and_cores)
        cores, used = {}, {}
        for addr, (host, n) in hosts.items():
            cores[host] = n
            used[host] = used.get(host, 0) + nthreads.get(addr, 1)
        return tuple(sorted((h, max(1, cores[h] // max(1, used[h]))) for h in cores))

    def run(self, tasks: list[FrameTask], on_result: OnResult | None = None) -> list[FrameResult]:
        import uuid

        from distributed import as_completed

        self._wait_for_workers()
        client = self.client
        if self.threads is not None:
            tasks = [t if t.threads is not None else dataclasses.replace(t, threads=self.threads)
                     for t in tasks]
        else:
            shares = self.host_threads()
            tasks = [dataclasses.replace(t, host_threads=shares) for t in tasks]
        token = uuid.uuid4().hex[:12]
        attempts = {t.index: 0 for t in tasks}
        by_index = {t.index: t for t in tasks}
        results: dict[int, FrameResult] = {}

        def submit(t):
            attempts[t.index] += 1
            return client.submit(render_frame_task, t, pure=False, retries=1,
                                 key=f"nehad-frame-{token}-{t.index}-{attempts[t.index]}")

        futures = {}
        for t in tasks:
            futures[submit(t)] = t.index
        ac = as_completed(list(futures), loop=client.loop, with_results=False)
        try:
            for f in ac:
                i = futures.pop(f)
                if f.status == "finished":
                    r = f.result()
                    results[i] = r
                    if on_result:
                        on_result(r)
                    continue
                from distributed.scheduler import KilledWorker

                exc = None if f.status == "cancelled" else f.exception()
                lost = exc is None or isinstance(exc, KilledWorker)
                if lost and attempts[i] < MAX_ATTEMPTS:
                    self.resubmitted += 1
                    g = submit(by_index[i])
                    futures[g] = i
                    ac.add(g)
                    continue
                if lost:
                    raise RenderError(f"frame {i}: its worker died {attempts[i]} times while "
                                      f"rendering it") from None
                if isinstance(exc, RenderError):
                    raise RenderError(" ".join(str(exc).split())) from None
                raise RenderError(f"frame {i}: {type(exc).__name__}: "
                                  f"{' '.join(str(exc).split())[:400]}") from None
        except BaseException:
            if futures:
                client.cancel(list(futures), force=True)
            raise
        return _ordered(results)


def _host_and_cores() -> tuple[str, int]:
    return socket.gethostname(), os.cpu_count() or 1


def make_backend(workers: int | None = 1, scheduler: str | None = None,
                 threads: int | None = None):
    """The backend for ``--workers N`` / ``--scheduler ADDRESS`` (see the module doc)."""
    from .values import MAX_THREADS, MAX_WORKERS, count_problem

    for key, value, most in (("workers", workers, MAX_WORKERS), ("threads", threads, MAX_THREADS)):
        why = count_problem(value, 1, most)
        if why:
            raise InputProblem(f"{{{key}}} {value}: {why}", input=key)
    if scheduler:
        return DaskBackend(scheduler, threads=threads)
    workers = 1 if workers is None else int(workers)
    if workers <= 1:
        return SerialBackend(threads)
    return PoolBackend(workers, threads)
