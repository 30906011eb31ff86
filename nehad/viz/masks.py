"""The Boltzmann equilibrium split (paper Sec. "Boltzmann Equilibrium Decomposition", docs/design.md section 4.7):
which Gaussians BED lets the deformation move at time t, how that looks, and how well it matches
the objects that really move.

Per Gaussian i the position mask is M_pos = (1 - gamma) exp(-beta E_st) + gamma and the deformed
mean mu' = mu + dmu (1 - M_pos): the BED weight ``w = 1 - M_pos`` is the share of the predicted
displacement that is applied (0 = held static, up to 1 - gamma = fully dynamic). The weights come
from :func:`nehad.field.bed.bed_masks`, the function the deformation field itself calls, so this
module repeats none of the formula.

- :func:`bed_weights` (torch): w per Gaussian at t; :func:`dynamic_fraction` over times.
- :func:`render_weights`: a render in which each Gaussian's colour is its weight; dividing by the
  rendered alpha gives the opacity-weighted mean weight of the Gaussians seen in each pixel.
- Scoring: a pixel is predicted dynamic when the render covers it (alpha > 0.5) and its weight
  exceeds a threshold (0.5); ground truth is the union of the moving objects' masks. IoU,
  precision and recall (pixel counts summed over the frames), the mean weight on moving and on
  static foreground pixels, and the AUC (the probability that a random moving pixel has a higher
  weight than a random static foreground pixel; threshold-free; 0.5 = no separation).
- Ground truth: MuJoCo scenes have per-object label masks (``{split}/masks/r_XXXX.png``, ids in
  ``class_mapping.json``, 0 = background, the floor is background in the labels but foreground in
  the alpha). Which objects move is read off the train masks: frames taken by the same fixed
  camera are compared, and an object whose mask changes (IoU < 0.95 between two of its frames)
  moves. A scene of ``nehad synth`` is recognised from its images, and its masks are ray cast
  from the generator's scene description (objects whose pose changes over time move).

The torch model is needed (an exported .onnx file has no mask output); torch is imported only by
the functions that use the model.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nehad.runtime.gaussians import SH_C0, GaussianCloud

from . import VizError
from .plots import colorbar, line_plot, weight_colors

if TYPE_CHECKING:
    from nehad.model import RunInfo

DEFAULT_THRESHOLD = 0.5
ALPHA_MIN = 0.5  # a pixel counts as covered (rendered or in the ground truth) above this
MOVING_IOU = 0.95  # an object whose masks from one camera overlap less than this moves
_BINS = 1024  # histogram bins of per-pixel weights for the AUC


# ------------------------------------------------------------------------------------------
# BED weights from the torch model


def bed_status(model) -> str | None:
    """None when the model has BED position masks, else why not (a phrase)."""
    cfg = model.field.cfg
    if cfg.decoder != "hnn":
        return f"its decoder is {cfg.decoder!r} (the 4DGS baseline has no BED)"
    if not cfg.bed_position:
        return "it was trained with field.bed_position=false"
    return None


def bed_weights(model, t: float) -> np.ndarray:
    """BED weights w = 1 - M_pos (N,) float32 of the run's Gaussians at time t."""
    import torch

    from nehad.field.bed import bed_masks
    from nehad.field.deformation import time_column

    why = bed_status(model)
    if why is not None:
        raise VizError(f"this run has no BED position mask: {why}")
    g, field = model.gaussians, model.field
    with torch.no_grad():
        if field.cfg.bed_distance == "deformed":  # the mask depends on the field's displacement
            sh = torch.cat([g.sh_dc, g.sh_rest], 1)
            m_pos = field(g.means, g.log_scales, g.quats, float(t), g.mu_eq, g.t_eq,
                          opacity_logits=g.opacity_logits, sh=sh).aux["m_pos"]
        else:
            t_col = time_column(float(t), g.means.shape[0], g.means)
            m_pos, _ = bed_masks(g.means, g.mu_eq, t_col, g.t_eq.reshape(-1, 1), field.cfg,
                                 float(field.extent))
    return (1.0 - m_pos.reshape(-1)).cpu().numpy().astype(np.float32)


