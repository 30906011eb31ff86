"""`nehad report RUN -o report.html`: one self-contained HTML page about a training run.

Sections: summary; training curves (loss, PSNR, Gaussian count from RUN/metrics.jsonl, PNG plots
drawn by :mod:`nehad.viz.plots`); metrics table (RUN/eval_*/metrics.json, written by
`nehad eval`); test renders beside ground truth with their PSNR and an error map; Gaussian
trajectories; the BED static/dynamic split (weight renders, dynamic fraction over time, score
against the moving objects); the resolved config.

Every image is an inline ``data:image/png;base64`` URI: the page needs no other file and no
network. A tiny inline script records, once the page has loaded, how many images the browser
decoded (``<html data-images-total=.. data-images-ok=..>``) so that a headless browser check can
read it from the DOM (scripts/check_report_browser.sh). A section whose inputs are missing (no
eval yet, dataset moved, no ground truth) says so instead of failing the report.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nehad.configtools import read_text

from . import VizError
from .plots import PALETTE, colormap, ema, encode_png, line_plot, to_uint8

if TYPE_CHECKING:
    from nehad.model import RunInfo

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,Helvetica,Arial,sans-serif;margin:0;
 color:#222;background:#fafafa}
main{max-width:1180px;margin:0 auto;padding:16px 24px 48px}
h1{font-size:1.6em;margin:.4em 0 .1em}h2{font-size:1.25em;margin:1.6em 0 .5em;
 border-bottom:1px solid #ddd;padding-bottom:.2em}
.sub{color:#666;margin:0 0 1em}
table{border-collapse:collapse;margin:.5em 0;font-size:.92em;background:#fff}
th,td{border:1px solid #ddd;padding:4px 9px;text-align:right}
th{background:#f0f0f0}td.l,th.l{text-align:left}
.grid{display:flex;flex-wrap:wrap;gap:14px;align-items:flex-start}
figure{margin:0;background:#fff;border:1px solid #e3e3e3;padding:6px}
figure img{display:block;max-width:100%;height:auto;image-rendering:auto}
figcaption{font-size:.85em;color:#555;margin-top:4px;max-width:640px}
.note{color:#8a5a00;background:#fff7e6;border:1px solid #f0d9a8;padding:6px 10px;
 display:inline-block}
pre{background:#fff;border:1px solid #e3e3e3;padding:10px;overflow:auto;font-size:.85em}
.row{display:flex;gap:4px}
.warn{color:#fff;background:#b00020;font-weight:bold;padding:6px 10px;margin:.4em 0;
 display:inline-block}
td.bad{background:#fdd;color:#900;font-weight:bold}td.skip{color:#999}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++;
  }
  document.documentElement.setAttribute('data-images-total', String(imgs.length));
  document.documentElement.setAttribute('data-images-ok', String(ok));
});
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def img_tag(image, alt: str, max_side: int | None = None, min_height: int = 0) -> str:
    """An <img> with the PNG inlined (float [0, 1] or uint8 RGB), downsized to `max_side`; an
    image lower than `min_height` is shown enlarged by an integer factor (pixelated, the PNG
    keeps its pixels)."""
    a = to_uint8(image)
    if max_side is not None and max(a.shape[:2]) > max_side:
        import cv2

        f = max_side / max(a.shape[:2])
        a = cv2.resize(a, (max(1, round(a.shape[1] * f)), max(1, round(a.shape[0] * f))),
                       interpolation=cv2.INTER_AREA)
    data = base64.b64encode(encode_png(a)).decode("ascii")
    h, w = a.shape[:2]
    k = max(1, -(-int(min_height) // h)) if min_height else 1
    style = (f' style="width:{w * k}px;height:{h * k}px;image-rendering:pixelated"'
             if k > 1 else "")
    return (f'<img src="data:image/png;base64,{data}" alt="{_e(alt)}" width="{w}" '
            f'height="{h}"{style}>')


def figure(image, caption: str, alt: str | None = None, max_side: int | None = None,
           min_height: int = 0) -> str:
    return (f"<figure>{img_tag(image, alt or caption, max_side, min_height)}"
            f"<figcaption>{_e(caption)}</figcaption></figure>")


def table(header, rows, left_cols: int = 1) -> str:
    def cell(tag, v, i):
        cls = ' class="l"' if i < left_cols else ""
        return f"<{tag}{cls}>{_e(v)}</{tag}>"

    out = ["<table><tr>" + "".join(cell("th", h, i) for i, h in enumerate(header)) + "</tr>"]
    for r in rows:
        out.append("<tr>" + "".join(cell("td", v, i) for i, v in enumerate(r)) + "</tr>")
    out.append("</table>")
    return "".join(out)


def note(text: str) -> str:
    return f'<p class="note">{_e(text)}</p>'


def _fmt(v, digits: int = 3) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(v)):
        return "n/a"  # also what a hand-edited metrics file holds in place of a number
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{digits}f}"


def _number(v) -> float:
    """A logged value as a float, NaN where the record holds something else."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return float("nan")
    return float(v)


