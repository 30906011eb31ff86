"""Where each labelled object's Gaussians are over a run's checkpoints (issue 25: why an object
vanishes: never created, pruned, starved by the cap, lost at the canonical time, ...).

    python bench/object_trace.py RUN --data DATA [--split train] [--frames 24]

For each checkpoint of RUN (keep them with --set train.keep_checkpoints=50) and each labelled
object of the dataset (``SPLIT/masks`` + ``class_mapping.json``), over `--frames` frames of the
split spread over the time range: the number of Gaussians whose centre at the frame's time
projects inside the object's mask with opacity >= 0.1 (median over the frames where the object
is visible), and the object's PSNR gain over a blank image on its own pixels (pooled over those
frames); split by the frames inside / outside the run's coarse time window. Prints one line per
checkpoint; with --json also writes the table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def trace(run: Path, data: Path | None, split: str, n_frames: int) -> list[dict]:
    from nehad.checkpoint import list_checkpoints, load_state
    from nehad.data.loader import load_dataset
    from nehad.evaluate import object_label_map
    from nehad.runtime.raster import render
    from nehad.model import cloud_at, model_from_state
    from nehad.viz.masks import class_names, mask_path, read_label_mask

    cfg0 = load_state(list_checkpoints(run)[0])["config"]
    if data is None or not data.is_dir():
        raise SystemExit("--data DIR: the run's dataset folder (checkpoints do not name it)")
    downscale = int(cfg0["data"]["downscale"])
    scene = load_dataset(data, splits=(split,), background=(1.0, 1.0, 1.0), downscale=downscale)
    frames = scene.frames[split]
    pick = np.unique(np.linspace(0, len(frames) - 1, n_frames).round().astype(int))
    frames = [frames[i] for i in pick]
    masks = [object_label_map(read_label_mask(mask_path(f.path)), f.camera.width,
                              f.camera.height) for f in frames]  # nehad eval's pixel rule
    names = class_names(data)
    ids = sorted(i for i in names if i != 0)
    coarse_iters = int(cfg0["coarse"]["iterations"])
    canonical = float(cfg0["train"]["canonical_time"])
    half = float(cfg0["coarse"]["time_window"])
    rows = []
    for ck in list_checkpoints(run):
        state = load_state(ck)
        step = int(state["step"])
        model = model_from_state(state)
        deform = step > coarse_iters
        row = {"step": step, "gaussians": len(model.gaussians), "objects": {}}
        per = {i: {"n": [], "se": [0.0, 0.0], "blank": [0.0, 0.0], "px": [0, 0]} for i in ids}
        for f, m in zip(frames, masks):
            t = f.time if deform else None
            cloud = cloud_at(model, t, 3)
            rgb = render(cloud, f.camera, (1.0, 1.0, 1.0)).rgb
            uv, z = f.camera.project(cloud.means)
            ok = (z > 0) & (cloud.opacities >= 0.1)
            u = np.floor(uv[:, 0]).astype(int)
            v = np.floor(uv[:, 1]).astype(int)
            inside = ok & (u >= 0) & (v >= 0) & (u < m.shape[1]) & (v < m.shape[0])
            lab = np.zeros(len(u), int)
            lab[inside] = m[v[inside], u[inside]]
            near = 0 if abs(f.time - canonical) <= half else 1
            for i in ids:
                pix = m == i
                if pix.sum() < 4:
                    continue
                o = per[i]
                o["n"].append(int((lab == i).sum()))
                o["se"][near] += float(((rgb[pix] - f.image[pix]) ** 2).sum())
                o["blank"][near] += float(((1.0 - f.image[pix]) ** 2).sum())
                o["px"][near] += int(pix.sum()) * 3
        for i in ids:
            o = per[i]
            gains = []
            for k in (0, 1):
                if o["px"][k] == 0 or o["se"][k] == 0:
                    gains.append(None)
                    continue
                gains.append(10 * np.log10(o["blank"][k] / o["se"][k]))
            row["objects"][names[i]] = {
                "gaussians_median": float(np.median(o["n"])) if o["n"] else None,
                "gaussians_min": int(min(o["n"])) if o["n"] else None,
                "gain_in_window": gains[0], "gain_outside": gains[1]}
        rows.append(row)
        fmt = lambda v: "  n/a" if v is None else f"{v:+5.1f}"
        parts = [f"{name}: n={d['gaussians_median']:.0f} (min {d['gaussians_min']}) "
                 f"gain win {fmt(d['gain_in_window'])} out {fmt(d['gain_outside'])}"
                 for name, d in row["objects"].items() if d["gaussians_median"] is not None]
        print(f"step {step:>6} N={row['gaussians']:>6}  " + " | ".join(parts), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("--data", type=Path, default=None)
    p.add_argument("--split", default="train")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    rows = trace(a.run, a.data, a.split, a.frames)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
