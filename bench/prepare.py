"""`nehad prepare` at issue 30's size: a made-up capture, posed, scored against its true cameras.

    python bench/prepare.py                     # rig: 12 videos x 60 frames at 400x400
    python bench/prepare.py --kind orbit        # one orbiting video of 60 frames
    python bench/prepare.py --train             # and `nehad train --preset quick` + eval

Prints the time of each phase of the preparation (the capture's drawing is not counted), the
rotation and position errors after a similarity alignment to the true cameras (issue 30: rig
<= 0.5 degree and <= 1% of the extent, orbit <= 1 degree and <= 2%), and with --train the
held-out PSNR beside a blank image's. The machine's load is printed beside: time it alone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kind", choices=["rig", "orbit"], default="rig")
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--out", type=Path, default=Path("bench_prepare"))
    ap.add_argument("--train", action="store_true", help="train --preset quick and evaluate")
    ap.add_argument("--prepare-args", default="", help="extra arguments for nehad prepare")
    args = ap.parse_args()

    from nehad.data.synth_capture import pose_errors, synthesize_capture

    cap = args.out / f"{args.kind}_capture"
    if not (cap / "truth.json").exists():
        t0 = time.perf_counter()
        synthesize_capture(cap, args.kind, resolution=args.resolution, frames=args.frames,
                           cameras=args.cameras)
        print(f"capture drawn in {time.perf_counter() - t0:.1f} s (not counted)")
    scene = args.out / f"{args.kind}_scene"
    if scene.exists():
        import shutil

        shutil.rmtree(scene)
    src = cap / "videos" if args.kind == "rig" else cap / "orbit.mp4"
    print(f"load before: {_load()}")
    t0 = time.perf_counter()
    subprocess.run(["nehad", "prepare", str(src), "-o", str(scene), *args.prepare_args.split()],
                   check=True)
    total = time.perf_counter() - t0
    record = json.loads((scene / "prepare.json").read_text())
    print(f"prepare: {total:.1f} s in all (load after: {_load()})")
    print("  phases (s): " + ", ".join(f"{k} {v:.1f}" for k, v in record["seconds"].items()))
    print(f"  registered {record['registered_images']} of {record['sfm_images']} images, "
          f"{record['matched_pairs']} pairs matched, reprojection {record['reprojection_error_px']} px")
    err = pose_errors(scene, cap / "truth.json")
    limit = (0.5, 0.01) if args.kind == "rig" else (1.0, 0.02)
    print(f"  poses of {err['cameras']} cameras: rotation max {err['rotation_max_deg']:.3f} deg "
          f"(median {err['rotation_median_deg']:.3f}; limit {limit[0]}), position max "
          f"{100 * err['position_max']:.3f}% of the extent (limit {100 * limit[1]:.0f}%)")
    if args.train:
        run = args.out / f"{args.kind}_run"
        t0 = time.perf_counter()
        subprocess.run(["nehad", "train", str(scene), "-o", str(run), "--preset", "quick"],
                       check=True)
        print(f"train --preset quick: {(time.perf_counter() - t0) / 60:.1f} min")
        subprocess.run(["nehad", "eval", str(run)], check=True)
        metrics = json.loads((run / "eval_test" / "metrics.json").read_text())
        print(f"  held-out PSNR {metrics['mean']['psnr']:.2f} dB, blank {metrics['blank']['psnr']:.2f} dB, "
              f"gain {metrics['psnr_gain']:+.2f} dB (issue 30: >= +10)")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
