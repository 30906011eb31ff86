"""Train and evaluate NeHaD against the 4DGS-style MLP decoder on real scenes, and the ablation.

    python bench/quality.py [--scenes scene1_close_proximity,...] [--decoders hnn,mlp]
                            [--preset cpu] [--set k=v ...] [--out runs/quality]
    python bench/quality.py --ablation scene1_close_proximity

Scenes are looked up in ../shared/data/mujoco (400x400 with the cpu preset's downscale 2) and
../shared/data/dnerf_lego_100 (100x100, black background, downscale 1). Prints one row per
(scene, decoder): test PSNR / SSIM / LPIPS-vgg / training minutes / Gaussians / render FPS, and
writes the rows to OUT/results_*.json (one file per invocation, so several invocations, e.g. one
per core with OMP_NUM_THREADS=1, can share OUT). Runs already finished are reused, and their
scores (RUN/bench_row.json) too (delete a run to redo it).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data"
DEFAULT_SCENES = ("scene1_close_proximity", "scene3_collision", "scene5_rapid_motion",
                  "dnerf_lego_100")
ABLATIONS = {
    "full NeHaD": [],
    "no HNN": ["field.use_hnn=false"],
    "no BED position": ["field.bed_position=false"],
    "no BED scale": ["field.bed_scale=false"],
    "no Verlet": ["field.verlet=false"],
    "no rigidity": ["field.rigidity=false"],
    "MLP decoder (4DGS)": ["field.decoder=mlp"],
}


def scene_path(name: str) -> tuple[Path, list[str]]:
    """Dataset folder and the settings it needs."""
    if name == "dnerf_lego_100":
        return DATA / name, ["data.downscale=1", "data.background=[0,0,0]"]
    return DATA / "mujoco" / name, []


def train_and_eval(data: Path, run: Path, preset: str, sets: list[str]) -> dict:
    from nehad.config import build_config
    from nehad.evaluate import evaluate_run
    from nehad.trainer import Trainer

    done = run / "model.pt"
    minutes = None
    if not done.exists():
        cfg = build_config(preset, None, sets)
        t0 = time.perf_counter()
        Trainer(cfg, data, run, resume=(run / "config.yaml").exists(), progress=True).train()
        minutes = (time.perf_counter() - t0) / 60
        (run / "train_minutes.txt").write_text(f"{minutes:.2f}\n")
    elif (run / "train_minutes.txt").exists():
        minutes = float((run / "train_minutes.txt").read_text())
    row_file = run / "bench_row.json"
    if row_file.exists() and minutes is None:
        return json.loads(row_file.read_text())
    result = evaluate_run(run, "test", data, lpips=True, progress=True)
    m = result["mean"]
    row = {"psnr": m["psnr"], "ssim": m["ssim"], "lpips_vgg": m["lpips_vgg"],
           "minutes": minutes, "gaussians": result["gaussians"], "fps": result["fps"],
           "resolution": result["resolution"]}
    row_file.write_text(json.dumps(row, indent=1))
    return row


def print_rows(rows: list[dict]) -> None:
    print(f"{'scene':<24} {'variant':<20} {'PSNR':>6} {'SSIM':>6} {'LPIPSvgg':>8} "
          f"{'train min':>9} {'Gaussians':>9} {'FPS':>6}")
    for r in rows:
        f = lambda v, d: "n/a" if v is None else f"{v:.{d}f}"
        print(f"{r['scene']:<24} {r['variant']:<20} {f(r['psnr'], 2):>6} {f(r['ssim'], 4):>6} "
              f"{f(r['lpips_vgg'], 4):>8} {f(r['minutes'], 1):>9} {r['gaussians']:>9} "
              f"{f(r['fps'], 1):>6}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default=",".join(DEFAULT_SCENES))
    ap.add_argument("--decoders", default="hnn,mlp")
    ap.add_argument("--ablation", default=None, metavar="SCENE",
                    help="run the component ablation on this scene instead")
    ap.add_argument("--variants", default=None,
                    help="comma-separated subset of the ablation variants (default: all)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "quality")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    if args.ablation:
        data, scene_sets = scene_path(args.ablation)
        wanted = args.variants.split(",") if args.variants else list(ABLATIONS)
        for variant in wanted:
            if variant not in ABLATIONS:
                sys.exit(f"--variants: unknown variant {variant!r} (choose from "
                         f"{', '.join(ABLATIONS)})")
            extra = ABLATIONS[variant]
            # The full model and the baseline are the main table's runs of that scene.
            shared = {"full NeHaD": "hnn", "MLP decoder (4DGS)": "mlp"}.get(variant)
            run = (args.out / f"{args.ablation}_{shared}" if shared else
                   args.out / f"ablation_{args.ablation}_{variant.replace(' ', '_')}")
            extra = extra if shared is None else [f"field.decoder={shared}"]
            rows.append({"scene": args.ablation, "variant": variant,
                         **train_and_eval(data, run, args.preset, scene_sets + args.sets + extra)})
            print_rows(rows[-1:])
    else:
        for scene in args.scenes.split(","):
            data, scene_sets = scene_path(scene)
            for dec in args.decoders.split(","):
                run = args.out / f"{scene}_{dec}"
                rows.append({"scene": scene, "variant": f"decoder {dec}",
                             **train_and_eval(data, run, args.preset,
                                              scene_sets + args.sets + [f"field.decoder={dec}"])})
                print_rows(rows[-1:])
    print()
    print_rows(rows)
    # One file per invocation: several invocations (e.g. one per core) may share --out.
    tag = args.ablation or "_".join(args.scenes.split(",")) + "_" + "_".join(
        args.decoders.split(","))
    (args.out / f"results_{'ablation_' if args.ablation else ''}{tag}.json").write_text(
        json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
