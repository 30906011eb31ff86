"""`nehad batch jobs.yaml`: many videos and still renders from one file (issue 5, docs/design.md section 10).

::

    # jobs.yaml -- relative paths are relative to this file's folder
    workers: 2                    # optional: local pool size (the CLI's --workers wins)
    # scheduler: tcp://host:8786  # optional: a Dask cluster instead (the CLI's --scheduler wins)
    defaults:                     # optional: keys every job gets unless it sets them
      model: model.onnx
      size: 400x400
    jobs:
      - name: orbit               # optional (default job1, job2, ...)
        output: out/orbit.mp4     # .mp4: a video job
        path: orbit:elevation=30
        frames: 120
        fps: 30
        time: 0:1
      - name: test-views
        output: out/test.mp4
        path: data/scene:test
        side_by_side: true
      - name: still
        output: out/still.png     # an image suffix: an image job
        view: data/scene/transforms_test.json:0
        time: 0.5

Keys of a video job: ``name, type, model, output, path, time, frames, fps, size, background,
frames_dir, frame_format, side_by_side, crf, extrapolate, lod``; of an image job: ``name, type,
model, output, view, time, size, background, extrapolate, lod``. ``model`` is any scene
``nehad render`` takes (runtime/scene.py); ``lod`` keeps streaming layers 0..lod. ``type`` (video or image) follows from the
output's suffix when absent. ``time`` is a number (freeze), ``"A:B"`` or ``[A, B]`` (sweep) or
``own``; ``size`` is ``"WxH"`` or ``[W, H]``; ``background`` is ``[R, G, B]`` or ``"R,G,B"``.

:func:`load_batch` checks the whole file before anything runs and raises :class:`BatchError`
naming the job and the key. :func:`run_batch` runs the jobs one after the other on one backend (a
pool or a Dask client shared by all jobs, so each worker loads a model once); a failing job is
reported and the others go on.
"""

from __future__ import annotations

import difflib
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import InputProblem
from .mp4 import MAX_FPS, MIN_FPS
from .suffixes import IMAGE_SUFFIXES
from .values import MAX_THREADS, MAX_WORKERS, count_problem, parse_background, parse_size

__all__ = ["BatchError", "BatchSpec", "BatchJob", "JobResult", "load_batch", "run_batch",
           "format_summary", "VIDEO_KEYS", "IMAGE_KEYS", "TOP_KEYS"]

TOP_KEYS = ("jobs", "defaults", "workers", "scheduler", "threads")
VIDEO_KEYS = ("name", "type", "model", "output", "path", "time", "frames", "fps", "size",
              "background", "frames_dir", "frame_format", "side_by_side", "crf", "extrapolate",
              "lod")
IMAGE_KEYS = ("name", "type", "model", "output", "view", "time", "size", "background",
              "extrapolate", "lod")
#: How a job's error names the inputs a runtime message leaves as {input} (runtime/errors.py).
KEY_NAMES = {"extrapolate": "extrapolate: true"}
ALL_KEYS = tuple(dict.fromkeys(VIDEO_KEYS + IMAGE_KEYS))


class BatchError(InputProblem):
    """A jobs file that cannot be used; the message names the file, the job and the key."""


@dataclass
class BatchJob:
    """One checked job: `type` video or image, `settings` its keys with values converted."""

    index: int
    name: str
    type: str
    settings: dict


@dataclass
class BatchSpec:
    path: Path
    jobs: list[BatchJob]
    workers: int | None = None
    scheduler: str | None = None
    threads: int | None = None


@dataclass
class JobResult:
    job: BatchJob
    ok: bool
    frames: int = 0
    rendered: int = 0
    seconds: float = 0.0
    output: str = ""
    error: str = ""
    details: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# loading and checking


def _suggest(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1)
    return f"; did you mean {close[0]!r}?" if close else f" (allowed: {', '.join(allowed)})"


