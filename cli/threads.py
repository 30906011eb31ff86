"""Thread defaults the `nehad` command sets before torch or numba load (docs/training.md#threads).

torch's CPU wheel and numba each bring an OpenMP runtime with one worker per core. Left at their
defaults, workers that finish a parallel region spin for a while before sleeping; in one process
that alternates torch (the field, the loss) and numba (the rasterizer), and on a machine whose
cores another process also wants, the spinning workers of one runtime take the cores the other
runtime's workers need, and every parallel region waits for a descheduled worker. Issue 13
measured a demo at 23.8 min that way against 2.8 min with one thread each.

``OMP_WAIT_POLICY=PASSIVE`` makes both runtimes' idle workers sleep at once. It is read when a
runtime loads, so it must be in the environment before the first ``import torch`` or numba
parallel call: :func:`apply_thread_defaults` runs when the command line is imported, and only
fills in what the user has not set, so ``OMP_NUM_THREADS=1 nehad ...`` and an explicit
``OMP_WAIT_POLICY=ACTIVE`` still win. ``bench/threads.py`` measures the settings quiet and busy.
"""

from __future__ import annotations

import os

# Variable -> value used when the environment does not name it.
DEFAULTS: dict[str, str] = {
    "OMP_WAIT_POLICY": "PASSIVE",
}


def apply_thread_defaults(environ=os.environ) -> dict[str, str]:
    """Set every :data:`DEFAULTS` entry that `environ` lacks; return the ones it set."""
    applied = {}
    for name, value in DEFAULTS.items():
        if name not in environ:
            environ[name] = value
            applied[name] = value
    return applied