def read_log(run: Path) -> list[dict]:
    """The records of RUN/metrics.jsonl: a JSON object per line whose step is a whole number
    >= 0 (its other values may be of any type: they are shown as n/a). Another line is a
    VizError naming the file and the line, except a torn last line (no newline ends it: a run
    killed while appending, which --resume drops), which is skipped."""
    path = Path(run) / "metrics.jsonl"
    if not path.is_file():
        return []
    out = []
    text = read_text(path, "metrics log", "JSON lines (one record per line)", VizError)
    lines = text.splitlines()
    for number, line in enumerate(lines, 1):
        try:
            rec = json.loads(line)
        except ValueError as e:
            problem = f"not valid JSON ({getattr(e, 'msg', e)})"
        except RecursionError:
            problem = "not valid JSON (nested too deeply)"
        else:
            step = rec.get("step") if isinstance(rec, dict) else None
            problem = (None if isinstance(step, int) and not isinstance(step, bool) and step >= 0
                       else "not a JSON object" if not isinstance(rec, dict)
                       else f"its step is not a whole number >= 0: {step!r}")
        if problem is None:
            out.append(rec)
        elif number < len(lines) or text.endswith("\n"):
            raise VizError(f"{path}: line {number}: {problem}; not a record nehad train writes "
                           f"(remove the line to make the report)")
    return out


def training_plots(records: list[dict], fine_start: int | None) -> list[tuple[str, np.ndarray]]:
    """(caption, image) for loss, PSNR and Gaussian count over the logged steps."""
    if not records:
        return []
    steps = np.array([r["step"] for r in records], np.float64)
    col = lambda k: np.array([_number(r.get(k)) for r in records], np.float64)
    vl = [(fine_start, "fine stage")] if fine_start else []
    alpha = min(1.0, 20.0 / max(len(records), 1))
    loss, psnr, count = col("loss"), col("psnr"), col("gaussians")
    grey = (175, 175, 175)
    out = [("Training loss (0.8 L1 + 0.2 D-SSIM + regularisers) of the logged steps; log scale",
            line_plot([{"x": steps, "y": loss, "label": "loss", "color": grey, "width": 1},
                       {"x": steps, "y": ema(loss, alpha), "label": "loss (EMA)",
                        "color": PALETTE[1]}],
                      title="Loss", xlabel="step", ylabel="loss", logy=True, vlines=vl)),
           ("PSNR of the training view(s) of each logged step (not a held-out score)",
            line_plot([{"x": steps, "y": psnr, "label": "train PSNR", "color": grey, "width": 1},
                       {"x": steps, "y": ema(psnr, alpha), "label": "train PSNR (EMA)",
                        "color": PALETTE[0]}],
                      title="PSNR", xlabel="step", ylabel="PSNR (dB)", vlines=vl))]
    if np.isfinite(count).any():
        out.append(("Number of Gaussians (densification and pruning)",
                    line_plot([{"x": steps, "y": count, "label": "Gaussians", "color": PALETTE[2]}],
                              title="Gaussians", xlabel="step", ylabel="count", vlines=vl)))
    return out


