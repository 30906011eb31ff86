"""The carried-objects stage (nehad.carry_stage) applied to a finished run, written as a copy.

    python bench/carry_probe.py RUN OUT [--steps 1500] [--members 24] [--min-blobs 12] [--knots 1]
                                        [--spin]

RUN is a `nehad train` output whose model.pt went through the chain check (the recipe's); OUT
gets its config.yaml and a model.pt with the stage applied (then `nehad eval OUT --no-lpips`
scores it beside RUN's own eval). Prints the stage's record and its seconds. The stage in a run
(`--set carve.carry_steps=N`) does the same after the check.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--members", type=int, default=24)
    ap.add_argument("--min-blobs", type=int, default=12)
    ap.add_argument("--knots", type=int, default=1)
    ap.add_argument("--spin", action="store_true",
                    help="look for spinning objects even where the run's config has "
                         "carve.carry_spin off")
    args = ap.parse_args()
    from dataclasses import replace

    from nehad.carry_stage import carry_stage
    from nehad.carve_pass import frame_spacing
    from nehad.data.loader import load_dataset
    from nehad.model import load_run
    from nehad.views import views_of

    run, out = Path(args.run), Path(args.out)
    model, info = load_run(run)
    cfg = info.config
    carve = replace(cfg.carve, carry_steps=args.steps, carry_members=args.members,
                    carry_min_blobs=args.min_blobs, carry_knots=args.knots,
                    carry_spin=cfg.carve.carry_spin or args.spin)
    scene = load_dataset(info.data_dir, splits=("train", cfg.carve.check_split or "val"),
                         background=info.background, downscale=cfg.data.downscale,
                         frame_stride=cfg.data.frame_stride)
    train = views_of(scene, "train")
    val = views_of(scene, cfg.carve.check_split or "val")
    t0 = time.perf_counter()
    did = carry_stage(model, train, val, carve, info.degree_for(model), tuple(info.background),
                      frame_spacing(train.times), info.time_range, cfg.train.seed)
    print(json.dumps(did), f"{time.perf_counter() - t0:.1f} s")
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(run / "config.yaml", out / "config.yaml")
    state = torch.load(run / "model.pt", weights_only=False)
    state["gaussians"] = model.gaussians.state_dict()
    torch.save(state, out / "model.pt")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
