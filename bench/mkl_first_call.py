"""How often the first parallel `torch.exp` of a fresh process comes back wrong, with and without
the serial first call that nehad.vector_math makes (its module doc).

    python bench/mkl_first_call.py [--processes 100] [--threads 2]

Each process draws 2000 x 3 log-scales as the trainer's Gaussians have them (uniform in
[-4.6, -2.4]), takes `torch.exp` of them with --threads threads (torch splits 6000 values
between its threads), then again with one thread, and reports whether the two differ. The
`cold` row runs that first; the `warmed` row first makes nehad.vector_math's call of 16 values.
It prints the count of wrong processes per row and the largest error in float32 ulp.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys
import numpy as np, torch
torch.set_num_threads(int(sys.argv[1]))
if sys.argv[2] == "warmed":
    from nehad.vector_math import initialise_vector_math  # (importing it makes the call)
log_scales = torch.from_numpy(np.random.default_rng(int(sys.argv[3])).uniform(
    -4.6, -2.4, (2000, 3)).astype(np.float32))
first = torch.exp(log_scales)
torch.set_num_threads(1)
serial = torch.exp(log_scales)
ulp = np.spacing(serial.numpy()).astype(np.float64)
err = float(np.max(np.abs(first.numpy().astype(np.float64) - serial.numpy()) / ulp))
print(json.dumps({"wrong": bool((first != serial).any()), "ulp": err}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    print(f"load average at start: {os.getloadavg()[0]:.2f}; {args.processes} processes a row, "
          f"torch threads {args.threads}")
    for row in ("cold", "warmed"):
        wrong, worst = 0, 0.0
        for k in range(args.processes):
            out = subprocess.run([sys.executable, "-c", CHILD, str(args.threads), row, str(k)],
                                 env=env, capture_output=True, text=True, check=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            wrong += r["wrong"]
            worst = max(worst, r["ulp"])
        print(f"{row:7s} wrong first calls: {wrong} of {args.processes}, largest error "
              f"{worst:.0f} ulp")


if __name__ == "__main__":
    main()