def _eval_results(run: Path) -> list[dict]:
    out = []
    for p in sorted(Path(run).glob("eval_*/metrics.json")):
        text = read_text(p, "metrics file", "the JSON written by nehad eval", VizError)
        try:
            doc = json.loads(text)
        except ValueError as e:
            raise VizError(f"{p}: malformed JSON ({e}); run nehad eval again") from None
        except RecursionError:
            raise VizError(f"{p}: malformed JSON (nested too deeply); run nehad eval again") \
                from None
        if not isinstance(doc, dict) or not _eval_layout(doc):
            raise VizError(f"{p}: not the JSON object nehad eval writes (run nehad eval again)")
        out.append(doc)
    return out


def _eval_layout(doc: dict) -> bool:
    """Whether the parts of an eval metrics.json the report reads have their types."""
    kinds = {"mean": dict, "fps_threads": dict, "resolution": list, "objects": list,
             "by_time": list, "quarters": list, "per_frame": list, "object_warnings": list,
             "object_rules": dict, "unlabelled": dict}
    if any(k in doc and doc[k] is not None and not isinstance(doc[k], t)
           for k, t in kinds.items()):
        return False
    if "resolution" in doc and doc["resolution"] is not None and len(doc["resolution"]) < 2:
        return False
    return all(isinstance(o, dict) for k in ("objects", "by_time", "quarters", "per_frame")
               for o in (doc.get(k) or []))


def metrics_section(run: Path) -> str:
    results = _eval_results(run)
    if not results:
        return note(f"No evaluation yet: run `nehad eval {run}` for PSNR, SSIM, MS-SSIM, D-SSIM, "
                    f"LPIPS and FPS.")
    keys = (("psnr", "PSNR", 2), ("ssim", "SSIM", 4), ("ms_ssim", "MS-SSIM", 4),
            ("d_ssim", "D-SSIM", 4), ("lpips_alex", "LPIPS-alex", 4), ("lpips_vgg", "LPIPS-vgg", 4))
    rows = []
    for r in results:
        m = r.get("mean", {})
        res = r.get("resolution") or ["?", "?"]
        threads = (r.get("fps_threads") or {}).get("numba")
        rows.append([r.get("split", "?"), r.get("frames", "?"), f"{res[0]}x{res[1]}"]
                    + [_fmt(m.get(k), d) for k, _, d in keys]
                    + [f"{_fmt(r.get('fps'), 1)}" + (f" ({threads} thr)" if threads else "")])
    parts = [table(["split", "frames", "size"] + [lab for _, lab, _ in keys] + ["FPS"], rows, 1)]
    lp = results[0].get("lpips_input")
    if lp:
        parts.append(f"<p class=sub>LPIPS input: {_e(lp)}. From RUN/eval_SPLIT/metrics.json.</p>")
    n_head = len(parts)
    for r in results:
        pf = r.get("per_frame") or []
        if pf:
            rows = [[p.get("file", p.get("frame")), _fmt(p.get("time"), 3)]
                    + [_fmt(p.get(k), d) for k, _, d in keys] for p in pf]
            parts.append(f"<details><summary>per frame ({_e(r.get('split'))}, {len(pf)})</summary>"
                         + table(["file", "t"] + [lab for _, lab, _ in keys], rows, 1)
                         + "</details>")
    # per-object scores (datasets with label masks): warnings first, the table after the metrics
    warns = [f'<p class="warn">{_e(r.get("split"))}: {_e(w)}</p><br>'
             for r in results for w in r.get("object_warnings") or []]
    parts[n_head:n_head] = [objects_section(r) for r in results if r.get("objects")]
    return "".join(warns) + "".join(parts)


