"""How fast a deformation field learns known motions, with no rendering in the way.

    python bench/decoder_fit.py [--preset quick] [--set field.decoder=mlp ...]
                                [--steps 1000] [--seed 0] [--no-standardize]

Points in four groups stand for the objects of a scene (the demo's, docs/usage.md): a ball
bouncing on the floor (|sin 2 pi t|, reversing at t = 0, 0.5, 1), a sphere moving on a line, a
sphere spinning about a vertical axis and a still floor. The preset's deformation field
(hex-plane, trunk, decoder, Verlet, rigidity clamp; `--set field.*` changes it) is fitted to
their true displacements by regression: each step one of 21 times, the mean squared
displacement error of every point plus the field's regularisers, Adam with the preset's
learning rates for the planes and the decoder and their decays (`nehad.optim.exp_lr`). As the trainer does at the
start of the deforming stage, the trunk is standardised over the points first
(`DeformationField.standardize_trunk`, `--no-standardize` skips it).

At five points of the run it prints, per group, the mean squared error over 40 times in
scene units^2 and the worst of the four time quarters. It isolates what the decoder can learn
and how fast from what a photometric loss lets it see (docs/results.md, 2026-11-27, "The demo's
bouncing ball and the decoder"). One thread; about a minute per 1000 steps.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

#: Where the spinning sphere's axis passes (scene units; the box is [-1.5, 1.5]^3).
SPIN_CENTRE = (0.6, -0.4, 0.1)


def groups_of(rng):
    """Canonical points (N, 3) float32 and their groups {name: slice}."""
    def ball(n, centre, radius):
        p = rng.normal(size=(n, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        return np.asarray(centre) + radius * p * rng.uniform(0, 1, (n, 1)) ** (1 / 3)

    floor = rng.uniform(-1.2, 1.2, (300, 3))
    floor[:, 2] = -0.8 + 0.05 * rng.normal(size=300)
    parts = {"bouncer": ball(300, (0.0, 0.15, 0.1), 0.2),
             "mover": ball(300, (-0.6, -0.5, 0.0), 0.2),
             "spinner": ball(300, SPIN_CENTRE, 0.25), "floor": floor}
    slices, start = {}, 0
    for name, p in parts.items():
        slices[name] = slice(start, start + len(p))
        start += len(p)
    return np.concatenate(list(parts.values())).astype(np.float32), slices


def displacement(points, groups, t: float) -> np.ndarray:
    """The true displacement of every point at time t, (N, 3)."""
    d = np.zeros_like(points)
    d[groups["bouncer"], 2] = (-0.45 + 1.1 * abs(math.sin(2 * math.pi * t))) - 0.1
    d[groups["mover"], 0] = 0.8 * (t - 0.5)
    p = points[groups["spinner"]] - np.asarray(SPIN_CENTRE, np.float32)
    a = 2 * math.pi * t
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    d[groups["spinner"]] = p @ rot.T.astype(np.float32) - p
    return d


class DisplacementFit:
    """The preset's deformation field fitted by regression to known displacements of fixed
    points (N, 3) float32: each step the mean squared displacement error at one time plus the
    field's regularisers, Adam with the preset's learning rates for the planes and the decoder
    and their decays over `steps` (`nehad.optim.exp_lr`). With `standardize` the trunk is
    standardised over the points first, as the trainer does at the start of the deforming stage
    (`DeformationField.standardize_trunk`). The box is [-1.5, 1.5]^3, the extent 3."""

    def __init__(self, preset: str, sets: list, points: np.ndarray, steps: int,
                 standardize: bool = True):
        import torch

        from nehad.config import build_config
        from nehad.field.deformation import DeformationField

        cfg = build_config(preset, None, sets)
        self.field = DeformationField(cfg.field, [[-1.5] * 3, [1.5] * 3], extent=3.0)
        self.means = torch.from_numpy(points)
        n = len(points)
        self.log_scales = torch.full((n, 3), -3.0)
        self.quats = torch.zeros(n, 4)
        self.quats[:, 0] = 1.0
        if standardize:
            with torch.no_grad():
                self.field.standardize_trunk(self.means, 0.5)
        opt = cfg.optim
        decoder_final = opt.decoder_lr if opt.decoder_lr_final is None else opt.decoder_lr_final
        self.lrs = [(opt.grid_lr_init, opt.grid_lr_final), (opt.decoder_lr, decoder_final)]
        groups = self.field.param_groups()
        self.adam = torch.optim.Adam([{"params": groups["grid"]}, {"params": groups["decoder"]}],
                                     eps=1e-15)
        self.steps = steps

    def displacement(self, t: float):
        """The field's displacement of every point at time t, (N, 3)."""
        return self.field(self.means, self.log_scales, self.quats, t).means - self.means

    def step(self, step: int, t: float, target) -> None:
        """One Adam step (0-based `step` of `steps`) on the displacements at time t."""
        from nehad.optim import exp_lr

        for group, (lo, hi) in zip(self.adam.param_groups, self.lrs):
            group["lr"] = exp_lr(step, self.steps, lo, hi)
        loss = (((self.displacement(t) - target) ** 2).sum(1).mean()
                + self.field.regularization_loss())
        self.adam.zero_grad()
        loss.backward()
        self.adam.step()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-standardize", action="store_true")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    points, groups = groups_of(rng)
    fit = DisplacementFit(args.preset, args.set, points, args.steps, not args.no_standardize)
    times = np.linspace(0.0, 1.0, 21)
    probe = np.linspace(0.0125, 0.9875, 40)
    targets = {float(t): torch.from_numpy(displacement(points, groups, float(t)))
               for t in np.concatenate([times, probe])}
    print(f"preset {args.preset} {' '.join(args.set)} seed {args.seed}; mean / worst quarter "
          "of the squared displacement error, scene units^2")
    start = time.perf_counter()
    for step in range(args.steps):
        t = float(rng.choice(times))
        fit.step(step, t, targets[t])
        if (step + 1) % max(1, args.steps // 5) == 0:
            errors = {g: [] for g in groups}
            with torch.no_grad():
                for tp in probe:
                    tp = float(tp)
                    err = ((fit.displacement(tp) - targets[tp]) ** 2).sum(1)
                    for g, sl in groups.items():
                        errors[g].append(float(err[sl].mean()))
            cells = []
            for g, e in errors.items():
                worst = max(np.mean(e[i:i + 10]) for i in range(0, 40, 10))
                cells.append(f"{g} {np.mean(e):.4f} / {worst:.4f}")
            print(f"step {step + 1:5d}  " + "  ".join(cells), flush=True)
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
