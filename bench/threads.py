"""Thread settings on a quiet and on a busy machine: wall and CPU time of a short training run.

    python bench/threads.py [--busy 1] [--steps 400] [--resolution 64]

Trains the `quick` preset, shortened to --steps, on a synthetic scene in a child process (so each
setting starts from a fresh interpreter: the OpenMP runtimes read their environment once, at
load), first alone and then beside --busy processes that spin on a core each (the "loaded
machine" of issue 13). Settings compared:

  library     nothing set: torch's and numba's OpenMP defaults (one thread per core, spinning
              workers);
  nehad       what the `nehad` command chooses when the user has not (threads = idle cores at
              start; nehad/cli/threads.py, docs/training.md#threads);
  passive     OMP_WAIT_POLICY=PASSIVE (idle workers sleep at once), threads left at one per core;
  one-thread  OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1, the workaround the issue measured.

Every row starts from an environment without the thread variables, so `library` measures the
libraries as a plain `python -c` user gets them. It prints wall time, CPU
time (user + system of the child) and the ratio to the `nehad` setting. Run it on an otherwise
quiet machine; it prints the load average it started under.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT.parent))

CHILD = """
import sys
if sys.argv[5] == "1":
    from nehad.cli.threads import apply_thread_defaults
    apply_thread_defaults()
from pathlib import Path
from nehad.config import build_config
from nehad.data.synth import synthesize_scene
from nehad.trainer import Trainer
data, run, steps, res = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
if not data.exists():
    synthesize_scene(data, resolution=res, frames=40, seed=0)
cfg = build_config("quick", None, [f"coarse.iterations={steps // 4}",
                                   f"fine.iterations={steps - steps // 4}"])
Trainer(cfg, data, run, progress=False, log=lambda *a: None).train()
"""


NEHAD = "__nehad__"  # marker: the child applies the command's own choice


def settings() -> dict[str, dict[str, str | None]]:
    from nehad.cli.threads import VARIABLES

    removed = {k: None for k in (*VARIABLES, "OMP_WAIT_POLICY", "NUMBA_THREADING_LAYER")}
    return {"library": removed,
            "nehad": {**removed, NEHAD: "1"},
            "passive": {**removed, "OMP_WAIT_POLICY": "PASSIVE"},
            "one-thread": {**removed, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}}


def run_child(env_changes: dict, data: Path, steps: int, res: int) -> tuple[float, float]:
    env = dict(os.environ)
    nehad = env_changes.get(NEHAD, "0")
    for k, v in env_changes.items():
        if k == NEHAD:
            continue
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    with tempfile.TemporaryDirectory() as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", CHILD, str(data), str(Path(tmp) / "run"),
                        str(steps), str(res), nehad], env=env, check=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--busy", type=int, default=1, help="spinning processes beside the loaded runs")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--only", default="", help="comma-separated subset of the settings")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:K=V,K=V",
                    help="another setting to compare (variables over the library defaults; K= removes K), "
                         "repeatable")
    a = ap.parse_args()
    print(f"cores {os.cpu_count()}, load average at start {os.getloadavg()[0]:.2f}, "
          f"{a.steps} steps at {a.resolution}px")
    chosen = settings()
    chosen_base = dict(chosen["library"])
    if a.only:
        chosen = {k: v for k, v in chosen.items() if k in a.only.split(",")}
    for spec in a.variant:
        name, _, assigns = spec.partition(":")
        pairs = dict(kv.split("=", 1) for kv in assigns.split(","))
        chosen[name] = {**chosen_base, **{k: (v or None) for k, v in pairs.items()}}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "scene"
        run_child({}, data, 8, a.resolution)  # synthesise once, warm the numba cache
        for load in sorted({0, a.busy}):
            spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                        for _ in range(load)]
            try:
                for name, env in chosen.items():
                    wall, cpu = run_child(env, data, a.steps, a.resolution)
                    rows.append((name, load, wall, cpu))
                    print(f"  {name:<11} busy={load}  wall {wall:7.1f} s  cpu {cpu:7.1f} s",
                          flush=True)
            finally:
                for p in spinners:
                    p.kill()
                    p.wait()
    ref = {load: wall for name, load, wall, _ in rows if name == "nehad"}
    print(f"\n{'setting':<11} {'busy':>4} {'wall s':>8} {'cpu s':>8} {'wall / nehad':>13}")
    for name, load, wall, cpu in rows:
        ratio = f"{wall / ref[load]:.2f}x" if load in ref else "-"
        print(f"{name:<11} {load:>4} {wall:>8.1f} {cpu:>8.1f} {ratio:>13}")


if __name__ == "__main__":
    main()