def objects_section(result: dict) -> str:
    """The per-object table of one metrics.json (object x time quarter: PSNR of the model and
    of the blank image on the object's ground-truth pixels, and the gain), the cells under the
    warning threshold highlighted (the warning lines go at the top of the metrics section)."""
    objects = result.get("objects") or []
    rules = result.get("object_rules") or {}
    warn = float(rules.get("warn_gain_db", 3.0))
    split = result.get("split", "?")
    ranges = [tb["range"] for tb in max(objects, key=lambda o: len(o["time_bins"]))["time_bins"]]
    head = ('<tr><th class="l" rowspan="2">object</th>'
            + "".join(f'<th colspan="3">t {a:.2f}-{b:.2f}</th>' for a, b in ranges)
            + '<th colspan="3">all frames</th></tr><tr>'
            + "<th>model</th><th>blank</th><th>gain</th>" * (len(ranges) + 1) + "</tr>")
    rest = result.get("unlabelled")  # the floor and its shadows: scored, never warned on
    rest = rest if isinstance(rest, dict) and isinstance(rest.get("time_bins"), list) else None
    rows = []
    for o in objects + ([rest] if rest else []):
        by_range = {tuple(tb["range"]): tb for tb in o["time_bins"]}
        cells = [f'<td class="l">{_e(o.get("name"))}</td>']
        for cell in [by_range.get(tuple(r)) for r in ranges] + [o]:
            gain = None if cell is None else cell.get("gain")
            if gain is None:
                why = "no frame" if cell is None else cell.get("skipped", "not scored")
                px = "" if cell is None else f", {cell.get('pixels', 0)} px"
                cells.append(f'<td class="skip" colspan="3" title="{_e(why)}">'
                             f"n/a ({_e(why)}{_e(px)})</td>")
                continue
            cls = ' class="bad"' if cell is not o and o is not rest and gain < warn else ""
            title = f' title="{cell["pixels"]} object pixels"' if "pixels" in cell else ""
            cells.append(f"<td{title}>{_fmt(cell.get('psnr'), 2)}</td>"
                         f"<td>{_fmt(cell.get('blank_psnr'), 2)}</td>"
                         f"<td{cls}>{gain:+.2f}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    out = [f"<h3>Objects ({_e(split)})</h3>"]
    out.append("<table>" + head + "".join(rows) + "</table>")
    out.append(f"<p class=sub>PSNR (dB) on each labelled object's ground-truth pixels "
               f"({_e(rules.get('pixel', 'label masks'))}), the squared error pooled over all its "
               f"pixels of the quarter's frames, beside a blank image (the background colour); "
               f"red: gain under +{warn:g} dB; a quarter with fewer than "
               f"{_e(rules.get('min_pixels', '?'))} object pixels is not scored."
               + (f" The last row, {_e(rest['name'])}, is the opaque pixels no label covers "
                  f"(a floor and the shadows on it), never marked." if rest else "") + "</p>")
    return "".join(out)


def _psnr(a, b) -> float:
    from nehad.metrics.image import psnr_of_mse

    return psnr_of_mse(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def _error_map(render, gt) -> np.ndarray:
    err = np.abs(np.asarray(render, np.float32) - np.asarray(gt, np.float32)).mean(-1)
    scale = max(float(np.percentile(err, 99.5)), 1e-3)
    return colormap(np.clip(err / scale, 0, 1).reshape(-1), "inferno").reshape(err.shape + (3,))


def _pick(n_total: int, n: int) -> list[int]:
    if n <= 0 or n_total <= 0:
        return []
    if n >= n_total:
        return list(range(n_total))
    return sorted({int(round(i)) for i in np.linspace(0, n_total - 1, n)})


def build_report(run_dir, output, data_dir=None, frames: int = 4, score: bool = True,
                 max_side: int = 480, track_count: int = 300, log=None) -> dict:
    """Write the report of `run_dir` to `output` (atomically). Returns {"bytes", "images",
    "sections", "skipped": {section: reason}}."""
    from nehad.runtime.images import atomic_path

    run = Path(run_dir)
    # every file the page reads from the run folder, read (and refused) before the slow work
    records = read_log(run)
    _eval_results(run)
    cfg_file_text = _read_config_text(run)
    rep = _open_run(run, log or (lambda m: None))
    evals = _eval_results(run)
    sections = [_section_summary(rep, records, evals), _section_curves(rep, records),
                _section_metrics(rep, evals)]
    rep = _with_test_frames(rep, data_dir, max_side)
    sections += [_section_renders(rep, frames, max_side),
                 _section_trajectories(rep, track_count),
                 _section_masks(rep, data_dir, score, max_side),
                 _section_config(rep, cfg_file_text)]
    page = _page(run, sections)
    data = page.encode("utf-8")
    output = Path(output)
    with atomic_path(output, VizError) as tmp:
        Path(tmp).write_bytes(data)
    return {"bytes": len(data), "images": page.count("<img "),
            "sections": [sid for sid, _, _ in sections], "skipped": rep.skipped}


@dataclass(frozen=True)
class _Report:
    """What every section of one report needs. `skipped` ({section: reason}) is filled in by
    the sections; the test frames and the camera come with `_with_test_frames`."""

    run: Path
    model: object
    info: RunInfo
    cfg: object
    degree: int
    background: tuple
    time_range: tuple
    say: Callable[[str], None]
    skipped: dict = field(default_factory=dict)
    test_frames: list = field(default_factory=list)
    camera: object = None  # the first test frame's, sized by `_fit`; None without test frames

    def gaussians_at(self, t):
        """The run's Gaussians at time t (deformed, at the run's SH degree)."""
        from nehad.model import cloud_at

        return cloud_at(self.model, float(t), self.degree)


def _expected_errors() -> tuple:
    """The errors a section reports (and skips) instead of failing the page."""
    from nehad.data.common import DatasetError
    from nehad.model import RunError

    return (VizError, DatasetError, RunError, OSError)


def _read_config_text(run: Path) -> str | None:
    """The text of RUN/config.yaml, None when there is none."""
    cfg_path = run / "config.yaml"
    return read_text(cfg_path, "config file", "the run's YAML config", VizError) \
        if cfg_path.is_file() else None


def _open_run(run: Path, say) -> _Report:
    """The loaded run, without its test frames."""
    from nehad.model import load_run

    model, info = load_run(run)
    return _Report(run=run, model=model, info=info, cfg=info.config,
                   degree=info.degree_for(model), background=info.background,
                   time_range=info.time_range, say=say)


def _fit(cam, max_side: int):
    """`cam` resized so that its longest side is `max_side` (up or down)."""
    s = max(cam.width, cam.height)
    return cam.with_size(max(1, round(cam.width * max_side / s)),
                         max(1, round(cam.height * max_side / s)))


def _with_test_frames(rep: _Report, data_dir, max_side: int) -> _Report:
    """`rep` with the test frames (the loader, split and frame stride of `nehad eval`, any
    dataset layout) and the first one's camera fitted to `max_side`; when the dataset cannot
    be read, none, and the reason in skipped["renders"]."""
    from nehad.data.loader import load_dataset

    test_frames, first_cam = [], None
    try:
        from .masks import default_data_dir

        data = default_data_dir(rep.info, data_dir)
        split = rep.cfg.data.eval_split
        scene = load_dataset(data, splits=(split,), background=rep.background,
                             downscale=rep.cfg.data.downscale,
                             frame_stride=rep.cfg.data.frame_stride)
        test_frames = scene.frames[split]
        first_cam = test_frames[0].camera if test_frames else None
    except _expected_errors() as e:
        rep.skipped["renders"] = str(e)
    camera = _fit(first_cam, max_side) if first_cam is not None else None
    return replace(rep, test_frames=test_frames, camera=camera)


def _section_summary(rep: _Report, records: list[dict], evals: list[dict]) -> tuple:
    """The run at a glance: dataset, config, size, last train PSNR, eval scores."""
    cfg, info = rep.cfg, rep.info
    lo, hi = rep.time_range
    last = records[-1] if records else {}
    rows = [["run", str(rep.run.resolve())], ["dataset", info.data_dir or "?"],
            ["preset", cfg.preset], ["decoder", cfg.field.decoder],
            ["steps", f"{'?' if info.steps is None else info.steps} ({cfg.coarse.iterations} coarse + "
                      f"{cfg.fine.iterations} fine)"],
            ["Gaussians", str(len(rep.model.gaussians))], ["SH degree", str(rep.degree)],
            ["time range", f"[{lo:g}, {hi:g}]"],
            ["background", ",".join(f"{v:g}" for v in rep.background)]]
    if last:
        rows.append(["last logged train PSNR", f"{_fmt(last.get('psnr'), 2)} dB (step "
                                               f"{last.get('step')})"])
        if "seconds" in last:
            rows.append(["training time", f"{float(last['seconds']) / 60:.1f} min"])
    for r in evals:
        m = r.get("mean", {})
        rows.append([f"{r.get('split')} PSNR / SSIM / LPIPS-alex",
                     f"{_fmt(m.get('psnr'), 2)} dB / {_fmt(m.get('ssim'), 4)} / "
                     f"{_fmt(m.get('lpips_alex'), 4)}"])
    return ("summary", "Summary", table(["", ""], rows, 2))


def _section_curves(rep: _Report, records: list[dict]) -> tuple:
    """Loss, PSNR and Gaussian count over the logged training steps."""
    rep.say("report: training curves")
    cfg = rep.cfg
    plots = training_plots(records, cfg.coarse.iterations if cfg.fine.iterations else None)
    if plots:
        body = '<div class="grid">' + "".join(figure(img, cap) for cap, img in plots) + "</div>"
    else:
        body = note(f"{rep.run}/metrics.jsonl has no records")
        rep.skipped["curves"] = "no metrics.jsonl records"
    return ("curves", "Training curves", body)


def _section_metrics(rep: _Report, evals: list[dict]) -> tuple:
    """The scores of `nehad eval` (`metrics_section`)."""
    try:
        body = metrics_section(rep.run)
    except (TypeError, ValueError, AttributeError, KeyError, IndexError) as e:
        raise VizError(f"{rep.run}/eval_*/metrics.json: not what nehad eval writes "
                       f"({type(e).__name__}: {e}); run nehad eval again") from None
    if not evals:
        rep.skipped["metrics"] = "no eval_*/metrics.json"
    return ("metrics", "Metrics", body)


def _section_renders(rep: _Report, frames: int, max_side: int) -> tuple:
    """`frames` test frames: ground truth | render | error map, with their PSNR."""
    test_frames = rep.test_frames
    if not test_frames or frames == 0:
        why = "--frames 0" if test_frames else rep.skipped.get("renders",
                                                                 "the test split is empty")
        body = note(f"No test renders: {why}")
        return ("renders", "Test renders beside ground truth", body)
    rep.say("report: test renders")
    figs, psnrs = [], []
    for i in _pick(len(test_frames), frames):
        fig, p = _render_figure(rep, test_frames[i], max_side)
        figs.append(fig)
        psnrs.append(p)
    body = ('<div class="grid">' + "".join(figs) + "</div>"
            + f"<p class=sub>{len(figs)} of {len(test_frames)} test frames at "
              f"{test_frames[0].camera.width}x{test_frames[0].camera.height}; mean PSNR of "
              f"these {np.mean(psnrs):.2f} dB.</p>")
    return ("renders", "Test renders beside ground truth", body)


def _render_figure(rep: _Report, fr, max_side: int) -> tuple[str, float]:
    """(the figure of test frame `fr`: ground truth | render | error map, the render's PSNR)."""
    from nehad.runtime.raster import render

    rgb = render(rep.gaussians_at(fr.camera.time), fr.camera, background=rep.background).rgb
    p = _psnr(rgb, fr.image)
    trio = np.concatenate([fr.image, np.ones((fr.image.shape[0], 4, 3), np.float32),
                           rgb, np.ones((fr.image.shape[0], 4, 3), np.float32),
                           _error_map(rgb, fr.image)], axis=1)
    fig = figure(trio, f"{fr.path.name}, t = {fr.camera.time:.3f}: ground truth | "
                       f"render | |error| (inferno, 99.5th pct = top); "
                       f"PSNR {p:.2f} dB", max_side=3 * max_side,
                 min_height=min(200, max_side))
    return fig, p


def _section_trajectories(rep: _Report, track_count: int) -> tuple:
    """Paths of `track_count` Gaussians over time, drawn over the render at the first time."""
    from .trajectories import compute_tracks, track_times, trajectory_image

    title = "Gaussian trajectories"
    cam = rep.camera
    if cam is None:
        rep.skipped["trajectories"] = "no camera"
        return ("trajectories", title,
                note("No trajectories: no camera (the dataset's test split was not found)"))
    rep.say("report: trajectories")
    lo, hi = rep.time_range
    try:
        times = track_times((lo, hi), 32)
        tracks = compute_tracks(rep.gaussians_at, cam, times, count=track_count)
        img = trajectory_image(rep.gaussians_at, cam, tracks, rep.background)
        pl = tracks.path_length
        still = (" No tracked Gaussian moves (a coarse-only run, or a field that learned no "
                 "motion)." if float(pl.max()) == 0.0 else "")
        body = figure(img, f"{len(tracks)} Gaussians (favouring those that move) tracked at "
                           f"{len(times)} times in [{lo:g}, {hi:g}], over the render at "
                           f"t = {lo:g}; colour = time (blue early, red late), dot = final "
                           f"position. Path length median {np.median(pl):.3g}, max "
                           f"{pl.max():.3g} world units.{still}")
    except _expected_errors() as e:
        body = note(f"No trajectories: {e}")
        rep.skipped["trajectories"] = str(e)
    return ("trajectories", title, body)


def _section_masks(rep: _Report, data_dir, score: bool, max_side: int) -> tuple:
    """The BED split: weight renders at three times, the dynamic fraction over time, and (with
    `score` and test frames) its score against the moving objects."""
    from .masks import bed_status

    title = "BED static/dynamic split"
    why = bed_status(rep.model)
    if why is not None:
        rep.skipped["masks"] = why
        return ("masks", title, note(f"No BED split: {why}."))
    rep.say("report: BED masks")
    parts = []
    if rep.camera is not None:
        parts.append(_weight_renders(rep))
    parts.append(_fraction_figure(rep))
    if score and rep.test_frames:
        _append_score(rep, parts, data_dir, max_side)
    elif score:
        rep.skipped["score"] = "no test frames"
    return ("masks", title, "".join(parts))


def _weight_renders(rep: _Report) -> str:
    """BED weight renders at the first, middle and last time."""
    from .masks import bed_weights, render_weights, weight_image

    lo, hi = rep.time_range
    figs = []
    for t in (lo, 0.5 * (lo + hi), hi):
        w = bed_weights(rep.model, t)
        wmap, alpha = render_weights(rep.gaussians_at(t), w, rep.camera)
        figs.append(figure(weight_image(wmap, alpha, rep.background),
                           f"t = {t:g}: {float((w > 0.5).mean()):.1%} of the Gaussians "
                           f"dynamic (w > 0.5)"))
    return '<div class="grid">' + "".join(figs) + "</div>"


def _fraction_figure(rep: _Report) -> str:
    """The fraction of dynamic Gaussians and their mean weight over time."""
    from .masks import dynamic_fraction, fraction_plot
    from .trajectories import track_times

    lo, hi = rep.time_range
    times = track_times((lo, hi), 41)
    frac = dynamic_fraction(rep.model, times)
    mean_w = dynamic_fraction(rep.model, times, weighted=True)
    return '<div class="grid">' + figure(
        fraction_plot(times, frac, 0.5, mean_w),
        "Fraction of Gaussians with BED weight w = 1 - M_pos > 0.5, and the mean weight, over "
        "time") + "</div>"


def _append_score(rep: _Report, parts: list[str], data_dir, max_side: int) -> None:
    """Append to `parts` the score of the split against the moving objects (table, text and
    pictures of two frames), or a note why there is none."""
    from .masks import format_scores, score_run

    rep.say("report: scoring the split against the moving objects")
    try:
        res = score_run(rep.run, "test", data_dir, model=rep.model, run_info=rep.info,
                        keep_maps=2)
        s = res["summary"]
        parts.append(table(
            ["IoU", "precision", "recall", "AUC", "mean w (moving)", "mean w (static fg)",
             "frames"],
            [[_fmt(s["iou"]), _fmt(s["precision"]), _fmt(s["recall"]), _fmt(s["auc"]),
              _fmt(s["mean_weight_moving"]), _fmt(s["mean_weight_static"]),
              res["frames"]]], 0))
        parts.append(f"<pre>{_e(format_scores(res))}</pre>")
        parts.append(_score_maps(res, rep.background, max_side))
    except _expected_errors() as e:
        parts.append(note(f"No score: {e}"))
        rep.skipped["score"] = str(e)


def _score_maps(res: dict, bg, max_side: int) -> str:
    """Ground truth beside the BED weight render, for the frames `score_run` kept maps of."""
    from .masks import truth_image, weight_image

    figs = []
    for m in res.get("maps", []):
        fr = m["frame"]
        pair = np.concatenate([truth_image(m["moving"], m["static"], bg),
                               np.ones((m["moving"].shape[0], 4, 3), np.float32),
                               weight_image(m["weight_map"], m["alpha"], bg,
                                            legend=False)], axis=1)
        figs.append(figure(pair, f"{fr.path.name}, t = {fr.camera.time:.3f}: ground "
                                 f"truth (red moving objects, blue static foreground)"
                                 f" | BED weight render", max_side=2 * max_side,
                           min_height=min(200, max_side)))
    return '<div class="grid">' + "".join(figs) + "</div>"


def _section_config(rep: _Report, cfg_file_text: str | None) -> tuple:
    """The run's config.yaml (or, without one, the config stored with the run)."""
    cfg_path = rep.run / "config.yaml"
    cfg_text = cfg_file_text if cfg_file_text is not None else \
        json.dumps(rep.info.config_dict, indent=1)
    return ("config", "Config", (f"<details open><summary>{_e(cfg_path.name)}</summary>"
                                 f"<pre>{_e(cfg_text)}</pre></details>"))


def _page(run: Path, sections: list[tuple]) -> str:
    """The whole page: title, navigation and the (id, title, html) sections."""
    from nehad import __version__

    now = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    nav = " · ".join(f'<a href="#{sid}">{_e(title)}</a>' for sid, title, _ in sections)
    body = "".join(f'<section id="{sid}"><h2>{_e(title)}</h2>{content}</section>'
                   for sid, title, content in sections)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>NeHaD report: {_e(run.name)}</title><style>{_CSS}</style>"
            f"<script>{_SCRIPT}</script></head><body><main>"
            f"<h1>NeHaD report: {_e(run.name)}</h1>"
            f"<p class=sub>nehad {_e(__version__)}, written {_e(now)}. {nav}</p>"
            f"{body}</main></body></html>\n")


__all__ = ["build_report", "figure", "img_tag", "metrics_section", "objects_section", "read_log",
           "table", "training_plots"]
