"""Can the deformation field carry a stress-suite scene's true motion, and across the split's gaps?

    python bench/motion_fit.py [--scene thin_rod] [--steps 4000] [--set field.resolution=[64,64,64,60]]

Points inside each labelled object of a stress scene (`nehad synth --suite stress`) at the
canonical time 0.5, and still points on its floor, are given to the preset's deformation field
(hex-plane, trunk, decoder, Verlet, rigidity clamp; `--set field.*` changes it), which is fitted
by regression to their true displacements at the suite's TRAINING times only (blocks of 20
timestamps: 14 train, 3 test, 3 val; `nehad.data.synth_stress.stress_plan`): each step one
training time, the mean squared displacement error of every point plus the field's
regularisers, Adam with the preset's learning rates and decays, the trunk standardised first
(`bench/decoder_fit.py`'s `DisplacementFit`). It then prints, per object, the position error at the
training times and at the TEST times (which lie 1-3 frame steps after a block's last training
time, in a gap no training view sees), in units of the object's thinnest width: its mean over
points and times, and the mean over times of the worst point.

It separates what the field can represent and interpolate from what a photometric loss lets it
find: with every displacement given, an error of a width or more at the test times means the
object leaves its own pixels there whatever the training does (docs/results.md, 2026-11-29,
"The spinning rod: blurred early steps, and the field fitted to the true motion by
regression"). One thread; 4-9 minutes at the default 4000 steps.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def object_points(obj, rng, n: int) -> np.ndarray:
    """(n, 3) points uniform inside `obj` (a Box or a Sphere of nehad.data.synth), in its
    local frame (before rotation, about its centre)."""
    if hasattr(obj, "half_size"):
        return rng.uniform(-1.0, 1.0, (n, 3)) * np.asarray(obj.half_size)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return obj.radius * p * rng.uniform(0.0, 1.0, (n, 1)) ** (1 / 3)


def world(obj, local: np.ndarray) -> np.ndarray:
    """Where the local points of `obj` are in the world at the time `obj` was built for."""
    rot = np.eye(3) if obj.rotation is None else np.asarray(obj.rotation)
    return np.asarray(obj.centre) + local @ rot.T


def thinnest(obj) -> float:
    """The object's smallest width (a box's thinnest side, a sphere's diameter)."""
    return float(2 * min(obj.half_size)) if hasattr(obj, "half_size") else 2 * obj.radius


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="thin_rod")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--points", type=int, default=600, help="points per object")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import torch

    from nehad.data.synth_stress import stress_objects, stress_plan

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from decoder_fit import DisplacementFit

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    labelled = [o for o in stress_objects(args.scene, 0.5) if o.labelled]
    local = {o.name: object_points(o, rng, args.points) for o in labelled}
    floor = rng.uniform(-1.4, 1.4, (300, 3))
    floor[:, 2] = 0.0

    def positions(t: float) -> np.ndarray:
        objs = {o.name: o for o in stress_objects(args.scene, t)}
        return np.concatenate([world(objs[o.name], local[o.name]) for o in labelled] + [floor])

    canonical = positions(0.5).astype(np.float32)
    fit = DisplacementFit(args.preset, args.set, canonical, args.steps)
    plan = stress_plan(120)
    train = [t for _, t, _ in plan["train"]]
    test = [t for _, t, _ in plan["test"]]
    target = {t: torch.from_numpy((positions(t) - canonical).astype(np.float32))
              for t in train + test}
    start = time.perf_counter()
    for step in range(args.steps):
        t = float(rng.choice(train))
        fit.step(step, t, target[t])

    def errors(times):
        with torch.no_grad():
            return torch.stack([(fit.displacement(t) - target[t]).norm(dim=1)
                                for t in times]).numpy()  # (times, points)

    at_train, at_test = errors(train), errors(test)
    print(f"{args.scene}, preset {args.preset} {' '.join(args.set)}, {args.steps} steps, seed "
          f"{args.seed}: position error in the object's thinnest widths, mean / mean over times "
          "of the worst point")
    for k, obj in enumerate(labelled):
        cols = slice(k * args.points, (k + 1) * args.points)
        width = thinnest(obj)
        cells = [f"{e[:, cols].mean() / width:.2f} / {e[:, cols].max(1).mean() / width:.2f}"
                 for e in (at_train, at_test)]
        print(f"  {obj.name:<16} (width {width:.2f}): training times {cells[0]}   test times "
              f"{cells[1]}")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
