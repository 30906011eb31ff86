"""Where a fine (deforming) training step spends its time.

    python bench/train_step.py [--scene ../shared/data/mujoco/scene1_close_proximity]
                               [--sizes 100,200,400] [--gaussians 10000] [--repeats 20]
                               [--set k=v ...]

Builds the trainer of the `cpu` preset on the scene at each image size (data.downscale), puts N
Gaussians of a trained-looking state in it (a fixed random cloud around the origin, 2-6 cm wide,
opacity 0.5, so every size and every version of the code draws the same picture), and times,
as medians over --repeats calls after a warm-up:

  step        Trainer.train_step of a fine step, everything included;
  field       the deformation of the N Gaussians, forward and backward, the planes' gradients
              added into their .grad as the step does (HexPlane.adding_gradients_in_place);
  render      projection + rasterization of the deformed Gaussians, forward and backward;
  loss        the photometric loss (L1 + D-SSIM) of an image, forward and backward, with the
              configured loss.kernel (numba unless --set loss.kernel=torch);
  regularise  the hex-plane regularisers, forward and backward (their gradients too);
  adam        one optimizer step over every parameter.

Below each size, step, field and loss as multiples of the render (issue 27 states its targets
that way, since machines of this kind differ about 2x in absolute speed), and field and loss
beside their compute floors (bench/floors.py: their multiply-adds at this machine's measured
float32 matrix-multiply rate).
The parts do not add up to the step exactly (the step also draws a frame, logs, densifies).
It prints the thread counts and the load average it ran under; time it on a quiet machine.
The script uses only calls that the earlier trainer also had, so the same file measures an
older checkout (`git worktree add /tmp/old <commit>` and run it there with PYTHONPATH=/tmp/old).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "mujoco" / "scene1_close_proximity"


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def build(scene: Path, downscale: int, n: int, extra: list[str], run: Path):
    import torch

    from nehad.config import build_config
    from nehad.configtools import ConfigError
    from nehad.trainer import Trainer

    base = [f"data.downscale={downscale}", "coarse.iterations=1", "fine.iterations=100000",
            f"train.init_max_points={n}", "densify.max_gaussians=0"]
    # no densification: this checkout's keys, or an older one's
    for no_densify in (["fine.densify_from=1.0", "fine.densify_until=1.0",
                        "coarse.densify_until=0.0"],
                       ["densify.start=1000000"]):
        try:
            cfg = build_config("cpu", None, base + no_densify + extra)
            break
        except ConfigError:
            continue
    tr = Trainer(cfg, scene, run, progress=False, log=None)
    g = tr.model.gaussians
    rng = np.random.default_rng(0)
    with torch.no_grad():
        k = len(g)
        g.means.copy_(torch.from_numpy(rng.normal(0.0, 0.6, (k, 3)).astype(np.float32)))
        g.means[:, 2].abs_()
        g.log_scales.copy_(torch.from_numpy(
            np.log(rng.uniform(0.02, 0.06, (k, 3))).astype(np.float32)))
        g.opacity_logits.fill_(0.0)
    tr.train_step(0)  # the coarse step
    tr.step = 1
    return tr


def floors(tr, rate: float) -> dict:
    """The field's and the loss's floors in ms (bench/floors.py) for `tr`'s model and images."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from floors import field_macs, loss_macs

    view = tr.train_views
    _, field_both = field_macs(tr.model, view.times[0])
    cam = view.cameras[0]
    _, loss_both = loss_macs(cam.width, cam.height)
    return {"field": 1e3 * field_both / rate, "loss": 1e3 * loss_both / rate,
            "field_gmac": field_both / 1e9}


