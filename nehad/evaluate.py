"""`nehad eval`: render a split of the dataset with a trained run and score it (docs/design.md section 9):
PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS alex and vgg (official [-1, 1] input convention) per frame and
mean, plus render FPS (deformation + rasterization at the dataset resolution, after a warm-up).

Every metric comes with the same metric of a *blank* image (the background colour everywhere)
against the same views: on scenes whose objects cover a few percent of the picture, a blank image
already scores 18-21 dB, so a PSNR means little without it (docs/results.md). PSNR is also
reported per quarter of the time range, so a model that fails at some times cannot hide in a
mean.

Objects: when the split has label masks (``SPLIT/masks/r_XXXX.png`` beside each image, uint8 ids,
0 = background, names in the dataset's ``class_mapping.json``: the MuJoCo layout), every id other
than 0 that occurs in the split's masks is scored on its own ground-truth pixels: PSNR of the
render and of the blank image, per time quarter (the bins above) and over all frames. A whole-image
PSNR hides an object that is not drawn at all when it is small (issue 25: a sphere absent from
every render while the scene scored +8 dB over blank), so:

- Pixels: the eval runs at the training resolution (``data.downscale`` f), and a label mask is
  brought there with the blocks the images were averaged over (f x f, remainder cropped,
  ``nehad.data.dnerf._area_downscale``): a low-resolution pixel belongs to an object when the
  object covers at least half of its block (area coverage >= 0.5); if two objects cover exactly
  half each, the lower id takes it, so objects never share a pixel. Pixels with coverage under
  0.5 (mostly another object or the background) are left out.
- Pooling: the squared error (RGB clipped to [0, 1], mean over the 3 channels) is summed over all
  the object's pixels in all frames of a quarter, then turned into one PSNR, so every object pixel
  weighs the same and a frame where the object covers a handful of pixels cannot swing the score.
  PSNR is capped at 100 dB (zero error).
- A quarter where the object has fewer than OBJECT_MIN_PIXELS (16) pixels summed over its frames
  is not scored (psnr null, "skipped" says why); its pixels still count in the object's total.
- An object whose gain over blank in some scored quarter is under OBJECT_WARN_GAIN (+3 dB) is
  named in a warning line (`object_warnings`), printed last by `format_table` and `nehad eval`.
- The *unlabelled foreground*: where the images have alpha, the opaque target pixels (alpha >= 0.5)
  that no label covers, scored the same way as one more row ("unlabelled" in metrics.json). On
  the MuJoCo scenes that is the floor and the shadows the objects cast on it, which move with
  them and hold a quarter to two fifths of a trained model's squared error (docs/results.md,
  2026-11-27). It is not an object: it never gets a warning and is not the worst object.

Writes RUN/eval_SPLIT/metrics.json and the renders RUN/eval_SPLIT/r_XXX.png (atomically).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from nehad.data.loader import load_dataset
from nehad.metrics.image import psnr_of_mse
from nehad.model import RunError, cloud_at, load_run

METRIC_KEYS = ("psnr", "ssim", "ms_ssim", "d_ssim", "lpips_alex", "lpips_vgg")
TIME_BINS = 4  # PSNR per quarter of the time range
OBJECT_MIN_PIXELS = 16  # an object-quarter with fewer pixels (over all its frames) is not scored
OBJECT_WARN_GAIN = 3.0  # dB over blank on the object's pixels; below it the object is "missing"
OBJECT_COVERAGE = 0.5  # a low-resolution pixel is the object's when it covers >= this of its block
PSNR_CAP = 100.0  # dB, the PSNR of a zero error
UNLABELLED_NAME = "unlabelled foreground"  # the opaque pixels no label covers (module doc)


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


# ------------------------------------------------------------------------------------------
# objects (label masks): see the module doc


def object_label_map(labels, width: int, height: int) -> np.ndarray:
    """(height, width) int32 ids of a full-resolution label mask brought to the eval resolution:
    a pixel is an object's when the object covers >= OBJECT_COVERAGE of its f x f block (the
    image loader's blocks: integer factor f, right/bottom remainder cropped); ties between two
    objects go to the lower id; 0 elsewhere."""
    from nehad.data.common import area_downscale

    labels = np.asarray(labels)
    h, w = labels.shape[:2]
    f = w // width if width > 0 else 0
    if f < 1 or w // f != width or h // f != height:
        raise ValueError(f"a {w}x{h} label mask does not match a {width}x{height} image by an "
                         f"integer downscale")
    if f == 1:
        return np.ascontiguousarray(labels[:height, :width], dtype=np.int32)
    out = np.zeros((height, width), np.int32)
    best = np.zeros((height, width), np.float32)
    for i in np.unique(labels):
        if i == 0:
            continue
        cov = area_downscale((labels == i)[:, :, None].astype(np.float32), f)[:, :, 0]
        take = (cov >= OBJECT_COVERAGE) & (cov > best)  # ascending ids: a tie keeps the lower
        out[take] = int(i)
        best[take] = cov[take]
    return out


def object_errors(label_map, rgb, truth, background) -> dict[int, tuple[int, float, float]]:
    """Per object id in `label_map`: (pixels, summed squared error of `rgb`, of the blank image)
    against `truth` on the object's pixels; squared error = mean over RGB, values clipped to
    [0, 1] as in the image metrics."""
    lab = np.asarray(label_map)
    a = np.clip(np.asarray(rgb, np.float64)[:, :, :3], 0.0, 1.0)
    t = np.clip(np.asarray(truth, np.float64)[:, :, :3], 0.0, 1.0)
    bg = np.clip(np.asarray(background, np.float64).reshape(1, 1, 3), 0.0, 1.0)
    err = ((a - t) ** 2).mean(-1)
    berr = ((bg - t) ** 2).mean(-1)
    out = {}
    for i in np.unique(lab):
        if i == 0:
            continue
        m = lab == i
        out[int(i)] = (int(m.sum()), float(err[m].sum()), float(berr[m].sum()))
    return out


def unlabelled_errors(label_map, alpha, rgb, truth, background) -> tuple[int, float, float]:
    """(pixels, summed squared error of `rgb`, of the blank image) on the unlabelled foreground:
    label 0 where the target's `alpha` >= 0.5 (the module doc), as `object_errors` scores."""
    fg = (np.asarray(label_map) == 0) & (np.asarray(alpha).reshape(np.shape(label_map)) >= 0.5)
    return object_errors(fg.astype(np.int32), rgb, truth, background).get(1, (0, 0.0, 0.0))


