"""The HNN decoder alone, forward + backward, in each `field.hnn_grad` mode, alternated.

    python bench/hnn.py [--rows 10000] [--width 64] [--hidden 64] [--depth 2]
                        [--activation softplus] [--modes closed_form,fused] [--rounds 15]

Builds a `HamiltonianDecoder` of the cpu preset's shape (W = 64, F1 and F2 of 2 x 64 hidden
units, softplus, gain 3) and times v = v_c + v_s for --rows random latents h plus the backward
of a random linear loss on v and v_c (to h and every weight), as in training. The modes take
turns, one call each per round, so a machine whose speed drifts between minutes slows them
alike; it prints each mode's median and quartiles over the rounds, the paired per-round
differences against the first mode, the thread counts and the load average.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from nehad.field.hnn import HamiltonianDecoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10000)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--depth", type=int, default=2)
    ap.add_argument("--activation", default="softplus")
    ap.add_argument("--modes", default="closed_form,fused")
    ap.add_argument("--rounds", type=int, default=15)
    args = ap.parse_args()
    import numba

    torch.manual_seed(0)
    dec = HamiltonianDecoder(args.width, args.hidden, args.depth, args.activation,
                             init_gain=3.0)
    h0 = torch.randn(args.rows, args.width)
    w_v, w_c = torch.randn(args.rows, args.width), torch.randn(args.rows, args.width)

    def step(mode: str) -> float:
        dec.grad_mode = mode
        dec.zero_grad(set_to_none=True)
        h = h0.clone().requires_grad_(True)
        t0 = time.perf_counter()
        out = dec(h)
        ((out.v * w_v).sum() + (out.v_c * w_c).sum()).backward()
        return 1000.0 * (time.perf_counter() - t0)

    modes = args.modes.split(",")
    for mode in modes:  # warm-up (and the Numba kernels' first compilation)
        step(mode)
        step(mode)
    print(f"threads: torch {torch.get_num_threads()}, numba {numba.get_num_threads()}; "
          f"load average before {os.getloadavg()[0]:.2f}")
    times = {m: [] for m in modes}
    for _ in range(args.rounds):
        for mode in modes:
            times[mode].append(step(mode))
    print(f"decoder forward + backward, {args.rows} rows, W {args.width}, "
          f"{args.depth} x {args.hidden} {args.activation}, {args.rounds} rounds (ms):")
    first = np.array(times[modes[0]])
    for mode in modes:
        t = np.array(times[mode])
        q1, med, q3 = np.percentile(t, [25, 50, 75])
        line = f"  {mode:12s} median {med:7.2f}  (quartiles {q1:.2f} .. {q3:.2f})"
        if mode != modes[0]:
            line += f"  paired difference to {modes[0]}: median {np.median(t - first):+.2f}"
        print(line)
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
