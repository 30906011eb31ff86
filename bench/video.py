"""Frames per second of a video render in three modes (issue 5; docs/design.md section 10): one process,
a local pool, and Dask distributed with local workers; and the overhead per frame of the pool
and Dask paths.

    python bench/video.py MODEL [--frames 120] [--size 400x400] [--workers 2] [--threads 2]

MODEL is an exported model.onnx (or a training run directory, exported to a temporary file
first). The path is an orbit derived from the model's default camera, t swept over the time
range, frames written as PNG like `nehad video` does (deformation + rasterization + PNG write).

Every mode is timed warm: its workers are started and have loaded the model and the Numba
kernels (start-up is reported on its own). The single process runs twice, with --threads threads
(default all cores) and with one; pool and Dask workers use cores / workers threads each. Overhead per frame =
(wall time x workers - the time the tasks themselves spent rendering and writing) / frames: the
scheduling, transfer and idle time a worker spends per frame. The frames of the three modes
are compared bitwise, and the video encode is timed once.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _tasks(plan, folder: Path):
    import dataclasses

    return [dataclasses.replace(t, output=str(folder / Path(t.output).name)) for t in plan.tasks]


def _timed(backend, tasks):
    start = time.perf_counter()
    results = backend.run(tasks)
    wall = time.perf_counter() - start
    return wall, sum(r.seconds for r in results)


def _same_frames(a: Path, b: Path) -> bool:
    from nehad.runtime.images import read_image

    names = sorted(p.name for p in a.glob("frame_*.png"))
    return names == sorted(p.name for p in b.glob("frame_*.png")) and all(
        (read_image(a / n) == read_image(b / n)).all() for n in names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--size", default="400x400")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None,
                    help="threads of the single process (default: all cores)")
    args = ap.parse_args()

    from nehad.runtime.distribute import DaskBackend, PoolBackend, SerialBackend
    from nehad.runtime.video import VideoJob, encode_video, plan_video

    cores = os.cpu_count() or 1
    work = Path(tempfile.mkdtemp(prefix="nehad-bench-video-"))
    try:
        model = args.model
        if model.is_dir():
            from nehad.export.onnx_export import export_run

            export_run(args.model, work / "model.onnx")
            model = work / "model.onnx"
        w, h = (int(v) for v in args.size.lower().split("x"))
        job = VideoJob(model=model, output=work / "out.mp4", path="orbit", frames=args.frames,
                       size=(w, h))
        plan = plan_video(job)
        n, wk = len(plan.tasks), args.workers
        share = max(1, cores // wk)
        print(f"{model.name}: {args.frames}-frame {w}x{h} orbit; {cores} cores; single process "
              f"{args.threads or cores} threads, pool/Dask {wk} workers x {share} threads")
        rows = []

        # -- one process, with all the threads asked for, then with one thread
        (work / "warm").mkdir()
        d1 = work / "single"
        for threads in dict.fromkeys([args.threads or cores, 1]):
            d = work / f"single{threads}"
            d.mkdir()
            single = SerialBackend(threads=threads)
            t0 = time.perf_counter()
            single.run(_tasks(plan, work / "warm")[:1])
            start1 = time.perf_counter() - t0
            wall, busy = _timed(single, _tasks(plan, d))
            rows.append((f"single process, {threads} thr", wall, busy, 1, start1))
            if not d1.exists():
                d.rename(d1)

        # -- local pool
        d2 = work / "pool"
        d2.mkdir()
        with PoolBackend(wk) as pool:
            t0 = time.perf_counter()
            warm = _tasks(plan, work / "warm")[1:1 + 2 * wk]
            pool.run(warm)
            start2 = time.perf_counter() - t0
            wall, busy = _timed(pool, _tasks(plan, d2))
        rows.append((f"local pool of {wk}", wall, busy, wk, start2))

        # -- Dask, local workers
        d3 = work / "dask"
        d3.mkdir()
        from distributed import Client, LocalCluster

        t0 = time.perf_counter()
        with LocalCluster(n_workers=wk, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            with DaskBackend(client=client, threads=share) as dk:
                dk.run(_tasks(plan, work / "warm")[1 + 2 * wk:1 + 4 * wk])
                start3 = time.perf_counter() - t0
                wall, busy = _timed(dk, _tasks(plan, d3))
        rows.append((f"Dask, {wk} local workers", wall, busy, wk, start3))

        t0 = time.perf_counter()
        encoder = encode_video(sorted(d1.glob("frame_*.png")), work / "out.mp4", 30.0)
        enc = time.perf_counter() - t0

        print(f"{'mode':<24} {'FPS':>7} {'ms/frame':>9} {'overhead ms/frame':>18} {'start-up s':>11}")
        for name, wall, busy, k, st in rows:
            over = (wall * k - busy) / n * 1000
            print(f"{name:<24} {n / wall:7.2f} {wall / n * 1000:9.1f} {over:18.1f} {st:11.1f}")
        pool, dask_row = rows[-2], rows[-1]
        pool_wall, dask_wall = pool[1], dask_row[1]
        print(f"Dask overhead per frame: {(dask_wall * wk - dask_row[2]) / n * 1000:.1f} ms of "
              f"worker time ({(dask_wall - pool_wall) / n * 1000:+.1f} ms wall per frame vs the "
              f"local pool)")
        print(f"frames bitwise identical: pool {_same_frames(d1, d2)}, Dask {_same_frames(d1, d3)}")
        print(f"encode {n} frames ({encoder}): {enc:.2f} s ({n / enc:.0f} frames/s)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