def dynamic_fraction(model, times, threshold: float = DEFAULT_THRESHOLD,
                     weighted: bool = False) -> np.ndarray:
    """Per time, the fraction of Gaussians whose weight exceeds `threshold` (or, `weighted`,
    the mean weight)."""
    out = []
    for t in np.asarray(times, np.float64).reshape(-1):
        w = bed_weights(model, float(t))
        out.append(float(w.mean()) if weighted else float((w > threshold).mean()))
    return np.asarray(out)


# ------------------------------------------------------------------------------------------
# rendering the weights (torch-free)


def weight_cloud(cloud: GaussianCloud, weights) -> GaussianCloud:
    """The same Gaussians with colour = weight on every channel (SH degree 0)."""
    w = np.asarray(weights, np.float32).reshape(-1)
    if w.shape[0] != len(cloud):
        raise VizError(f"weights: {w.shape[0]} values for {len(cloud)} Gaussians")
    dc = ((w - 0.5) / SH_C0)[:, None, None] * np.ones((1, 1, 3), np.float32)
    return GaussianCloud(cloud.means, cloud.scales, cloud.quats, cloud.opacities, dc)


def render_weights(cloud: GaussianCloud, weights, camera) -> tuple[np.ndarray, np.ndarray]:
    """(weight map (H, W), alpha (H, W)): the opacity-weighted mean weight of the Gaussians in
    each pixel (sum w a T / alpha; NaN where nothing is drawn) and the render's alpha."""
    from nehad.runtime.raster import render

    out = render(weight_cloud(cloud, weights), camera, background=(0.0, 0.0, 0.0))
    alpha = out.alpha.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        wmap = np.where(alpha > 1e-6, out.rgb[:, :, 0] / np.maximum(alpha, 1e-12), np.nan)
    return np.clip(wmap, 0.0, 1.0).astype(np.float32), alpha


def weight_image(weight_map, alpha, background=(1.0, 1.0, 1.0), legend: bool = True) -> np.ndarray:
    """A picture of a weight map: blue static, grey, red dynamic, over `background` by the
    render's alpha; with `legend`, a colour bar below. Float RGB in [0, 1]."""
    col = weight_colors(np.nan_to_num(weight_map, nan=0.0))
    a = np.clip(np.asarray(alpha, np.float32), 0.0, 1.0)[..., None]
    img = col * a + np.asarray(background, np.float32) * (1.0 - a)
    if legend:
        w = img.shape[1]
        bar = colorbar(w, 34 if w >= 160 else 30, weight_colors, "static", "dynamic")
        img = np.concatenate([img, bar], axis=0)
    return img.astype(np.float32)


def fraction_plot(times, fractions, threshold: float = DEFAULT_THRESHOLD, mean_weight=None,
                  size=(640, 300)) -> np.ndarray:
    """Plot of the fraction of dynamic Gaussians (and optionally the mean weight) over time."""
    series = [{"x": times, "y": fractions, "label": f"fraction with w > {threshold:g}",
               "markers": len(times) <= 40}]
    if mean_weight is not None:
        series.append({"x": times, "y": mean_weight, "label": "mean weight w"})
    return line_plot(series, title="BED: dynamic Gaussians over time", xlabel="time t",
                     ylabel="fraction", size=size, ylim=(-0.02, 1.02))


# ------------------------------------------------------------------------------------------
# ground truth: which pixels belong to moving objects


def mask_path(image_path) -> Path:
    """The label mask of an image of a MuJoCo split: ``split/masks/<name>.png``."""
    p = Path(image_path)
    return p.parent / "masks" / (p.stem + ".png")


def read_label_mask(path) -> np.ndarray:
    import cv2

    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise VizError(f"{path}: cannot read the label mask")
    if m.ndim == 3:
        m = m[:, :, 0]
    return m.astype(np.int32)


def class_names(data_dir) -> dict[int, str]:
    path = Path(data_dir) / "class_mapping.json"
    if not path.is_file():
        return {}
    try:
        return {int(k): str(v) for k, v in json.loads(path.read_text()).items()}
    except (ValueError, AttributeError, RecursionError):  # RecursionError: nested too deeply
        raise VizError(f"{path}: expected a JSON object of id -> name") from None


