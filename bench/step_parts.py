"""Where a training step of a trained model goes, part by part.

    python bench/step_parts.py RUN [--data DIR] [--downscale 2] [--every 7] [--rounds 2]

bench/train_step.py times a fixed random cloud with every Gaussian in view. A trained model
differs: about half of its Gaussians get no gradient from a view, and its points spread over the
whole hex-plane. This script loads RUN (a `nehad train` output), takes every --every-th training
view of its data at 1/--downscale of the full size, and times a forward (the deformation at the
view's time), a render, the photometric loss and the backward, as a fine step does (no
optimizer, no regularisers). Each custom autograd Function (the hex-plane lookup, the fused HNN
decoder, the projection, the rasterization, the loss) is timed in place; "rest" is what the
torch ops around them take (trunk, adapters, Verlet, clamp, quaternions, activations). Medians
and means over --rounds passes over the views, after one warm-up pass; the thread counts and the
load average are printed. Time it alone (docs/performance.md, "Where a real training step
goes").
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np


def timed_functions(totals: dict) -> None:
    """Wrap the forward and backward of the step's custom autograd Functions so that each adds
    its seconds to `totals`."""
    import nehad.field.hexplane_kernel as hexk
    import nehad.field.hnn_fused as fused
    import nehad.fused_loss as loss
    import nehad.splat.projection as proj
    import nehad.splat.rasterize as rast

    parts = {"hex-plane": hexk.HexPlaneLookup, "decoder": fused.FusedInputGradients,
             "projection": proj._NumbaProjection, "rasterization": rast.RasterizeGaussians,
             "loss": loss._FusedPhotometricLoss}
    for label, cls in parts.items():
        for name in ("forward", "backward"):
            inner = getattr(cls, name)

            def wrapper(*args, _inner=inner, _key=(label, name)):
                t0 = time.perf_counter()
                out = _inner(*args)
                totals[_key] = totals.get(_key, 0.0) + time.perf_counter() - t0
                return out

            setattr(cls, name, staticmethod(wrapper))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--data", type=Path, default=None, help="the run's dataset (default: its own)")
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--every", type=int, default=7, help="every N-th training view")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()

    import numba
    import torch

    from nehad.data.loader import load_dataset
    from nehad.losses import photometric_loss
    from nehad.model import load_run
    from nehad.splat.rasterize import render_torch
    from nehad.views import views_of

    totals: dict = {}
    timed_functions(totals)
    model, info = load_run(args.run)
    data = args.data or Path(info.data_dir)
    views = views_of(load_dataset(data, splits=("train",), downscale=args.downscale), "train")
    picks = list(range(0, len(views.cameras), args.every))
    sh_degree = 3 if info.sh_degree is None else int(info.sh_degree)
    background = tuple(float(v) for v in info.background)
    phases = {}

    def step(k: int) -> None:
        t0 = time.perf_counter()
        params = model.gaussians_at(views.times[k])
        t1 = time.perf_counter()
        res = render_torch(*params, views.cameras[k], background=background, sh_degree=sh_degree)
        loss = photometric_loss(res.rgb, views.images[k], 0.2, "numba")
        t2 = time.perf_counter()
        loss.backward()
        t3 = time.perf_counter()
        model.zero_grad(set_to_none=True)
        for key, a, b in (("forward", t0, t1), ("render + loss", t1, t2), ("backward", t2, t3)):
            phases[key] = phases.get(key, 0.0) + b - a

    print(f"threads: torch {torch.get_num_threads()}, numba {numba.get_num_threads()}; "
          f"load average before {os.getloadavg()[0]:.2f}")
    for k in picks:
        step(k)
    totals.clear()
    phases.clear()
    steps = []
    for _ in range(args.rounds):
        for k in picks:
            t0 = time.perf_counter()
            step(k)
            steps.append(time.perf_counter() - t0)
    n = len(steps)
    print(f"{len(model.gaussians)} Gaussians, {views.images[0].shape[1]}x{views.images[0].shape[0]},"
          f" {len(picks)} views x {args.rounds}: step median {1e3 * np.median(steps):.1f} ms, "
          f"mean {1e3 * np.mean(steps):.1f}")
    print(f"  {'part':16s} {'forward':>8s} {'backward':>9s}   (ms a step, means)")
    known_fwd = known_bwd = 0.0
    for label in ("hex-plane", "decoder", "projection", "rasterization", "loss"):
        f = 1e3 * totals.get((label, "forward"), 0.0) / n
        b = 1e3 * totals.get((label, "backward"), 0.0) / n
        known_fwd += f
        known_bwd += b
        print(f"  {label:16s} {f:8.2f} {b:9.2f}")
    fwd_all = 1e3 * (phases["forward"] + phases["render + loss"]) / n
    bwd_all = 1e3 * phases["backward"] / n
    print(f"  {'rest (torch ops)':16s} {fwd_all - known_fwd:8.2f} {bwd_all - known_bwd:9.2f}")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