def measure(tr, repeats: int) -> dict:
    import torch

    from nehad.losses import photometric_loss
    from nehad.splat.rasterize import render_torch

    out = {}
    step = [1]

    def one_step():
        tr.train_step(step[0])
        step[0] += 1

    out["step"] = median_ms(one_step, repeats)
    view = tr.train_views
    cam, t, target = view.cameras[0], view.times[0], view.images[0]
    model = tr.model

    # as the step runs them: the planes' gradients added into their .grad in place (HexPlane;
    # an older checkout without it returns them to autograd)
    in_place = getattr(model.field.hexplane, "adding_gradients_in_place", contextlib.nullcontext)

    def field():
        with in_place():
            params = model.gaussians_at(t, deform=True)
        sum(p.sum() for p in params).backward()

    out["field"] = median_ms(field, repeats)
    with torch.no_grad():
        deformed = [p.detach().clone() for p in model.gaussians_at(t, deform=True)]
    for p in deformed:
        p.requires_grad_(True)
    degree = tr.active_sh_degree(10 ** 6)

    def render():
        res = render_torch(*deformed, cam, background=tr.background, sh_degree=degree)
        (res.rgb - target).abs().mean().backward()

    out["render"] = median_ms(render, repeats)
    image = target.clone().mul_(0.9).requires_grad_(True)
    kernel = getattr(tr.cfg.loss, "kernel", None)  # None: a checkout without the fused loss
    extra = () if kernel is None else (kernel,)
    out["loss"] = median_ms(lambda: photometric_loss(image, target, 0.2, *extra).backward(),
                            repeats)

    def regularise():
        with in_place():
            loss = model.field.regularization_loss()
        loss.backward()

    out["regularise"] = median_ms(regularise, repeats)
    opt = tr.optimizer
    for group in opt.param_groups:
        group["lr"] = 1e-12
        for p in group["params"]:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
    out["adam"] = median_ms(opt.step, repeats)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", type=Path, default=DATA)
    ap.add_argument("--sizes", default="100,200,400", help="image widths (800 / downscale)")
    ap.add_argument("--gaussians", type=int, default=10000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--set", dest="sets", action="append", default=[])
    args = ap.parse_args()
    if not args.scene.is_dir():
        sys.exit(f"--scene: {args.scene} not found")
    import numba
    import torch

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from floors import matmul_rate

    load = os.getloadavg()
    rate = matmul_rate()
    print(f"threads: torch {torch.get_num_threads()}, numba {numba.get_num_threads()}; "
          f"load average before {load[0]:.2f}; float32 matmul {rate / 1e9:.1f} G multiply-adds/s")
    print(f"{'size':>9} {'N':>6} " + " ".join(f"{k:>10}" for k in
                                              ("step", "field", "render", "loss", "regularise",
                                               "adam")) + "   (ms)")
    for size in (int(v) for v in args.sizes.split(",")):
        downscale = max(1, int(round(800 / size)))
        run = Path(tempfile.mkdtemp(prefix="nehad_bench_step_"))
        try:
            tr = build(args.scene, downscale, args.gaussians, args.sets, run / "run")
            r = measure(tr, args.repeats)
            floor = floors(tr, rate)
        finally:
            shutil.rmtree(run, ignore_errors=True)
        w = tr.train_views.cameras[0].width
        print(f"{w:>4}x{w:<4} {len(tr.model.gaussians):>6} " +
              " ".join(f"{r[k]:>10.1f}" for k in ("step", "field", "render", "loss",
                                                  "regularise", "adam")))
        # issue 27's targets as ratios to the render of the same run (machines differ ~2x)
        print(f"{'':>16}x render: step {r['step'] / r['render']:.2f}, field "
              f"{r['field'] / r['render']:.2f}, loss {r['loss'] / r['render']:.2f}")
        print(f"{'':>16}floor (ms): field {floor['field']:.1f} ({floor['field_gmac']:.3f} G "
              f"multiply-adds; x floor {r['field'] / floor['field']:.1f}), loss "
              f"{floor['loss']:.1f} (x floor {r['loss'] / floor['loss']:.1f})")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
