"""MKL's vector-math functions initialised by one serial call before torch runs them in parallel.

torch's CPU build computes exp, log, tanh and the like on float tensors through MKL's vector
math (VML), and splits a tensor of more than 2048 elements into chunks that its threads pass to
MKL at the same time. MKL sets itself up on its first VML call; when that first call is such a
parallel one, the threads race through the setup and, in some processes, one thread's chunk comes
back wrong: measured on this machine (torch 2.13.0, 2 threads), the first `torch.exp` of a fresh
process on 6000 float32 values returned its second half off by up to 1766 ulp (1e-4 relative) in
10 of 200 processes, every later call right; with one serial call of 16 values first, 0 of 100
(docs/development.md, "The training fingerprint and MKL's first call"). A training run hit it on
its first step's scales, so about one run in twenty computed other bits than the next, which
the bit-for-bit training record (tests/test_fingerprint.py) caught as a flaky CI failure.

Importing this module makes that serial call once per process; the torch modules that compute
(nehad.gaussians, which the model, the trainer and the export import) import it.
"""

from __future__ import annotations

import torch


def initialise_vector_math() -> None:
    """One call of MKL's vector math on 16 values (below torch's 2048-element split, so on
    this thread alone), which sets MKL up before any parallel call can race through it."""
    with torch.no_grad():
        torch.exp(torch.zeros(16, dtype=torch.float32))


initialise_vector_math()