def pooled_psnr(sse: float, pixels: int) -> float:
    """PSNR of a summed squared error over `pixels` pixels (capped at PSNR_CAP)."""
    return min(psnr_of_mse(sse / pixels), PSNR_CAP)


def _object_score(pixels: int, sse: float, bsse: float, min_pixels: int) -> dict:
    if pixels < max(min_pixels, 1):
        return {"pixels": pixels, "psnr": None, "blank_psnr": None, "gain": None,
                "skipped": f"fewer than {min_pixels} object pixels"}
    p, b = pooled_psnr(sse, pixels), pooled_psnr(bsse, pixels)
    return {"pixels": pixels, "psnr": p, "blank_psnr": b, "gain": p - b}


def frame_objects(record: dict, names: dict) -> dict:
    """{object name: score} of one frame's object record (`_frame_object_record`): each object
    with a pixel at the eval resolution, scored on its pixels in that frame alone (metrics.json's
    per_frame entries; a quarter pools its frames, `summarize_objects`, and scores only from
    OBJECT_MIN_PIXELS pixels, where a frame's score of a few pixels is only informative). It
    shows which frames of a quarter lose an object: for example the first after a run of
    training times, or the ones further into a held-out gap."""
    return {names.get(i, f"id {i}"): _object_score(*record["errors"][i], 1)
            for i in sorted(record["errors"])}


def summarize_objects(records: list[dict], names: dict, time_range, bins: int = TIME_BINS,
                      min_pixels: int = OBJECT_MIN_PIXELS) -> list[dict]:
    """Per-object scores from per-frame records {"time", "ids": [ids present in the full-size
    mask], "errors": object_errors(...)}: one entry per id present in some frame, with its pooled
    PSNR, blank PSNR and gain overall and per time bin (every bin holding a frame is listed;
    one with fewer than `min_pixels` object pixels is skipped)."""
    t0, t1 = float(time_range[0]), float(time_range[1])
    ids = sorted({int(i) for r in records for i in r["ids"]} - {0})
    frame_bins = [time_bin(r["time"], time_range, bins) for r in records]
    objects = []
    for i in ids:
        tot = np.zeros(3)
        per_bin = []
        for b in range(bins):
            members = [r for r, fb in zip(records, frame_bins) if fb == b]
            if not members:
                continue
            acc = np.zeros(3)
            for r in members:
                acc += r["errors"].get(i, (0, 0.0, 0.0))
            tot += acc
            per_bin.append({"range": [t0 + (t1 - t0) * b / bins, t0 + (t1 - t0) * (b + 1) / bins],
                            "frames": len(members),
                            **_object_score(int(acc[0]), acc[1], acc[2], min_pixels)})
        overall = _object_score(int(tot[0]), tot[1], tot[2], min_pixels)
        overall.pop("skipped", None)
        objects.append({"id": i, "name": names.get(i, f"object {i}"), **overall,
                        "time_bins": per_bin})
    return objects


