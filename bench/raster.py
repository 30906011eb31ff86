"""Rasterizer speed (and a static fit's quality) on this machine, beside its compute floor.

Prints median milliseconds per frame, forward and forward+backward, for 20k and 100k random
Gaussians at 400x400 and 800x800, in the scene of ../shared/notes/cpu-raster.md (means uniform
in [-1,1]^3, world std 0.01-0.04, opacity 0.1-0.9, SH degree 0, camera at distance 3.5, fov 50
degrees), with the thread counts and the load average it ran under.

  forward          = Numba projection + binning + rasterization (what the runtime does per frame)
  forward+backward = torch projection + rasterization + L1 loss + backward (one training step's
                     render and gradient, as the trainer runs it)
  contributing     = Gaussian-pixel pairs that are blended: alpha >= 1/255, before the pixel
                     stops (counted from the frame's tile lists and stopping indices)
  floor            = contributing pairs at the inner loop's measured rate: the forward (and the
                     backward) kernel on a frame where every pixel of every tile entry is blended
                     (2500 tiles x 192 entries of low-opacity Gaussians covering the image), so
                     'x floor' is what projection, binning, skipped pixels and tiles cost on top

--busy K starts K processes that spin on a core each before the frames are timed (another job
taking cores: the forward frames then run with the thread count the runtime picks under that
load, runtime/threads.py; compare with NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 for one thread).

Then trains a static 3DGS fit on a 128x128 synthetic scene held at one time: a coarse-only run
of the trainer (`nehad train` with fine.iterations=0) of --fit-steps steps, and prints its speed
and held-out PSNR beside a blank image's (`nehad eval`'s).

    python bench/raster.py [--quick] [--repeats 15] [--fit-steps 3000] [--busy K]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.scenes import orbit_camera, random_cloud  # noqa: E402
from nehad.runtime.raster import TileBins, rasterize, rasterize_backward, render  # noqa: E402
from nehad.runtime.raster.binning import P_CA, P_CC, P_MX, P_MY, P_OP, P_ROW0, P_ROW1  # noqa: E402
from nehad.runtime.raster.fastexp import fast_exp  # noqa: E402

SIZES = [(20_000, 400), (20_000, 800), (100_000, 400), (100_000, 800)]


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up (JIT, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def load_average() -> str:
    try:
        return "%.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "n/a"


@numba.njit(parallel=True, cache=True)
def _count_contributing(tile_offsets, gauss_ids, packed, width, height, stop):
    """Pairs the forward pass blends: alpha >= 1/255 before the pixel's stopping index."""
    ntx = (width + 15) // 16
    nty = (height + 15) // 16
    per_tile = np.zeros(ntx * nty, np.int64)
    for tile in numba.prange(ntx * nty):
        x0 = (tile % ntx) * 16
        y0 = (tile // ntx) * 16
        start = tile_offsets[tile]
        count = 0
        for y in range(y0, min(y0 + 16, height)):
            for x in range(x0, min(x0 + 16, width)):
                for k in range(start, min(tile_offsets[tile + 1], start + stop[y, x])):
                    rec = packed[gauss_ids[k]]
                    dx = np.float32(x) + np.float32(0.5) - rec[0]
                    dy = np.float32(y) + np.float32(0.5) - rec[1]
                    power = -(np.float32(0.5) * (rec[2] * dx * dx + rec[4] * dy * dy)
                              + rec[3] * dx * dy)
                    if min(np.float32(0.99), rec[5] * fast_exp(power)) >= np.float32(1 / 255):
                        count += 1
        per_tile[tile] = count
    return per_tile.sum()


def contributing_pairs(out) -> int:
    b = out.bins
    return int(_count_contributing(b.tile_offsets, b.gauss_ids, b.packed, b.width, b.height,
                                   out.stop))


def inner_loop_rates(repeats: int, size: int = 800, entries: int = 192) -> tuple[float, float]:
    """Pairs per second of the forward and backward kernels when every pixel of every entry is
    blended: `entries` Gaussians of opacity 0.02 and negligible curvature on every tile of a
    size x size frame (T stays above 0.98^192 = 0.02, far from the 1e-4 stop)."""
    ntx = (size + 15) // 16
    n_tiles = ntx * ntx
    packed = np.zeros((entries, 16), np.float32)
    packed[:, P_MX] = size / 2
    packed[:, P_MY] = size / 2
    packed[:, P_CA] = 1e-9
    packed[:, P_CC] = 1e-9
    packed[:, P_OP] = 0.02
    packed[:, 6:9] = np.random.default_rng(0).uniform(0, 1, (entries, 3))
    packed[:, 9] = np.arange(1, entries + 1)
    packed[:, P_ROW0] = 0
    packed[:, P_ROW1] = size - 1
    bins = TileBins(np.arange(n_tiles + 1, dtype=np.int64) * entries,
                    np.tile(np.arange(entries, dtype=np.int32), n_tiles), packed, size, size)
    pairs = n_tiles * entries * 256
    zeros = np.zeros(entries, np.float32)
    args = (zeros.reshape(-1, 1).repeat(2, 1), zeros.reshape(-1, 1).repeat(3, 1),
            zeros.reshape(-1, 1).repeat(3, 1), zeros, zeros + 1, np.ones(entries, np.int32),
            size, size)

    def forward():
        return rasterize(*args, bins=bins)

    out = forward()
    assert int(out.stop.min()) >= 2 ** 29, "a pixel stopped: the workload is not all-blended"
    grad = np.random.default_rng(1).normal(size=(size, size, 3)).astype(np.float32)
    fwd = median_ms(forward, repeats)
    bwd = median_ms(lambda: rasterize_backward(out, grad), repeats)
    return pairs / (fwd * 1e-3), pairs / (bwd * 1e-3)


def bench_speed(repeats: int, busy: int = 0) -> list[str]:
    rate_f, rate_b = inner_loop_rates(repeats)
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
    try:
        time.sleep(1.0 if busy else 0.0)
        return _bench_sizes(repeats, rate_f, rate_b, busy)
    finally:
        for p in spinners:
            p.kill()


def _bench_sizes(repeats, rate_f, rate_b, busy) -> list[str]:
    """Every forward figure first (the runtime's frames, before torch has a thread pool in this
    process, as in `nehad render`), then every forward+backward."""
    forward = {}
    for n, size in SIZES:
        cloud, cam = random_cloud(n), orbit_camera(size)
        contrib = contributing_pairs(render(cloud, cam))
        forward[n, size] = (contrib, median_ms(lambda: render(cloud, cam), repeats))
    numba_threads = numba.get_num_threads()

    import torch

    from nehad.splat.rasterize import render_torch

    lines = [f"threads: numba {numba.config.NUMBA_NUM_THREADS} (forward frames ended with "
             f"{numba_threads}, runtime/threads.py), torch {torch.get_num_threads()}; "
             f"busy processes {busy}; load average {load_average()} (1, 5, 15 min)",
             f"inner loop (every pair blended): forward {rate_f / 1e9:.2f} G pairs/s, "
             f"backward {rate_b / 1e9:.2f} G pairs/s"]
    lines.append(f"{'gaussians':>9} {'size':>7} {'fwd ms':>7} {'floor':>6} {'x floor':>7} "
                 f"{'fwd+bwd ms':>10} {'floor':>6} {'x floor':>7} {'contributing M':>14}")
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)  # training does not adapt
    for n, size in SIZES:
        cloud, cam = random_cloud(n), orbit_camera(size)
        contrib, fwd = forward[n, size]
        floor_f = 1e3 * contrib / rate_f
        floor_fb = floor_f + 1e3 * contrib / rate_b
        params = [torch.tensor(a, requires_grad=True) for a in
                  (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh)]
        target = torch.rand(size, size, 3)

        def step():
            res = render_torch(*params, cam)
            (res.rgb - target).abs().mean().backward()

        fb = median_ms(step, repeats)
        lines.append(f"{n:>9} {size:>3}x{size:<3} {fwd:>7.1f} {floor_f:>6.1f} {fwd / floor_f:>7.2f} "
                     f"{fb:>10.1f} {floor_fb:>6.1f} {fb / floor_fb:>7.2f} {contrib / 1e6:>14.1f}")
    lines.append(f"load average at the end: {load_average()}")
    return lines


