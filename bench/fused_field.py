"""The training path's fused decoder (trunk, both scalar nets, the kinetic terms, the adapters and
the Verlet force in one autograd Function), forward + backward, optionally against another
checkout's.

    python bench/fused_field.py [--rows 16000] [--live 0.55] [--rounds 60]
                                [--against ../other-checkout]

Random inputs of the `cpu` preset's shapes (plane features 64 -> W 64, one hidden layer of 64
softplus units per net, kinetic terms, 10 adapter outputs and the 3 of the force); a random
linear loss on the adapters' outputs and the force, zero on a (1 - --live) share of the rows
(in a real step about half the Gaussians get no gradient from the view, docs/performance.md).
With --against, `nehad/field/hnn_fused.py` of that checkout (and the modules it imports from
nehad/field) is loaded beside this one's (the Function's call is the same in both; its last
two outputs are the adapters' and the force), the two parities are checked and the two run in
turns, alternating which goes first; it prints each one's median and the paired differences. docs/performance.md ("The kinetic terms folded
into the heads") has figures.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

import nehad.field.hnn_fused as this


#: The modules of the fused decoder, in import order (an older checkout has fewer of them).
_DECODER_MODULES = ("vecmath", "hnn_kernels", "hnn_blocks", "hnn_heads", "hnn_fused")


def _load(checkout: str):
    """The other checkout's `hnn_fused`, with the modules it imports from nehad.field taken from
    that checkout too (while they load, they stand in for this checkout's in sys.modules)."""
    field = Path(checkout) / "nehad" / "field"
    names = [f"nehad.field.{m}" for m in _DECODER_MODULES]
    ours = {name: sys.modules.get(name) for name in names}
    try:
        for name in names:
            path = field / f"{name.rsplit('.', 1)[1]}.py"
            if not path.is_file():
                continue
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            spec.loader.exec_module(module)
        return module
    finally:
        for name, module in ours.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=16000)
    ap.add_argument("--live", type=float, default=0.55, help="share of rows with a gradient")
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--against", default=None, help="another checkout to compare with")
    args = ap.parse_args()
    import numba

    torch.manual_seed(0)
    n, width, hidden, n_out = args.rows, 64, 64, 10
    f = torch.randn(n, 64).requires_grad_(True)
    params = []
    for _ in range(2):  # each net's W_1, b_1, w_out
        params += [0.2 * torch.randn(hidden, width), 0.1 * torch.randn(hidden),
                   0.2 * torch.randn(1, hidden)]
    params += [0.05 * torch.randn(width, width) for _ in range(2)]  # kinetic terms' A_1, A_2
    params += [0.1 * torch.randn(width, 64), torch.zeros(width)]  # trunk
    params += [0.1 * torch.randn(n_out, width), torch.zeros(n_out), 0.1 * torch.randn(3, width)]
    params = [p.requires_grad_(True) for p in params]
    live = (torch.rand(n, 1) < args.live).float()
    w_out, w_force = torch.randn(n, n_out) * live, torch.randn(n, 3) * live

    def step(module):
        out, force = module.FusedInputGradients.apply(f, 1, True, True, True, True, True,
                                                      *params)[-2:]
        loss = (out * w_out).sum() + (force * w_force).sum()
        return torch.autograd.grad(loss, [f, *params])

    modules = {"this": this}
    if args.against:
        modules["other"] = _load(args.against)
        ref, got = step(modules["other"]), step(this)
        rel = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
                  for a, b in zip(got, ref))
        print(f"largest difference of a gradient to the other checkout's: {rel:.1e} relative")
    for module in modules.values():  # warm-up (and the Numba kernels' first compilation)
        step(module)
        step(module)
    print(f"threads: torch {torch.get_num_threads()}, numba {numba.get_num_threads()}; "
          f"load average before {os.getloadavg()[0]:.2f}")
    times = {name: [] for name in modules}
    names = list(modules)
    for r in range(args.rounds):
        for name in (names if r % 2 == 0 else names[::-1]):
            t0 = time.perf_counter()
            step(modules[name])
            times[name].append(1000.0 * (time.perf_counter() - t0))
    print(f"fused field forward + backward, {n} rows ({args.live:.0%} with a gradient), "
          f"{args.rounds} rounds (ms):")
    for name in names:
        q1, med, q3 = np.percentile(times[name], [25, 50, 75])
        print(f"  {name:6s} median {med:7.2f}  (quartiles {q1:.2f} .. {q3:.2f})")
    if len(names) == 2:
        d = np.array(times["this"]) - np.array(times["other"])
        q1, med, q3 = np.percentile(d, [25, 50, 75])
        print(f"  this - other, paired: median {med:+.2f} (quartiles {q1:+.2f} .. {q3:+.2f})")
    print(f"load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