def worst_object_bin(objects: list[dict]) -> dict | None:
    """The scored object-quarter with the lowest gain over blank ({"id", "name", "range",
    "pixels", "psnr", "blank_psnr", "gain"}), None when none was scored."""
    cands = [(o, tb) for o in objects for tb in o["time_bins"] if tb.get("gain") is not None]
    if not cands:
        return None
    o, tb = min(cands, key=lambda c: c[1]["gain"])
    return {"id": o["id"], "name": o["name"], "range": tb["range"], "pixels": tb["pixels"],
            "psnr": tb["psnr"], "blank_psnr": tb["blank_psnr"], "gain": tb["gain"]}


def object_warnings(result_or_objects, threshold: float = OBJECT_WARN_GAIN) -> list[str]:
    """One line per object whose gain over blank is under `threshold` in some scored quarter,
    e.g. ``warning: sphere missing in t 0.00-0.25 (+0.4 dB over blank on its pixels)``."""
    objects = (result_or_objects.get("objects") or [] if isinstance(result_or_objects, dict)
               else result_or_objects)
    lines = []
    for o in objects:
        bad = [tb for tb in o["time_bins"] if tb.get("gain") is not None
               and tb["gain"] < threshold]
        if bad:
            where = ", ".join(f"t {tb['range'][0]:.2f}-{tb['range'][1]:.2f}" for tb in bad)
            gains = ", ".join(f"{tb['gain']:+.1f}" for tb in bad)
            lines.append(f"warning: {o['name']} missing in {where} ({gains} dB over blank on "
                         f"its pixels)")
    return lines


def _object_masks(data: Path, split: str, frames) -> tuple[dict, list[tuple]] | None:
    """(names, (ids, label map) per frame: `_label_map`) when the split has label masks, else
    None. Every mask is read here, before anything is rendered: a frame without its mask, a mask
    that cannot be read or does not fit its image, and a masks folder without a mask beside
    class_mapping.json are errors (a partial score would hide objects)."""
    from nehad.viz import VizError
    from nehad.viz.masks import class_names, has_label_masks, mask_path

    folder, mapping = data / split / "masks", data / "class_mapping.json"
    if not has_label_masks(data, split):
        if folder.is_dir() and mapping.is_file():
            raise RunError(f"{folder}: holds no label masks (*.png), but {mapping} names "
                           f"objects; put the {split} frames' masks there or remove the folder")
        return None
    paths = [mask_path(f.path) for f in frames]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise RunError(f"{missing[0]}: label mask not found ({len(missing)} of the {len(paths)} "
                       f"{split} frames have none, but {data / split / 'masks'} exists)")
    try:
        names = class_names(data)
    except VizError as e:
        raise RunError(str(e)) from None
    return names, [_label_map(path, frame) for path, frame in zip(paths, frames)]


def _label_map(path: Path, frame) -> tuple[list[int], np.ndarray]:
    """(the ids other than 0 in the label mask at `path`, its `object_label_map` at the frame's
    size), else a RunError naming the mask."""
    from nehad.viz import VizError
    from nehad.viz.masks import read_label_mask

    try:
        labels = read_label_mask(path)
        h, w = frame.image.shape[:2]
        lab = object_label_map(labels, w, h)
    except (VizError, ValueError) as e:
        text = str(e)
        raise RunError(text if text.startswith(str(path)) else f"{path}: {text}") from None
    return [int(i) for i in np.unique(labels) if i != 0], lab


def _frame_object_record(mask: tuple[list[int], np.ndarray], frame, rgb, background) -> dict:
    """One frame's object scores against its checked mask (`_label_map`)."""
    ids, lab = mask
    rest = (None if frame.alpha is None
            else unlabelled_errors(lab, frame.alpha, rgb, frame.image, background))
    return {"time": frame.camera.time, "ids": ids,
            "errors": object_errors(lab, rgb, frame.image, background), "unlabelled": rest}


def _atomic_json(path: Path, obj) -> None:
    from nehad.runtime.images import atomic_write_bytes

    atomic_write_bytes(path, json.dumps(obj, indent=1).encode())