def bench_static_fit(steps: int) -> str:
    """A coarse-only run (static 3DGS, the `cpu` preset's stage at full resolution, SH degree 1)
    on a 128x128 scene held at t = 0.5; its held-out PSNR as `nehad eval` measures it."""
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.evaluate import evaluate_run
    from nehad.trainer import Trainer

    with tempfile.TemporaryDirectory() as tmp:
        data = synthesize_scene(Path(tmp) / "scene", resolution=128, frames=60, fixed_time=0.5,
                                seed=3, points=4000)
        cfg = build_config("cpu", None, [f"coarse.iterations={steps}", "fine.iterations=0",
                                         "data.downscale=1", "data.resolution_schedule=[]",
                                         "train.sh_degree=1", "train.init_max_points=0"])
        tr = Trainer(cfg, data, Path(tmp) / "run", progress=False, log=None)
        summary = tr.train()
        result = evaluate_run(Path(tmp) / "run", "test", data, lpips=False,
                              write_renders=False, progress=False)
    seconds = summary["seconds"]
    return (f"static fit 128x128 (coarse-only run, {summary['gaussians']} Gaussians, "
            f"{len(tr.train_views.images)} train views): {summary['steps']} iterations in "
            f"{seconds:.0f} s ({summary['steps'] / seconds:.1f} it/s), held-out PSNR "
            f"{result['mean']['psnr']:.2f} dB (a blank image: {result['blank']['psnr']:.2f} dB) "
            f"on {result['frames']} views")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=15, help="timed runs per figure (median)")
    ap.add_argument("--fit-steps", type=int, default=3000,
                    help="steps of the static fit (a coarse-only run); 0 skips")
    ap.add_argument("--quick", action="store_true", help="3 repeats and no fit")
    ap.add_argument("--busy", type=int, default=0,
                    help="processes spinning on a core each while the frames are timed")
    args = ap.parse_args()
    repeats = 3 if args.quick else args.repeats
    for line in bench_speed(repeats, args.busy):
        print(line, flush=True)
    if args.fit_steps > 0 and not args.quick:
        print(bench_static_fit(args.fit_steps), flush=True)


if __name__ == "__main__":
    main()
