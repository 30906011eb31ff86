"""What the slow-size prior (`loss.scale_rate_weight`, nehad/scale_rate.py) adds to a step.

    python bench/prior_cost.py RUN [--time 0.4] [--samples 1024] [--repeats 12]

Loads RUN (a `nehad train` output) and times, alternated in one process, three forward +
backward passes over every Gaussian at one time: the view alone (`gaussians_at`); the view
and the prior calling the field on its own samples (its stand-alone path); the view with the
prior's samples in the same field evaluation (`gaussians_and_samples_at`, what training runs);
and the view with the prior paired with the view's time (`loss.scale_rate_times=view`: the
view's own rows reused, one row per sample).
Prints the medians (after two warm-up rounds) and each path's cost over the view alone beside
the samples' share of the rows. Time it alone (docs/performance.md).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--time", type=float, default=0.4, help="the view's time")
    ap.add_argument("--samples", type=int, default=1024, help="the prior's Gaussians a step")
    ap.add_argument("--repeats", type=int, default=12)
    args = ap.parse_args()

    import torch

    from nehad.model import load_run
    from nehad.scale_rate import ScaleRatePrior

    model, _ = load_run(args.run)
    prior = ScaleRatePrior(0.1, args.samples, seed=0)
    paired = ScaleRatePrior(0.1, args.samples, seed=0, times="view")
    for p in (prior, paired):
        p.set_times(np.linspace(0.0, 1.0, 121))  # the MuJoCo scenes' frame step
    n = len(model.gaussians)

    def scalar(params):  # every Gaussian gets a gradient
        return params[0].sum() + params[1].sum() + params[3].sum()

    def view(step):
        return scalar(model.gaussians_at(args.time))

    def own_call(step):
        return view(step) + prior.loss(model, step)

    def same_call(step):
        params, sampled = model.gaussians_and_samples_at(
            args.time, *prior.rows_and_times(n, step))
        return scalar(params) + prior.loss(model, step, sampled)

    def paired_call(step):
        params, sampled = model.gaussians_and_samples_at(
            args.time, *paired.rows_and_times(n, step, args.time), with_view_rows=True)
        return scalar(params) + paired.loss(model, step, sampled, args.time)

    paths = {"view alone": view, "prior in its own call": own_call,
             "prior in the view's call": same_call,
             "paired with the view": paired_call}
    times = {k: [] for k in paths}
    for r in range(args.repeats + 2):
        for label, path in paths.items():
            model.zero_grad(set_to_none=True)
            t0 = time.perf_counter()
            path(r).backward()
            if r >= 2:
                times[label].append(time.perf_counter() - t0)
    med = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    print(f"{n} Gaussians, {2 * args.samples} prior rows, t = {args.time}; torch threads "
          f"{torch.get_num_threads()}, load average {os.getloadavg()[0]:.2f}")
    base = med["view alone"]
    for label, ms in med.items():
        extra = "" if label == "view alone" else f"  (+{ms - base:.1f} ms)"
        print(f"  {label:26s} {ms:7.1f} ms{extra}")
    print(f"  the prior rows' share of the view: {2 * args.samples / n * base:.1f} ms "
          f"(paired with the view: {args.samples / n * base:.1f})")


if __name__ == "__main__":
    main()