class _Where:
    def __init__(self, source: str, index: int | None, name: str | None):
        self.source, self.index, self.name = source, index, name

    def err(self, key: str | None, problem: str) -> BatchError:
        if self.index is None:
            where = f"{self.source}: defaults"
        else:
            label = f"job {self.name!r} (jobs[{self.index}])" if self.name else f"jobs[{self.index}]"
            where = f"{self.source}: {label}"
        return BatchError(f"{where}: {key}: {problem}" if key else f"{where}: {problem}")


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _convert(key: str, value, w: _Where, base: Path):
    """The value of one job key, checked and converted (paths made absolute against `base`)."""
    from .paths import PathError, parse_time_spec

    def path_value():
        if not isinstance(value, str) or not value.strip():
            raise w.err(key, f"expected a file path, got {value!r}")
        p = Path(value).expanduser()
        return p if p.is_absolute() else base / p

    if key in ("name", "type"):
        if not isinstance(value, str) or not value.strip():
            raise w.err(key, f"expected a non-empty string, got {value!r}")
        if key == "type" and value not in ("video", "image"):
            raise w.err(key, f"expected video or image, got {value!r}")
        return value.strip()
    if key in ("model", "output", "frames_dir"):
        return path_value()
    if key in ("path", "view"):
        if not isinstance(value, str) or not value.strip():
            raise w.err(key, f"expected a camera path string, got {value!r}")
        return _resolve_spec(value.strip(), base)
    if key == "time":
        if isinstance(value, (list, tuple)):
            if len(value) != 2 or not all(_is_num(v) for v in value):
                raise w.err(key, f"expected [A, B] with two numbers, got {value!r}")
            return f"{float(value[0])!r}:{float(value[1])!r}"
        if _is_num(value):
            return repr(float(value))
        if isinstance(value, str):
            try:
                parse_time_spec(value)
            except PathError as e:
                raise w.err(key, str(e)) from None
            return value
        raise w.err(key, f"expected a time T, a sweep 'A:B' or [A, B], or own; got {value!r}")
    if key == "frames":
        if not _is_int(value) or value < 1:
            raise w.err(key, f"expected a whole number >= 1, got {value!r}")
        return int(value)
    if key == "fps":
        if not _is_num(value) or not MIN_FPS <= value <= MAX_FPS:
            raise w.err(key, f"expected a number in [{MIN_FPS:g}, {MAX_FPS:g}], got {value!r}")
        return float(value)
    if key == "crf":
        if not _is_int(value) or not 0 <= value <= 51:
            raise w.err(key, f"expected a whole number in 0..51, got {value!r}")
        return int(value)
    if key == "size":
        if isinstance(value, (list, tuple)):
            if len(value) != 2 or not all(_is_int(v) for v in value):
                raise w.err(key, f"expected [W, H] in pixels, got {value!r}")
            value = f"{value[0]}x{value[1]}"
        if not isinstance(value, str):
            raise w.err(key, f"expected WxH (e.g. 400x400), got {value!r}")
        try:
            return parse_size(value)
        except ValueError as e:
            raise w.err(key, str(e)) from None
    if key == "background":
        if _is_num(value):
            value = [value] * 3
        if isinstance(value, (list, tuple)):
            if len(value) != 3 or not all(_is_num(v) for v in value):
                raise w.err(key, f"expected [R, G, B] in [0, 1], got {value!r}")
            value = ",".join(repr(float(v)) for v in value)
        if not isinstance(value, str):
            raise w.err(key, f"expected [R, G, B] in [0, 1], got {value!r}")
        try:
            return parse_background(value)
        except ValueError as e:
            raise w.err(key, str(e)) from None
    if key == "frame_format":
        if value not in ("png", "exr"):
            raise w.err(key, f"expected png or exr, got {value!r}")
        return value
    if key == "lod":
        if not _is_int(value) or value < 0:
            raise w.err(key, f"expected a whole number >= 0, got {value!r}")
        return int(value)
    if key in ("side_by_side", "extrapolate"):
        if not isinstance(value, bool):
            raise w.err(key, f"expected true or false, got {value!r}")
        return value
    raise w.err(key, "unknown key" + _suggest(key, ALL_KEYS))  # pragma: no cover


def _resolve_spec(spec: str, base: Path) -> str:
    """Make the file paths inside a camera-path spec absolute against `base`."""
    kind = spec.partition(":")[0].lower()
    if kind in ("orbit", "spiral"):
        def fix(m):
            p = Path(m.group(2)).expanduser()
            return m.group(1) + str(p if p.is_absolute() else base / p)

        return re.sub(r"(\bfrom=)([^,\]]+)", fix, spec)
    if spec.lower() == "default":
        return spec
    p = Path(spec).expanduser()
    return str(p if p.is_absolute() else base / p)


