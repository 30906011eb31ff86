"""Ctrl-C on `nehad train`, at many moments, beside a busy core (issue 26).

    python bench/ctrl_c.py [--offsets 20] [--repeat 1] [--busy 1] [--timeout 30] [--out DIR]

Synthesises a 32 px scene once, then for every repetition and offset: starts `nehad train
SCENE -o RUN --preset test --set fine.iterations=100000` (a checkpoint every 20 steps), waits for
the first checkpoint, waits the offset (spread evenly over [0, --span) seconds, so the SIGINT
lands at every point of the step / checkpoint / metrics cycle), sends SIGINT and measures how long
the process takes to exit. A process still alive after --timeout seconds is sent SIGUSR1 (the CLI
dumps every thread's stack, faulthandler) and then killed; its stderr is kept in DIR.

Prints one line per trial and a summary (exits, status 130, the promised message, max/median
exit time); the exit status is 1 if any trial hung or missed the message.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1"}


# --plain: the CLI without its own SIGINT handling (as before issue 26), with only the stack dump
PLAIN = ("import faulthandler, signal, sys; faulthandler.register(signal.SIGUSR1, all_threads=True)\n"
         "from nehad.cli.main import main; from nehad.cli.threads import apply_thread_defaults\n"
         "apply_thread_defaults(); main(sys.argv[1:], prog_name='nehad')")


def trial(scene: Path, run: Path, offset: float, timeout: float, log: Path,
          plain: bool = False) -> dict:
    head = ["-c", PLAIN] if plain else ["-m", "nehad.cli.main"]
    cmd = [sys.executable, *head, "train", str(scene), "-o", str(run),
           "--preset", "test", "--quiet", "--set", "fine.iterations=100000"]
    with open(log, "w+") as err:
        proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.DEVNULL, stderr=err)
        hung = False
        try:
            deadline = time.time() + 300
            while not list((run / "checkpoints").glob("step_*.pt")):
                if proc.poll() is not None:
                    raise RuntimeError(f"train exited early ({proc.returncode}): see {log}")
                if time.time() > deadline:
                    raise RuntimeError(f"no checkpoint after 300 s: see {log}")
                time.sleep(0.02)
            time.sleep(offset)
            sent = time.perf_counter()
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                hung = True
                proc.send_signal(signal.SIGUSR1)  # the stacks, into the log
                time.sleep(2)
            seconds = time.perf_counter() - sent
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        err.seek(0)
        text = err.read()
    return {"offset": offset, "seconds": seconds, "code": proc.returncode, "hung": hung,
            "message": "keeps its checkpoint at step" in text and "--resume" in text,
            "traceback": "Traceback" in text, "lock_left": (run.parent / f".{run.name}.nehad-lock").exists(),
            "log": log}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--offsets", type=int, default=20)
    ap.add_argument("--span", type=float, default=4.0, help="offsets spread over [0, SPAN) s")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--busy", type=int, default=1, help="busy-loop processes beside (cores)")
    ap.add_argument("--timeout", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--plain", action="store_true",
                    help="run the CLI without its SIGINT handler (stack dump on SIGUSR1 only)")
    a = ap.parse_args()
    out = a.out or Path(tempfile.mkdtemp(prefix="nehad-ctrl-c-"))
    out.mkdir(parents=True, exist_ok=True)
    scene = out / "scene"
    if not (scene / "transforms_train.json").is_file():
        subprocess.run([sys.executable, "-m", "nehad.cli.main", "synth", str(scene),
                        "--resolution", "32", "--frames", "20", "--gaussians", "0"], env=ENV,
                       check=True, stdout=subprocess.DEVNULL)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(a.busy)]
    results = []
    try:
        for rep in range(a.repeat):
            for k in range(a.offsets):
                offset = a.span * k / a.offsets
                run = out / f"run_{rep}_{k}"
                r = trial(scene, run, offset, a.timeout, out / f"stderr_{rep}_{k}.txt", a.plain)
                results.append(r)
                flag = "HUNG" if r["hung"] else ("ok" if r["code"] == 130 and r["message"]
                                                 and not r["traceback"] else "BAD")
                print(f"rep {rep} offset {offset:5.2f} s: exit {r['code']} after "
                      f"{r['seconds']:6.2f} s  {flag}"
                      + ("" if flag == "ok" else f"  (stderr: {r['log']})"), flush=True)
                if flag == "ok":
                    import shutil
                    shutil.rmtree(run, ignore_errors=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    secs = [r["seconds"] for r in results]
    good = sum(r["code"] == 130 and r["message"] and not r["traceback"] and not r["hung"]
               and not r["lock_left"] for r in results)
    print(f"{len(results)} trials: {good} ended with status 130 and the message, "
          f"{sum(r['hung'] for r in results)} hung; exit time median "
          f"{statistics.median(secs):.2f} s, max {max(secs):.2f} s (logs in {out})")
    return 0 if good == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
