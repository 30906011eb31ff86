"""Rasterizer speed (and a static fit's quality) on this machine.

Prints median milliseconds per frame and Gaussian-pixel pairs per second, forward and
forward+backward, for 20k and 100k random Gaussians at 400x400 and 800x800, in the scene of
../shared/notes/cpu-raster.md (means uniform in [-1,1]^3, world std 0.01-0.04, opacity 0.1-0.9,
SH degree 0, camera at distance 3.5, fov 50 degrees), with the thread counts.

  forward          = Numba projection + binning + rasterization (what the runtime does per frame)
  forward+backward = torch projection + rasterization + L1 loss + backward (one training step's
                     render and gradient, as the trainer runs it)
  pairs            = Gaussian-pixel pairs of the 3DGS workload: 256 per (Gaussian, tile) of the
                     3-sigma tile rule, no early stop (the notes' '402 M at 100k/800x800')

Then trains a static 3DGS fit on a 128x128 synthetic scene held at one time: a coarse-only run
of the trainer (`nehad train` with fine.iterations=0) of --fit-steps steps, and prints its speed
and held-out PSNR (`nehad eval`'s).

    python bench/raster.py [--quick] [--fit-steps 3000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.scenes import orbit_camera, random_cloud  # noqa: E402
from nehad.runtime.raster import project_gaussians, render  # noqa: E402


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up (JIT, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def tile_pairs(cloud, cam) -> int:
    p = project_gaussians(cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh, cam)
    r = p.radii[p.radii > 0].astype(np.float64)
    m = p.means2d[p.radii > 0].astype(np.float64) - 0.5
    ntx = (cam.width + 15) // 16
    nty = (cam.height + 15) // 16
    tx = (np.clip(np.floor((m[:, 0] + r + 15) / 16), 0, ntx) - np.clip(np.floor((m[:, 0] - r) / 16), 0, ntx))
    ty = (np.clip(np.floor((m[:, 1] + r + 15) / 16), 0, nty) - np.clip(np.floor((m[:, 1] - r) / 16), 0, nty))
    return int((tx * ty).sum() * 256)


def bench_speed(repeats: int) -> list[str]:
    import torch

    from nehad.splat.rasterize import render_torch

    lines = [f"threads: numba {numba.get_num_threads()}, torch {torch.get_num_threads()}"]
    lines.append(f"{'gaussians':>9} {'size':>7} {'fwd ms':>8} {'fwd Gpair/s':>11} "
                 f"{'fwd+bwd ms':>10} {'f+b Gpair/s':>11} {'pairs M':>8}")
    for n, size in [(20_000, 400), (20_000, 800), (100_000, 400), (100_000, 800)]:
        cloud = random_cloud(n)
        cam = orbit_camera(size)
        pairs = tile_pairs(cloud, cam)
        fwd = median_ms(lambda: render(cloud, cam), repeats)
        params = [torch.tensor(a, requires_grad=True) for a in
                  (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh)]
        target = torch.rand(size, size, 3)

        def step():
            res = render_torch(*params, cam)
            (res.rgb - target).abs().mean().backward()

        fb = median_ms(step, repeats)
        lines.append(f"{n:>9} {size:>3}x{size:<3} {fwd:>8.1f} {pairs / fwd / 1e6:>11.2f} "
                     f"{fb:>10.1f} {pairs / fb / 1e6:>11.2f} {pairs / 1e6:>8.0f}")
    return lines


def bench_static_fit(steps: int) -> str:
    """A coarse-only run (static 3DGS, the `cpu` preset's stage at full resolution, SH degree 1)
    on a 128x128 scene held at t = 0.5; its held-out PSNR as `nehad eval` measures it."""
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.evaluate import evaluate_run
    from nehad.trainer import make_trainer

    with tempfile.TemporaryDirectory() as tmp:
        data = synthesize_scene(Path(tmp) / "scene", resolution=128, frames=60, fixed_time=0.5,
                                seed=3, points=4000)
        cfg = build_config("cpu", None, [f"coarse.iterations={steps}", "fine.iterations=0",
                                         "data.downscale=1", "data.resolution_schedule=[]",
                                         "train.sh_degree=1", "train.init_max_points=0"])
        tr = make_trainer(cfg, data, Path(tmp) / "run", progress=False, log=None)
        summary = tr.train()
        result = evaluate_run(Path(tmp) / "run", "test", data, lpips=False,
                              write_renders=False, progress=False)
    seconds = summary["seconds"]
    return (f"static fit 128x128 (coarse-only run, {summary['gaussians']} Gaussians, "
            f"{len(tr.train_views.images)} train views): {summary['steps']} iterations in "
            f"{seconds:.0f} s ({summary['steps'] / seconds:.1f} it/s), held-out PSNR "
            f"{result['mean']['psnr']:.2f} dB on {result['frames']} views")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed runs per figure (median)")
    ap.add_argument("--fit-steps", type=int, default=3000,
                    help="steps of the static fit (a coarse-only run); 0 skips")
    ap.add_argument("--quick", action="store_true", help="3 repeats and no fit")
    args = ap.parse_args()
    repeats = 3 if args.quick else args.repeats
    for line in bench_speed(repeats):
        print(line, flush=True)
    if args.fit_steps > 0 and not args.quick:
        print(bench_static_fit(args.fit_steps), flush=True)


if __name__ == "__main__":
    main()