def evaluate_run(run_dir, split: str = "test", data_dir=None, lpips: bool = True,
                 write_renders: bool = True, progress: bool = True, max_frames: int = 0) -> dict:
    """Render `split` (its first `max_frames` frames when > 0) with the run, score every frame
    and write RUN/eval_SPLIT/metrics.json (and the renders); returns what it wrote."""
    run = Path(run_dir)
    model, info = load_run(run)
    data, frames = _eval_frames(run, info, split, data_dir, max_frames)
    masks = _object_masks(data, split, frames)
    out_dir = run / f"eval_{split}"
    made = not out_dir.exists()
    out_dir.mkdir(exist_ok=True)
    try:
        per_frame, object_records, render_seconds = _render_and_score(
            model, info, split, frames, masks, out_dir if write_renders else None, lpips, progress)
    except BaseException:  # a bad frame or mask, an interrupt: no empty folder left behind
        if made and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    h, w = frames[0].image.shape[:2]
    time_range = list(info.time_range)
    result = {
        "run": str(run), "split": split, "frames": len(per_frame), "resolution": [w, h],
        "gaussians": len(model.gaussians), **summarize(per_frame, time_range),
        "background": list(info.background), "per_frame": per_frame,
        "fps": len(per_frame) / render_seconds if render_seconds > 0 else None,
        "fps_threads": {"torch": torch.get_num_threads(), "numba": _numba_threads()},
        "lpips_input": "[-1, 1] (official lpips convention; 3DGS/4DGS code fed [0, 1])",
    }
    if masks is not None:
        result.update(_objects_result(object_records, masks[0], time_range, split))
        for record, objects in zip(per_frame, object_records):
            record["objects"] = frame_objects(objects, masks[0])
    _atomic_json(out_dir / "metrics.json", result)
    return result


def _eval_frames(run: Path, info, split: str, data_dir, max_frames: int) -> tuple[Path, list]:
    """(dataset folder, the frames of `split` to evaluate), loaded as the run was trained: same
    background, downscale and frame stride."""
    cfg = info.config
    data = Path(data_dir) if data_dir is not None else Path(info.data_dir or "")
    if not data.is_dir():
        raise RunError(f"{run}: dataset folder {data} not found; pass --data DIR")
    scene = load_dataset(data, splits=(split,), background=info.background,
                         downscale=cfg.data.downscale, frame_stride=cfg.data.frame_stride)
    frames = scene.frames[split]
    if max_frames > 0:
        frames = frames[:max_frames]
    return data, frames


def _render_and_score(model, info, split: str, frames, masks, render_dir: Path | None,
                      lpips: bool, progress: bool) -> tuple[list[dict], list[dict], float]:
    """Render every frame (after an untimed warm-up) and score it beside the blank image:
    (per-frame records, per-frame object records when `masks`, seconds spent rendering).
    The renders are written to `render_dir` unless it is None."""
    from tqdm import tqdm

    from nehad.runtime.images import write_image
    from nehad.runtime.raster import render

    background = info.background
    degree = info.degree_for(model)
    # warm-up: JIT and caches, not timed
    render(cloud_at(model, frames[0].camera.time, degree), frames[0].camera, background)
    per_frame, object_records, render_seconds = [], [], 0.0
    blank_image = np.broadcast_to(np.asarray(background, np.float32), frames[0].image.shape)
    for i, frame in enumerate(tqdm(frames, desc=f"eval {split}", disable=not progress)):
        t0 = time.perf_counter()
        cloud = cloud_at(model, frame.camera.time, degree)
        rgb = render(cloud, frame.camera, background).rgb
        render_seconds += time.perf_counter() - t0
        per_frame.append(_frame_record(i, frame, rgb, blank_image, lpips))
        if masks is not None:
            object_records.append(_frame_object_record(masks[1][i], frame, rgb, background))
        if render_dir is not None:
            write_image(render_dir / f"r_{i:03d}.png", rgb)
    return per_frame, object_records, render_seconds


def _frame_record(i: int, frame, rgb, blank_image, lpips: bool) -> dict:
    """The metrics of one frame's render and of the blank image (``blank_`` keys) against it
    (LPIPS of both in one network pass per net, the blank image's features kept from the
    first frame: `nehad.metrics.lpips_scores`)."""
    from nehad.metrics import image_metrics, lpips_scores

    nets = ("alex", "vgg") if lpips else ()
    scores = image_metrics(rgb, frame.image, lpips_nets=())
    blank = image_metrics(blank_image, frame.image, lpips_nets=())
    if nets:
        both = lpips_scores([rgb, blank_image], frame.image, nets, require_lpips=True,
                            recurring=(1,))
        for out, lp in zip((scores, blank), both):
            out.update(lp)
    record = {"frame": i, "file": frame.path.name, "time": frame.camera.time}
    record.update({k: scores.get(k) for k in METRIC_KEYS})
    record.update({f"blank_{k}": blank.get(k) for k in METRIC_KEYS})
    return record


