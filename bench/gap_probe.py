"""How a trained stress-suite model draws each object across a block of the time split.

    python bench/gap_probe.py RUN [--scene NAME] [--resolution 200] [--cams 0,1,...,11]
        [--offsets -6.5,-0.5,0,1,2,3,4,5,6,7] [--drop mortal|immortal]

The stress suite (`nehad synth --suite stress`) splits its 120 timestamps in blocks of 20: 14
consecutive training times, then 3 test and 3 validation times that no training view sees, so
every test view lies in a gap of 7 frame steps (docs/results.md, 2026-11-28). This script asks
the model for any time of a block, not only the dataset's: offset 0 is a block's last training
time, -6.5 lies between two training times in the block's middle, 1-3 are the test times, 4-6
the validation times, 7 the next block's first training time. At each offset of every block it
renders the run from each rig camera in `--cams` (also cameras that never saw that time) and
draws the truth with the suite's own ray caster; each object is scored on its own pixels as
`nehad eval` scores it, pooled over blocks and cameras: its gain over a blank (white) image,
beside the gain of the truth at the nearest training time ("held": a model exact at every
training time that does not move anything between them, bench/stepping_oracle.py).

`--drop mortal` makes the Gaussians with a finite life (the tracks' chains) transparent,
`--drop immortal` the others (the deformation field's): which of the two draws an object.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

LAST = 119  # the suite's last timestamp: 120 timestamps over [0, 1]
LAST_TRAIN = 13  # a block's last training timestamp (14 train, 3 test, 3 val)


def probe(run, scene: str, resolution: int, cams, offsets, drop: str = ""):
    """({offset: {object: (model gain, held gain)}}, the blocks pooled, seconds spent) (module
    docstring)."""
    from nehad.runtime.gaussians import GaussianCloud
    from nehad.runtime.raster import render

    from nehad.data.synth import class_mapping, label_mask, render_view
    from nehad.data.synth_stress import rig_camera, stress_objects, stress_plan
    from nehad.evaluate import object_errors
    from nehad.model import cloud_at, load_run

    start = time.perf_counter()
    model, info = load_run(run)
    degree = info.degree_for(model)
    mortal = (model.gaussians.life_rate.detach().reshape(-1) != 0).numpy()
    train_times = np.array([t for _, t, _ in stress_plan(120)["train"]])
    names = {int(k): v for k, v in class_mapping(stress_objects(scene, 0.0)).items()}
    white = np.ones(3, np.float32)
    # the same blocks at every offset: those whose every offset lies in [0, 1] (the last
    # block's gap has no next block: its test times extrapolate past the last training time)
    blocks = [b for b in range(LAST // 20 + 1)
              if 0 <= 20 * b + LAST_TRAIN + min(offsets)
              and 20 * b + LAST_TRAIN + max(offsets) <= LAST]
    table = {}
    for off in offsets:
        sums: dict[int, np.ndarray] = {}
        for b in blocks:
            t = (20 * b + LAST_TRAIN + off) / LAST  # as stress_plan writes k / (frames - 1)
            nearest = float(train_times[np.argmin(np.abs(train_times - t))])
            objects, held_objects = stress_objects(scene, t), stress_objects(scene, nearest)
            cloud = cloud_at(model, t, degree)
            if drop:
                opacities = cloud.opacities.copy()
                opacities[mortal if drop == "mortal" else ~mortal] = 0.0
                cloud = GaussianCloud(cloud.means, cloud.scales, cloud.quats, opacities, cloud.sh)
            for c in cams:
                cam = rig_camera(c, resolution, time=t)
                truth, coverage = render_view(objects, cam, supersample=2, return_coverage=True)
                held = render_view(held_objects, cam, supersample=2)
                truth, held = (x[..., :3] + white * (1.0 - x[..., 3:4]) for x in (truth, held))
                labels = label_mask(objects, coverage)
                drawn = render(cloud, cam, info.background).rgb
                for key, pair in ((0, drawn), (1, held)):
                    for i, (n, sse, bsse) in object_errors(labels, pair, truth, white).items():
                        acc = sums.setdefault(i, np.zeros((2, 3)))
                        acc[key] += (n, sse, bsse)
        table[off] = {names[i]: tuple(10.0 * math.log10(a[k, 2] / max(a[k, 1], 1e-12))
                                      for k in (0, 1))
                      for i, a in sorted(sums.items()) if i in names and a[0, 0] > 0}
    return table, blocks, time.perf_counter() - start


def _held(gain: float) -> str:
    """The held picture's gain; at a training time it is the truth itself."""
    return "held exact" if gain > 90.0 else f"held {gain:+5.1f}"


def main() -> None:
    from nehad.data.synth_stress import STRESS_SCENES
    from nehad.model import load_run

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a `nehad train` output trained on a stress-suite scene")
    ap.add_argument("--scene", default=None,
                    help="the stress scene (default: the name of the run's dataset folder)")
    ap.add_argument("--resolution", type=int, default=200,
                    help="image size (200: the cpu preset's last training size on the suite)")
    ap.add_argument("--cams", default=",".join(str(i) for i in range(12)),
                    help="rig cameras to render from (default: all 12)")
    ap.add_argument("--offsets", default="-6.5,-0.5,0,1,2,3,4,5,6,7",
                    help="frame steps after each block's last training time")
    ap.add_argument("--drop", choices=("", "mortal", "immortal"), default="",
                    help="make the Gaussians with a finite life (mortal) or the others "
                         "transparent")
    args = ap.parse_args()
    scene = args.scene
    if scene is None:
        scene = Path(load_run(args.run)[1].data_dir or "").name
    if scene not in STRESS_SCENES:
        ap.error(f"--scene: expected one of {', '.join(STRESS_SCENES)}, got {scene!r}")
    offsets = [float(x) for x in args.offsets.split(",")]
    cams = [int(x) for x in args.cams.split(",")]
    table, blocks, secs = probe(args.run, scene, args.resolution, cams, offsets, args.drop)
    objects = sorted({name for row in table.values() for name in row})
    print(f"{scene}: gain over blank on each object's pixels, the model (held: the truth at the "
          f"nearest training time), {len(cams)} cameras, blocks {', '.join(map(str, blocks))}; "
          f"offset in frame steps after the block's last training time")
    print("offset  " + "".join(f"{name:>24s}" for name in objects))
    for off, row in table.items():
        cells = "".join(f"{row[n][0]:+9.1f} ({_held(row[n][1])})" if n in row else " " * 24
                        for n in objects)
        print(f"{off:+6.1f}  {cells}")
    print(f"({secs:.0f} s)")


if __name__ == "__main__":
    main()
