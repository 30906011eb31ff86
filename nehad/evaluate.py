"""`nehad eval`: render a split of the dataset with a trained run and score it (docs/design.md section 9):
PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS alex and vgg (official [-1, 1] input convention) per frame and
mean, plus render FPS (deformation + rasterization at the dataset resolution, after a warm-up).

Every metric comes with the same metric of a *blank* image (the background colour everywhere)
against the same views: on scenes whose objects cover a few percent of the picture, a blank image
already scores 18-21 dB, so a PSNR means little without it (docs/results.md). PSNR is also
reported per quarter of the time range, so a model that fails at some times cannot hide in a
mean.

Writes RUN/eval_SPLIT/metrics.json and the renders RUN/eval_SPLIT/r_XXX.png (atomically).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from nehad.config import config_from_dict
from nehad.data.loader import load_dataset
from nehad.trainer import RunError, cloud_at, load_run

METRIC_KEYS = ("psnr", "ssim", "ms_ssim", "d_ssim", "lpips_alex", "lpips_vgg")
TIME_BINS = 4  # PSNR per quarter of the time range


def time_bin(t: float, time_range, bins: int = TIME_BINS) -> int:
    """Index of the bin of [t0, t1] (split in `bins` equal parts) that holds t."""
    t0, t1 = float(time_range[0]), float(time_range[1])
    if t1 <= t0:
        return 0
    return int(min(max((t - t0) / (t1 - t0) * bins, 0), bins - 1))


def _mean(records: list[dict], key: str):
    vals = [r[key] for r in records if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def summarize(per_frame: list[dict], time_range, bins: int = TIME_BINS) -> dict:
    """Means of the per-frame scores and of their blank baselines, the gain in PSNR, and PSNR
    per time bin ({"range": [a, b], "frames", "psnr", "blank_psnr"}; empty bins omitted)."""
    mean = {k: _mean(per_frame, k) for k in METRIC_KEYS}
    blank = {k: _mean(per_frame, f"blank_{k}") for k in METRIC_KEYS}
    t0, t1 = float(time_range[0]), float(time_range[1])
    out_bins = []
    for b in range(bins):
        members = [r for r in per_frame if time_bin(r["time"], time_range, bins) == b]
        if not members:
            continue
        out_bins.append({"range": [t0 + (t1 - t0) * b / bins, t0 + (t1 - t0) * (b + 1) / bins],
                         "frames": len(members), "psnr": _mean(members, "psnr"),
                         "blank_psnr": _mean(members, "blank_psnr")})
    gain = None if mean["psnr"] is None or blank["psnr"] is None else mean["psnr"] - blank["psnr"]
    worst = min(out_bins, key=lambda b: b["psnr"] - b["blank_psnr"]) if out_bins else None
    return {"mean": mean, "blank": blank, "psnr_gain": gain, "time_bins": out_bins,
            "worst_time_bin": worst}


def _atomic_json(path: Path, obj) -> None:
    from nehad.runtime.images import atomic_write_bytes

    atomic_write_bytes(path, json.dumps(obj, indent=1).encode())


def evaluate_run(run_dir, split: str = "test", data_dir=None, lpips: bool = True,
                 write_renders: bool = True, progress: bool = True, max_frames: int = 0) -> dict:
    from tqdm import tqdm

    from nehad.metrics import image_metrics
    from nehad.runtime.images import write_image
    from nehad.runtime.raster import render

    run = Path(run_dir)
    model, meta = load_run(run)
    cfg = config_from_dict(meta["config"])
    data = Path(data_dir) if data_dir is not None else Path(meta.get("data_dir", ""))
    if not data.is_dir():
        raise RunError(f"{run}: dataset folder {data} not found; pass --data DIR")
    background = tuple(float(v) for v in meta["background"])
    scene = load_dataset(data, splits=(split,), background=background,
                         downscale=cfg.data.downscale, frame_stride=cfg.data.frame_stride)
    frames = scene.frames[split]
    if max_frames > 0:
        frames = frames[:max_frames]
    out_dir = run / f"eval_{split}"
    out_dir.mkdir(exist_ok=True)
    degree = int(meta["sh_degree"])

    # warm-up: JIT and caches, not timed
    render(cloud_at(model, frames[0].camera.time, degree), frames[0].camera, background)
    per_frame, render_seconds = [], 0.0
    blank_image = np.broadcast_to(np.asarray(background, np.float32), frames[0].image.shape)
    for i, frame in enumerate(tqdm(frames, desc=f"eval {split}", disable=not progress)):
        t0 = time.perf_counter()
        cloud = cloud_at(model, frame.camera.time, degree)
        rgb = render(cloud, frame.camera, background).rgb
        render_seconds += time.perf_counter() - t0
        scores = image_metrics(rgb, frame.image, require_lpips=lpips,
                               lpips_nets=("alex", "vgg") if lpips else ())
        blank = image_metrics(blank_image, frame.image, require_lpips=lpips,
                              lpips_nets=("alex", "vgg") if lpips else ())
        record = {"frame": i, "file": frame.path.name, "time": frame.camera.time}
        record.update({k: scores.get(k) for k in METRIC_KEYS})
        record.update({f"blank_{k}": blank.get(k) for k in METRIC_KEYS})
        per_frame.append(record)
        if write_renders:
            write_image(out_dir / f"r_{i:03d}.png", rgb)
    h, w = frames[0].image.shape[:2]
    time_range = meta.get("time_range") or [0.0, 1.0]
    result = {
        "run": str(run), "split": split, "frames": len(per_frame), "resolution": [w, h],
        "gaussians": len(model.gaussians), **summarize(per_frame, time_range),
        "background": list(background), "per_frame": per_frame,
        "fps": len(per_frame) / render_seconds if render_seconds > 0 else None,
        "fps_threads": {"torch": torch.get_num_threads(), "numba": _numba_threads()},
        "lpips_input": "[-1, 1] (official lpips convention; 3DGS/4DGS code fed [0, 1])",
    }
    _atomic_json(out_dir / "metrics.json", result)
    return result


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


def format_table(result: dict) -> str:
    """The eval summary as text: each metric beside its blank-image baseline, PSNR per time
    bin, render speed."""
    m, b = result["mean"], result.get("blank", {})
    fmt = lambda v, d: "n/a" if v is None else f"{v:.{d}f}"
    names = [("psnr", "PSNR", 2), ("ssim", "SSIM", 4), ("ms_ssim", "MS-SSIM", 4),
             ("d_ssim", "D-SSIM", 4), ("lpips_alex", "LPIPS-alex", 4),
             ("lpips_vgg", "LPIPS-vgg", 4)]
    lines = [f"{result['split']}: {result['frames']} frames at {result['resolution'][0]}x"
             f"{result['resolution'][1]}, {result['gaussians']} Gaussians",
             f"  {'metric':<11}{'model':>9}{'blank':>9}"]
    for key, label, d in names:
        lines.append(f"  {label:<11}{fmt(m.get(key), d):>9}{fmt(b.get(key), d):>9}")
    if result.get("psnr_gain") is not None:
        lines.append(f"  PSNR gain over the blank image: {result['psnr_gain']:+.2f} dB")
    bins = result.get("time_bins") or []
    if bins:
        lines.append("  PSNR by time (model / blank):")
        for tb in bins:
            lines.append(f"    t {tb['range'][0]:.2f}-{tb['range'][1]:.2f} ({tb['frames']:>2} "
                         f"frames)  {fmt(tb['psnr'], 2)} / {fmt(tb['blank_psnr'], 2)}  "
                         f"({tb['psnr'] - tb['blank_psnr']:+.2f})")
    lines.append(f"  render {fmt(result['fps'], 1)} FPS (deformation + rasterization, "
                 f"{result['fps_threads']['numba']} threads)")
    return "\n".join(lines)