def _job_type(settings: dict, w: _Where) -> str:
    if "type" in settings:
        return settings["type"]
    out = settings.get("output")
    if out is not None:
        suffix = Path(out).suffix.lower()
        if suffix == ".mp4":
            return "video"
        if suffix in IMAGE_SUFFIXES:
            return "image"
        raise w.err("output", f"{out.name}: expected a .mp4 video or an image "
                              f"({', '.join(IMAGE_SUFFIXES)}), or give type")
    if "frames_dir" in settings:
        return "video"
    raise w.err("output", "missing (a .mp4 video or an image file)")


def load_batch(path, check_files: bool = False) -> BatchSpec:
    """Read and check a jobs file (module doc); raises :class:`BatchError`. With `check_files`
    (`nehad batch --check`) also what each job would fail on once it runs (`_check_job_files`:
    its model missing here, ...); a run reports those per job and goes on with the others (a
    model may be where the workers run, not here). A sweep of times for an image job is a
    mistake in the file, refused either way."""
    from .paths import parse_time_spec
    from .yamlfile import MalformedYAML, load_yaml_text

    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise BatchError(f"{source}: no such jobs file")
    try:
        doc = load_yaml_text(path.read_text(encoding="utf-8"))
    except MalformedYAML as e:
        raise BatchError(f"{source}: {e}") from None
    except UnicodeDecodeError as e:
        raise BatchError(f"{source}: not a UTF-8 text file (byte {e.start}: "
                         f"{e.object[e.start]:#04x}); expected a YAML jobs file") from None
    except OSError as e:
        raise BatchError(f"{source}: cannot read ({e.strerror or e})") from None
    if not isinstance(doc, dict):
        raise BatchError(f"{source}: expected a mapping with a 'jobs' list at the top level")
    for key in doc:
        if key not in TOP_KEYS:
            raise BatchError(f"{source}: unknown top-level key {key!r}" + _suggest(str(key), TOP_KEYS))
    base = path.parent.absolute()
    workers, threads = doc.get("workers"), doc.get("threads")
    for key, value, most in (("workers", workers, MAX_WORKERS), ("threads", threads, MAX_THREADS)):
        why = count_problem(value, 1, most)
        if why:
            raise BatchError(f"{source}: {key}: {why}, got {value!r}")
    scheduler = doc.get("scheduler")
    if scheduler is not None and (not isinstance(scheduler, str) or "://" not in scheduler):
        raise BatchError(f"{source}: scheduler: expected an address like tcp://HOST:8786, got "
                         f"{scheduler!r}")
    defaults_raw = doc.get("defaults") or {}
    if not isinstance(defaults_raw, dict):
        raise BatchError(f"{source}: defaults: expected a mapping of job keys")
    wd = _Where(source, None, None)
    defaults = {}
    for key, value in defaults_raw.items():
        if key not in ALL_KEYS or key in ("name", "type", "output"):
            allowed = [k for k in ALL_KEYS if k not in ("name", "type", "output")]
            raise wd.err(str(key), "not a key defaults can set" + _suggest(str(key), allowed))
        defaults[key] = _convert(key, value, wd, base)
    jobs_raw = doc.get("jobs")
    if not isinstance(jobs_raw, list) or not jobs_raw:
        raise BatchError(f"{source}: jobs: expected a non-empty list of jobs")
    jobs, names, outputs = [], {}, {}
    for i, raw in enumerate(jobs_raw):
        name = raw.get("name") if isinstance(raw, dict) else None
        w = _Where(source, i, name if isinstance(name, str) else None)
        if not isinstance(raw, dict):
            raise w.err(None, f"expected a mapping of keys, got {type(raw).__name__}")
        settings = {}
        for key, value in raw.items():
            if not isinstance(key, str) or key not in ALL_KEYS:
                raise w.err(str(key), "unknown key" + _suggest(str(key), ALL_KEYS))
            settings[key] = _convert(key, value, w, base)
        kind = _job_type({**defaults, **settings}, w)
        allowed = VIDEO_KEYS if kind == "video" else IMAGE_KEYS
        for key in settings:
            if key not in allowed:
                raise w.err(key, f"does not apply to {'an image' if kind == 'image' else 'a video'} job"
                            + _suggest(key, allowed))
        merged = {k: v for k, v in defaults.items() if k in allowed}
        merged.update(settings)
        if "model" not in merged:
            raise w.err("model", "missing (set it in the job or in defaults)")
        if kind == "image" and "output" not in merged:
            raise w.err("output", "missing (the image to write)")
        if kind == "video" and "output" not in merged and "frames_dir" not in merged:
            raise w.err("output", "missing (a .mp4, or frames_dir for frames only)")
        if kind == "video" and "output" in merged and merged["output"].suffix.lower() != ".mp4":
            raise w.err("output", f"{merged['output'].name}: a video job writes a .mp4")
        if kind == "image" and merged["output"].suffix.lower() not in IMAGE_SUFFIXES:
            raise w.err("output", f"{merged['output'].name}: an image job writes "
                                  f"{', '.join(IMAGE_SUFFIXES)}")
        if kind == "image" and "time" in merged and \
                parse_time_spec(merged["time"]).mode == "sweep":  # checked by _convert
            raise w.err("time", f"{merged['time']}: an image job renders one time T")
        if kind == "video" and merged.get("side_by_side") and "path" not in merged:
            raise w.err("side_by_side", "needs a dataset path with ground truth (path: DATA:test)")
        name = merged.pop("name", None) or f"job{i + 1}"
        merged.pop("type", None)
        if name in names:
            raise w.err("name", f"{name!r} is also the name of jobs[{names[name]}]")
        names[name] = i
        for key in ("output", "frames_dir"):
            if key in merged:
                target = str(merged[key])
                if target in outputs:
                    raise w.err(key, f"{merged[key]} is also written by job {outputs[target]!r}")
                outputs[target] = name
        jobs.append(BatchJob(i, name, kind, merged))
    for job in jobs if check_files else ():  # the whole file's keys first, then its files
        _check_job_files(job.settings, job.type, _Where(source, job.index, job.name))
    _check_outputs_are_not_inputs(path, source, jobs)
    return BatchSpec(path, jobs, workers, scheduler, threads)


