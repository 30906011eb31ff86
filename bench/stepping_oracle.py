"""What a model that steps between the training times would score on each stress-suite object.

    python bench/stepping_oracle.py [--scenes thin_rod,spinning_textures] [--resolution 400]

The stress suite (`nehad synth --suite stress`) splits its 120 timestamps in blocks of 20: 14
train, 3 test, 3 val, so every test time lies 1-3 frame steps after the last training time of
its block and 5-7 before the next block's first. This script draws, from each test camera, the
truth at the test time and the truth at the NEAREST training time, with the suite's own ray
caster: the second is the picture of a model that is exact at every training time and holds it
until the next (no motion between them). Each object's gain over a blank image on its own
pixels, per time quarter, is scored as `nehad eval` scores a model (`nehad.evaluate`:
the white evaluation background, the label masks of the test time, pooled squared errors per
quarter of the training time range).

Where the stepping picture scores under +8 dB, issue 25's bar asks the model to move the
object between the training times (a spin, a fast flight), not only to fit each view; where
it scores far over, a stepping model would pass (docs/results.md, 2026-11-28).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def stepping_scores(name: str, resolution: int, frames: int = 120, supersample: int = 2):
    """(per-object summaries as `nehad.evaluate.summarize_objects` gives them, seconds)."""
    from nehad.data.synth import class_mapping, label_mask, render_view
    from nehad.data.synth_stress import rig_camera, stress_objects, stress_plan
    from nehad.evaluate import object_errors, summarize_objects

    start = time.perf_counter()
    plan = stress_plan(frames)
    train_times = np.array([t for _, t, _ in plan["train"]])
    white = np.ones(3)
    records = []
    for _, t, cam_id in plan["test"]:
        cam = rig_camera(cam_id, resolution, time=t)
        objects = stress_objects(name, t)
        truth, coverage = render_view(objects, cam, supersample=supersample,
                                      return_coverage=True)
        nearest = float(train_times[np.argmin(np.abs(train_times - t))])
        held = render_view(stress_objects(name, nearest), cam, supersample=supersample)
        over = [img[..., :3] + white * (1.0 - img[..., 3:4]) for img in (truth, held)]
        labels = label_mask(objects, coverage)
        records.append({"time": t, "ids": [int(i) for i in np.unique(labels)],
                        "errors": object_errors(labels, over[1], over[0], white)})
    names = {int(k): v for k, v in class_mapping(stress_objects(name, 0.0)).items()}
    span = (float(train_times.min()), float(train_times.max()))
    return summarize_objects(records, names, span), time.perf_counter() - start


def main() -> None:
    from nehad.data.synth_stress import STRESS_SCENES

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(STRESS_SCENES),
                    help="comma-separated stress scenes (default: all)")
    ap.add_argument("--resolution", type=int, default=400, help="image size (the suite's 400)")
    args = ap.parse_args()
    print("gain over blank on each object's pixels, per quarter of the training time range, of "
          "the truth at the nearest training time (a model that steps between them):")
    for name in args.scenes.split(","):
        objects, secs = stepping_scores(name.strip(), args.resolution)
        for o in objects:
            quarters = "  ".join("   -  " if tb.get("gain") is None else f"{tb['gain']:+6.1f}"
                                 for tb in o["time_bins"])
            print(f"  {name:18s} {o['name']:18s} {quarters}")
        print(f"  ({name}: {secs:.0f} s)")


if __name__ == "__main__":
    main()