def _objects_result(object_records: list[dict], names: dict, time_range, split: str) -> dict:
    """The per-object entries of metrics.json: scores, worst quarter, warnings and rules."""
    objects = summarize_objects(object_records, names, time_range)
    rest = [{"time": r["time"], "ids": [1], "errors": {1: r["unlabelled"]}}
            for r in object_records if r.get("unlabelled") is not None]
    unlabelled = (summarize_objects(rest, {1: UNLABELLED_NAME}, time_range)[0]
                  if len(rest) == len(object_records) and rest else None)
    if unlabelled is not None:
        unlabelled.pop("id")
    return {
        "objects": objects, "worst_object_bin": worst_object_bin(objects),
        "object_warnings": object_warnings(objects), "unlabelled": unlabelled,
        "object_rules": {
            "masks": f"{split}/masks/*.png, names from class_mapping.json",
            "pixel": f"area coverage >= {OBJECT_COVERAGE:g} of the pixel's block at the eval "
                     f"resolution (ties to the lower id)",
            "pooling": "squared error summed over the object's pixels of all frames in the "
                       "quarter, then one PSNR",
            "min_pixels": OBJECT_MIN_PIXELS, "warn_gain_db": OBJECT_WARN_GAIN}}


def _numba_threads() -> int:
    import numba

    return int(numba.get_num_threads())


def format_objects(result: dict) -> list[str]:
    """Lines of the per-object table: PSNR on each object's pixels, model and blank over all
    frames, and the gain over blank per time quarter ('!' marks a gain under OBJECT_WARN_GAIN,
    '-' a quarter with too few object pixels)."""
    objects = result.get("objects") or []
    if not objects:
        return []
    rest = result.get("unlabelled")
    rules = result.get("object_rules") or {}
    warn = rules.get("warn_gain_db", OBJECT_WARN_GAIN)
    ranges = [tb["range"] for tb in max(objects, key=lambda o: len(o["time_bins"]))["time_bins"]]
    width = max(14, *(len(o["name"]) + 2 for o in objects + ([rest] if rest else [])))
    fmt = lambda v, d: "n/a" if v is None else f"{v:.{d}f}"
    lines = ["  Objects: PSNR on each one's own pixels, model / blank; gain per time quarter:",
             f"    {'object':<{width}}{'model':>7}{'blank':>7}{'gain':>8}"
             + "".join(f"{f'{a:.2f}-{b:.2f}':>11}" for a, b in ranges)]
    for o in objects + ([rest] if rest else []):
        cells = []
        by_range = {tuple(tb["range"]): tb for tb in o["time_bins"]}
        for r in ranges:
            tb = by_range.get(tuple(r))
            if tb is None or tb.get("gain") is None:
                cells.append("-")
            else:
                low = tb["gain"] < warn and o is not rest
                cells.append(f"{tb['gain']:+.1f}" + ("!" if low else " "))
        gain = "n/a" if o.get("gain") is None else f"{o['gain']:+.2f}"
        lines.append(f"    {o['name']:<{width}}{fmt(o.get('psnr'), 2):>7}"
                     f"{fmt(o.get('blank_psnr'), 2):>7}{gain:>8}"
                     + "".join(f"{c:>11}" for c in cells).rstrip())
    lines.append(f"    (! gain under +{warn:g} dB; - fewer than "
                 f"{rules.get('min_pixels', OBJECT_MIN_PIXELS)} object pixels in the quarter)")
    if rest:
        lines.append(f"    ({UNLABELLED_NAME}: opaque pixels no label covers, e.g. a floor and "
                     f"its shadows; never warned on)")
    return lines


def format_table(result: dict, warnings: bool = True) -> str:
    """The eval summary as text: each metric beside its blank-image baseline, PSNR per time
    bin, the per-object table (when the split has label masks), render speed, and last the
    warning lines of objects missing in some quarter (`warnings=False` leaves them out, for a
    caller that prints them itself)."""
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
    lines += format_objects(result)
    lines.append(f"  render {fmt(result['fps'], 1)} FPS (deformation + rasterization, "
                 f"{result['fps_threads']['numba']} threads)")
    if warnings:
        lines += object_warnings(result)
    return "\n".join(lines)