def _check_job_files(job: dict, kind: str, w: _Where) -> None:
    """What a job would fail on once it runs, found before anything runs: its model missing,
    its output folder missing, a streaming layer the model lacks."""
    model = job["model"]
    if not model.exists():
        raise w.err("model", f"{model}: no such file or folder")
    for key in ("output", "frames_dir"):
        if key in job and not job[key].parent.is_dir():
            raise w.err(key, f"{job[key]}: folder {job[key].parent} does not exist")
    if "lod" in job and model.is_file() and model.suffix.lower() == ".onnx":
        from .onnx_model import OnnxModelError, read_model_info

        try:
            layers = read_model_info(model).num_layers
        except OnnxModelError as e:
            raise w.err("model", str(e)) from None
        if job["lod"] >= layers:
            raise w.err("lod", f"{job['lod']}: {model.name} has {layers} layer(s), "
                               f"0..{layers - 1}")


def _check_outputs_are_not_inputs(path: Path, source: str, jobs: list) -> None:
    """No job writes the jobs file or a file any job reads (a model, a camera file), checked
    before any job runs (issue 26)."""
    from .outputs import check_outputs

    inputs = [("the jobs file", path)]
    for job in jobs:
        for key in ("model", "view", "path"):
            if key in job.settings:
                inputs.append((f"{_label(job)}.{key}", job.settings[key]))
    for job in jobs:
        outputs = []
        if "output" in job.settings:
            outputs.append((f"{_label(job)}.output", job.settings["output"]))
        if "frames_dir" in job.settings:
            outputs.append((f"{_label(job)}.frames_dir", job.settings["frames_dir"], "frame_*"))
        check_outputs(outputs, inputs, lambda msg: BatchError(f"{source}: {msg}"))


def _label(job) -> str:
    return f"jobs[{job.index}] ({job.name})"


# ---------------------------------------------------------------------------------------------
# running


def _video_job(job: BatchJob, openers: tuple = ()):
    """The VideoJob of a video job; keys the job leaves out keep VideoJob's defaults."""
    from .video import VideoJob

    s = job.settings
    given = {k: s[k] for k in ("output", "path", "time", "frames", "size", "fps", "frames_dir",
                               "frame_format", "side_by_side", "background", "extrapolate",
                               "crf", "lod") if k in s}
    return VideoJob(model=s["model"], name=job.name, openers=tuple(openers), **given)