def has_label_masks(data_dir, split: str) -> bool:
    d = Path(data_dir) / split / "masks"
    return d.is_dir() and any(d.glob("*.png"))


def moving_object_ids(data_dir, split: str = "train", iou: float = MOVING_IOU) -> dict:
    """Which labelled objects move: {"moving": [ids], "static": [ids], "names": {id: name},
    "method": str}. Frames of `split` that share a camera pose are compared; an object moves
    when its mask in two such frames overlaps less than `iou` (IoU). Without two frames from one
    camera, every labelled object is taken as moving (and the method says so)."""
    root = Path(data_dir)
    tf = root / f"transforms_{split}.json"
    try:
        doc = json.loads(tf.read_text())
        frames = doc["frames"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        raise VizError(f"{tf}: cannot read the frames of the {split} split") from None
    names = class_names(root)
    groups = defaultdict(list)
    for f in frames:
        key = tuple(np.round(np.asarray(f["transform_matrix"], np.float64).ravel(), 5))
        groups[key].append(f)
    seen, min_iou = set(), {}
    for fs in groups.values():
        if len(fs) < 2:
            continue
        masks = [read_label_mask(mask_path(root / _with_png(f["file_path"]))) for f in fs]
        ids = set(np.unique(np.concatenate([np.unique(m) for m in masks]))) - {0}
        seen |= ids
        for i in ids:
            ref = masks[0] == i
            for m in masks[1:]:
                cur = m == i
                union = int((ref | cur).sum())
                if union:
                    v = (ref & cur).sum() / union
                    min_iou[i] = min(min_iou.get(i, 1.0), float(v))
    labelled = sorted(set(names) - {0}) or sorted(seen)
    if not min_iou:
        return {"moving": labelled, "static": [], "names": names,
                "method": "assumed: every labelled object (no two frames share a camera)"}
    moving = sorted(i for i in labelled if min_iou.get(i, 1.0) < iou)
    return {"moving": moving, "static": [i for i in labelled if i not in moving], "names": names,
            "min_iou": {int(i): round(v, 4) for i, v in sorted(min_iou.items())},
            "method": f"masks from the same camera differ (IoU < {iou:g}) in the {split} split"}


def _with_png(file_path: str) -> str:
    return file_path if Path(file_path).suffix else file_path + ".png"


def _resize_binary(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """A boolean mask at another size: area coverage > 0.5 (labels are full resolution, a run
    may render at a lower one)."""
    if mask.shape == (height, width):
        return mask.astype(bool)
    import cv2

    m = mask.astype(np.float32)
    h, w = m.shape
    if w % width == 0 and h % height == 0 and w // width == h // height:
        f = w // width
        cov = m.reshape(height, f, width, f).mean(axis=(1, 3))
    else:
        cov = cv2.resize(m, (width, height), interpolation=cv2.INTER_AREA)
    return cov > 0.5


def label_ground_truth(frame, moving_ids, width: int, height: int):
    """(moving (H, W) bool, static foreground (H, W) bool) of a MuJoCo frame: moving = any moving
    object; static foreground = covered in the image's alpha (> 0.5) and no moving object."""
    labels = read_label_mask(mask_path(frame.path))
    moving = _resize_binary(np.isin(labels, list(moving_ids)), width, height)
    if frame.alpha is not None:
        fg = np.asarray(frame.alpha) > ALPHA_MIN
        if fg.shape != moving.shape:
            fg = _resize_binary(fg, width, height)
    else:
        fg = np.ones_like(moving)
    return moving, fg & ~moving


def synth_scene_name(frame) -> str | None:
    """The `nehad synth` scene whose ray-cast alpha matches the frame's (None: not one)."""
    from nehad.data.synth import SCENES, render_view, scene_objects

    if frame.alpha is None or frame.camera.time is None:
        return None
    best, best_err = None, 0.03
    for name in SCENES:
        rgba = render_view(scene_objects(name, frame.camera.time), frame.camera, supersample=2)
        err = float(np.abs(rgba[:, :, 3] - frame.alpha).mean())
        if err < best_err:
            best, best_err = name, err
    return best


def synth_moving_objects(scene: str) -> list[bool]:
    """For each object of a `nehad synth` scene: does its pose change over [0, 1]?"""
    from nehad.data.synth import scene_objects

    ref = scene_objects(scene, 0.0)
    moving = [False] * len(ref)
    for t in np.linspace(0.0, 1.0, 17)[1:]:
        for k, obj in enumerate(scene_objects(scene, float(t))):
            same = np.allclose(obj.centre, ref[k].centre, atol=1e-9)
            if getattr(obj, "rotation", None) is not None:
                same = same and np.allclose(obj.rotation, ref[k].rotation, atol=1e-9)
            moving[k] = moving[k] or not same
    return moving


def synth_ground_truth(scene: str, camera, moving_flags=None):
    """(moving, static foreground) masks of a synthetic scene frame, ray cast at the camera's
    size and time (coverage > 0.5)."""
    from nehad.data.synth import render_view, scene_objects

    flags = synth_moving_objects(scene) if moving_flags is None else moving_flags
    _, cov = render_view(scene_objects(scene, camera.time), camera, supersample=3,
                         return_coverage=True)
    f = np.asarray(flags, bool)
    moving = cov[:, :, f].sum(-1) > ALPHA_MIN
    static = cov[:, :, ~f].sum(-1) > ALPHA_MIN
    return moving, static & ~moving


# ------------------------------------------------------------------------------------------
# scoring


def frame_counts(weight_map, alpha, moving, static_fg,
                 threshold: float = DEFAULT_THRESHOLD) -> dict:
    """Pixel counts and weight histograms of one frame (see the module doc)."""
    covered = np.asarray(alpha) > ALPHA_MIN
    w = np.nan_to_num(np.asarray(weight_map, np.float64), nan=0.0)
    pred = covered & (w > threshold)
    moving = np.asarray(moving, bool)
    static_fg = np.asarray(static_fg, bool)
    if pred.shape != moving.shape:
        raise VizError(f"the render is {pred.shape[1]}x{pred.shape[0]} but the ground truth "
                       f"{moving.shape[1]}x{moving.shape[0]}")
    tp = int((pred & moving).sum())
    fp = int((pred & ~moving).sum())
    fn = int((~pred & moving).sum())
    edges = np.linspace(0.0, 1.0, _BINS + 1)
    hm = np.histogram(w[covered & moving], edges)[0]
    hs = np.histogram(w[covered & static_fg], edges)[0]
    return {"tp": tp, "fp": fp, "fn": fn, "moving_pixels": int(moving.sum()),
            "static_pixels": int(static_fg.sum()), "predicted_pixels": int(pred.sum()),
            "weight_sum_moving": float(w[covered & moving].sum()),
            "weight_sum_static": float(w[covered & static_fg].sum()),
            "hist_moving": hm, "hist_static": hs}


def _ratio(a: float, b: float):
    return float(a / b) if b > 0 else None


def auc_from_histograms(hist_pos, hist_neg):
    """P(score of a positive > score of a negative), ties counting half, from histograms."""
    p = np.asarray(hist_pos, np.float64)
    n = np.asarray(hist_neg, np.float64)
    if p.sum() == 0 or n.sum() == 0:
        return None
    below = np.concatenate([[0.0], np.cumsum(n)[:-1]])
    return float((p * (below + 0.5 * n)).sum() / (p.sum() * n.sum()))


def summarize(counts: list[dict]) -> dict:
    """Scores over frames: IoU, precision, recall from summed counts; mean weights; AUC."""
    tot = {k: sum(c[k] for c in counts) for k in ("tp", "fp", "fn", "moving_pixels",
                                                   "static_pixels", "predicted_pixels",
                                                   "weight_sum_moving", "weight_sum_static")}
    hm = sum(c["hist_moving"] for c in counts) if counts else np.zeros(_BINS)
    hs = sum(c["hist_static"] for c in counts) if counts else np.zeros(_BINS)
    tp, fp, fn = tot["tp"], tot["fp"], tot["fn"]
    return {"iou": _ratio(tp, tp + fp + fn), "precision": _ratio(tp, tp + fp),
            "recall": _ratio(tp, tp + fn),
            "mean_weight_moving": _ratio(tot["weight_sum_moving"], int(hm.sum())),
            "mean_weight_static": _ratio(tot["weight_sum_static"], int(hs.sum())),
            "auc": auc_from_histograms(hm, hs),
            "tp": tp, "fp": fp, "fn": fn, "moving_pixels": tot["moving_pixels"],
            "static_pixels": tot["static_pixels"], "predicted_pixels": tot["predicted_pixels"]}


def default_data_dir(info: RunInfo, data_dir=None) -> Path:
    data = Path(data_dir) if data_dir is not None else Path(info.data_dir or "")
    if not data.is_dir():
        raise VizError(f"dataset folder {data} not found; pass --data DIR")
    return data


def score_run(run_dir, split: str = "test", data_dir=None, threshold: float = DEFAULT_THRESHOLD,
              moving_ids=None, synth_scene: str | None = None, max_frames: int = 0,
              model=None, run_info=None, keep_maps: int = 0, progress=None) -> dict:
    """Score the run's BED split against the moving objects on every frame of `split`.

    Ground truth: the dataset's label masks when it has them (`moving_ids` overrides the
    detected moving objects), else a `nehad synth` scene (given or recognised). Returns
    {"summary": {...}, "per_frame": [...], "ground_truth": str, "moving": ..., ...}; the first
    `keep_maps` frames also carry their weight map, alpha and ground truth (for pictures)."""
    if model is None:
        from nehad.model import load_run

        model, run_info = load_run(run_dir)
    why = bed_status(model)
    if why is not None:
        raise VizError(f"{run_dir}: this run has no BED position mask: {why}")
    data, frames = _score_frames(run_info, split, data_dir, max_frames)
    info: dict = {"split": split, "data": str(data), "threshold": threshold,
                  "alpha_min": ALPHA_MIN}
    described, truth = _ground_truth(data, split, frames, moving_ids, synth_scene)
    info.update(described)
    counts, per_frame, maps = [], [], []
    degree = run_info.degree_for(model)
    for i, frame in enumerate(frames):
        c, record, kept = _score_frame(model, degree, frame, truth, threshold)
        counts.append(c)
        per_frame.append({"frame": i, **record})
        if i < keep_maps:
            maps.append({"frame": frame, **kept})
        if progress is not None:
            progress()
    result = {**info, "frames": len(frames), "summary": summarize(counts), "per_frame": per_frame}
    if keep_maps:
        result["maps"] = maps
    return result


def _score_frames(run_info: RunInfo, split: str, data_dir, max_frames: int) -> tuple[Path, list]:
    """(dataset folder, the frames of `split` to score: the first `max_frames` when > 0)."""
    from nehad.data.dnerf import load_dnerf

    data = default_data_dir(run_info, data_dir)
    scene = load_dnerf(data, splits=(split,), background=run_info.background,
                       downscale=run_info.config.data.downscale)
    frames = scene.frames[split]
    if max_frames > 0:
        frames = frames[:max_frames]
    if not frames:
        raise VizError(f"{data}: the {split} split has no frames")
    return data, frames


def _ground_truth(data: Path, split: str, frames, moving_ids, synth_scene: str | None):
    """(what the ground truth is: the result's "ground_truth", "moving", ... entries, and
    truth(frame) -> (moving, static foreground) masks) for the split."""
    # a `nehad synth` scene (random cameras: no two frames share one, so the label masks cannot
    # tell which objects move) is scored against its ray-cast truth, though it has label masks
    synth_name = synth_scene or (None if moving_ids else synth_scene_name(frames[0]))
    if has_label_masks(data, split) and synth_name is None:
        return _label_truth(data, moving_ids)
    if synth_name is None:
        raise VizError(f"{data}: no ground truth for the split: no {split}/masks/ label "
                       f"masks, and not recognised as a `nehad synth` scene")
    return _synth_truth(synth_name)


def _label_truth(data: Path, moving_ids):
    """`_ground_truth` from the dataset's label masks (`moving_ids`, or the detected ones)."""
    found = moving_object_ids(data)
    ids = sorted(int(i) for i in moving_ids) if moving_ids else found["moving"]
    known = set(found["moving"]) | set(found["static"])
    unknown = [i for i in ids if known and i not in known]
    if unknown:
        listed = ", ".join(f"{i} {found['names'].get(i, '')}".strip() for i in sorted(known))
        raise VizError(f"--moving-ids: no object {unknown[0]} in the label masks of {data} "
                       f"(its objects: {listed})")
    if not ids:
        raise VizError(f"{data}: no moving object found in the label masks "
                       f"({found['method']}); name them with --moving-ids")
    names = found["names"]
    described = {"ground_truth": "label masks", "moving": [names.get(i, str(i)) for i in ids],
                 "moving_ids": ids,
                 "moving_detection": found["method"] if not moving_ids else "given",
                 "static_objects": [names.get(i, str(i)) for i in found["static"]
                                    if i not in ids]}

    def truth(frame):
        return label_ground_truth(frame, ids, frame.camera.width, frame.camera.height)

    return described, truth


def _synth_truth(name: str):
    """`_ground_truth` ray cast from the `nehad synth` scene `name`."""
    from nehad.data.synth import SCENES, scene_objects

    if name not in SCENES:
        raise VizError(f"--synth-scene {name}: expected one of {', '.join(SCENES)}")
    flags = synth_moving_objects(name)
    objs = scene_objects(name, 0.0)
    described = {"ground_truth": f"nehad synth scene {name!r} (ray cast)",
                 "moving": [o.name for o, f in zip(objs, flags) if f],
                 "static_objects": [o.name for o, f in zip(objs, flags) if not f]}

    def truth(frame):
        return synth_ground_truth(name, frame.camera, flags)

    return described, truth


def _score_frame(model, degree: int, frame, truth, threshold: float):
    """One frame scored: (its `frame_counts`, its per-frame record without the index, its
    weight map, alpha and ground truth)."""
    from nehad.model import cloud_at

    t = float(frame.camera.time)
    w = bed_weights(model, t)
    wmap, alpha = render_weights(cloud_at(model, t, degree), w, frame.camera)
    moving, static_fg = truth(frame)
    c = frame_counts(wmap, alpha, moving, static_fg, threshold)
    s = summarize([c])
    record = {"file": frame.path.name, "time": t,
              "dynamic_gaussians": float((w > threshold).mean()),
              **{k: s[k] for k in ("iou", "precision", "recall", "auc",
                                   "mean_weight_moving", "mean_weight_static")}}
    return c, record, {"weight_map": wmap, "alpha": alpha, "moving": moving, "static": static_fg}


def truth_image(moving, static_fg, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Ground truth as a picture in the colours of `weight_image`: moving red, static blue."""
    img = np.ones(moving.shape + (3,), np.float32) * np.asarray(background, np.float32)
    img[static_fg] = weight_colors(0.0)
    img[moving] = weight_colors(1.0)
    return img


def format_scores(result: dict) -> str:
    s = result["summary"]

    def f(v, d=3):
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}f}"

    lines = [f"BED split vs moving objects ({result['ground_truth']}; moving: "
             f"{', '.join(result['moving']) or 'none'}) on {result['frames']} {result['split']} "
             f"frames, threshold {result['threshold']:g}:",
             f"  IoU {f(s['iou'])}  precision {f(s['precision'])}  recall {f(s['recall'])}  "
             f"AUC {f(s['auc'])}",
             f"  mean weight 1 - M_pos: moving pixels {f(s['mean_weight_moving'])}, static "
             f"foreground {f(s['mean_weight_static'])}"]
    return "\n".join(lines)


def scores_json(result: dict) -> dict:
    """The result without the arrays (for a JSON file)."""
    return {k: v for k, v in result.items() if k != "maps"}


__all__ = ["ALPHA_MIN", "DEFAULT_THRESHOLD", "auc_from_histograms", "bed_status", "bed_weights",
           "class_names", "dynamic_fraction", "format_scores", "fraction_plot", "frame_counts",
           "has_label_masks", "label_ground_truth", "mask_path", "moving_object_ids",
           "read_label_mask", "render_weights", "score_run", "scores_json", "summarize",
           "synth_ground_truth", "synth_moving_objects", "synth_scene_name", "truth_image",
           "weight_cloud", "weight_image"]