def _image_task(job: BatchJob, resume: bool, threads, openers: tuple = ()):
    """The FrameTask of an image job (one camera at one time): the scene, camera and time
    chosen as `nehad render` chooses them (runtime/scene.py)."""
    from .distribute import FrameTask
    from .memory import check_frame_memory
    from .paths import PathError, parse_time_spec
    from .scene import choose_camera, open_scene, scene_time
    from .video import VideoError

    s = job.settings
    out = Path(s["output"])
    if not out.parent.is_dir():
        raise VideoError(f"{{output}} {out}: folder {out.parent} does not exist", "output")
    scene = open_scene(s["model"], lod=s.get("lod"), openers=tuple(openers))
    cam = choose_camera(scene, s.get("view", "default"), s.get("size"))
    t = None
    if "time" in s:
        tspec = parse_time_spec(s["time"])
        if tspec.mode == "sweep":
            raise PathError(f"{{time}} {s['time']}: an image job renders one time T", "time")
        t = tspec.start if tspec.mode == "freeze" else None
    t = scene_time(scene, cam, t, s.get("extrapolate", False))
    check_frame_memory(cam.width, cam.height, scene.num_gaussians,
                       f"size {s['size'][0]}x{s['size'][1]}" if s.get("size") is not None
                       else f"view {s.get('view', 'default')}")
    bg = tuple(s.get("background") or scene.default_background)
    return FrameTask(str(Path(s["model"]).absolute()), 0, cam, t, bg, str(out.absolute()),
                     None, threads, skip_existing=resume, lod=s.get("lod"),
                     openers=tuple(openers))


def _one_line(e: BaseException) -> str:
    text = e.message(KEY_NAMES) if isinstance(e, InputProblem) else str(e)
    return " ".join(text.split()) or type(e).__name__


def run_batch(spec: BatchSpec, backend, resume: bool = False, progress: bool = True,
              on_job=None, openers: tuple = ()) -> list[JobResult]:
    """Run every job of `spec` on `backend`; a job's failure is recorded and the next one runs.
    `on_job(result)` is called after each job; `openers` open scene kinds the runtime cannot
    (runtime/scene.py). KeyboardInterrupt stops the batch."""
    from .video import run_video

    user_errors = (InputProblem, OSError)
    results = []
    for job in spec.jobs:
        start = time.perf_counter()
        try:
            if job.type == "video":
                rep = run_video(_video_job(job, openers), backend, resume=resume,
                                progress=progress)
                out = str(rep.output) if rep.output is not None else f"{rep.frames_dir}/"
                res = JobResult(job, True, rep.frames, rep.rendered,
                                time.perf_counter() - start, out)
            else:
                task = _image_task(job, resume, None, openers)
                r = backend.run([task])[0]
                res = JobResult(job, True, 1, 0 if r.skipped else 1, time.perf_counter() - start,
                                r.path)
        except user_errors as e:
            res = JobResult(job, False, seconds=time.perf_counter() - start, error=_one_line(e))
        except Exception as e:  # a bug in one job must not stop the others
            res = JobResult(job, False, seconds=time.perf_counter() - start,
                            error=f"internal error: {type(e).__name__}: {_one_line(e)}")
        results.append(res)
        if on_job:
            on_job(res)
    return results


def format_summary(results: list[JobResult], cwd: Path | None = None) -> str:
    """The table `nehad batch` prints: one row per job."""
    cwd = (cwd or Path.cwd()).absolute()

    def short(p: str) -> str:
        try:
            return str(Path(p).relative_to(cwd)) + ("/" if p.endswith("/") else "")
        except ValueError:
            return p

    rows = [("job", "type", "frames", "rendered", "seconds", "status", "output / error")]
    for r in results:
        rows.append((r.job.name, r.job.type, str(r.frames) if r.ok else "-",
                     str(r.rendered) if r.ok else "-", f"{r.seconds:.1f}",
                     "ok" if r.ok else "FAILED", short(r.output) if r.ok else r.error))
    widths = [max(len(row[c]) for row in rows) for c in range(6)]
    lines = ["  ".join(row[c].ljust(widths[c]) for c in range(6)) + "  " + row[6] for row in rows]
    failed = sum(1 for r in results if not r.ok)
    lines.append(f"{len(results) - failed} of {len(results)} jobs done"
                 + (f", {failed} failed" if failed else ""))
    return "\n".join(lines)
