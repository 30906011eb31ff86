"""Videos: frames rendered by any backend into a folder, then encoded (docs/design.md section 10, issue 5).

    job = VideoJob(model="model.onnx", output="orbit.mp4", path="orbit", frames=120, fps=30,
                   size=(400, 400))
    with make_backend(workers=2) as backend:
        report = run_video(job, backend)

How a video is made:

1. :func:`plan_video` turns the job into frames (camera path and time schedule of
   :mod:`nehad.runtime.paths`), checks the output and size (an odd width or height is padded by
   one repeated column or row when encoded: runtime/mp4.py) and names the frame folder: ``--frames-dir`` when given (kept), else ``OUT.mp4.frames``
   beside the video (removed once the video is written). Nothing is rendered yet.
2. :func:`prepare_frames` readies the folder: ``nehad-frames.json`` (a manifest: model hash, frame
   count, size, background, a hash of every camera and time) and, with ``resume``, the frames
   already there; a manifest that differs from the job refuses to resume and names the keys.
   Without ``resume`` old frames are removed. Temporary files of an interrupted write are removed
   (and the stale partial video of a killed encoder beside the output, issue 15). The output and
   the frame folder are locked while a run uses them (:mod:`nehad.runtime.lock`): a second run
   with the same ones refuses at once instead of deleting the folder under the first.
3. The backend renders the missing frames (``frame_00000.png`` ...; PNG 8-bit or EXR float),
   each written atomically, so an interrupted run (Ctrl-C, SIGKILL, a lost server) leaves only
   whole frames and ``resume`` renders only the missing ones.
4. :func:`encode_video` writes the mp4 atomically with the one encoder of runtime/mp4.py: H.264
   (libx264) yuv420p through PyAV, or OpenCV's ``mp4v`` when PyAV is missing. With ``resume``, a video that is already there and
   whose work folder is gone (an earlier run finished it) is kept as it is.

With ``side_by_side`` (a ``DATA:SPLIT`` path), each frame is the render with the dataset's image
to its right. All problems with the inputs raise :class:`VideoError` (or the path/camera errors)
with a message naming the input.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .distribute import FrameResult, FrameTask, PoolBackend
from .lock import output_lock
from .memory import check_frame_memory
from .errors import InputProblem
from .mp4 import DEFAULT_CRF, DEFAULT_FPS, encode, video_rate  # noqa: F401  (video_rate: API)
from .paths import PathError, Reference, parse_path_spec, parse_time_spec, plan_frames

__all__ = ["VideoError", "VideoJob", "VideoPlan", "VideoReport", "plan_video", "prepare_frames",
           "run_video", "encode_video", "probe_video", "scene_reference",
           "frame_name", "video_rate", "count_frames", "VIDEO_SUFFIXES", "FRAME_FORMATS",
           "MANIFEST"]

VIDEO_SUFFIXES = (".mp4",)
FRAME_FORMATS = ("png", "exr")
MANIFEST = "nehad-frames.json"
MANIFEST_FORMAT = "nehad-frames/1"
_FRAME_RE = re.compile(r"^frame_\d{5}\.(png|exr)$")
_TMP_RE = re.compile(r"^\.(frame_\d{5}\..*\.tmp\.(png|exr)|nehad-frames\..*\.tmp\.json)$")


class VideoError(InputProblem):
    """A video job that cannot be done as given; the message names the input."""


def frame_name(index: int, fmt: str = "png") -> str:
    return f"frame_{index:05d}.{fmt}"


@dataclass
class VideoJob:
    """What to render (see the CLI's `nehad video` for the meaning of each field)."""

    model: Path
    output: Path | None = None  # .mp4; None: the frame sequence only (needs frames_dir)
    path: str = "orbit"
    time: str | None = None  # "A:B", "T", "own"; None: the path's own times or the time range
    frames: int | None = None
    size: tuple[int, int] | None = None
    fps: float = DEFAULT_FPS
    frames_dir: Path | None = None
    frame_format: str = "png"
    side_by_side: bool = False
    background: tuple[float, float, float] | None = None
    extrapolate: bool = False
    crf: int = DEFAULT_CRF
    encoder: str = "auto"  # auto (PyAV, else OpenCV), pyav, opencv
    name: str = ""
    lod: int | None = None  # streaming layers 0..lod (None: all)
    openers: tuple = ()  # scene openers for a training run folder (runtime/scene.py)


@dataclass
class VideoPlan:
    job: VideoJob
    frames: list  # PlannedFrame
    tasks: list[FrameTask]
    frames_dir: Path
    keep_frames: bool
    width: int  # of a frame (twice the render width side by side)
    height: int
    background: tuple
    manifest: dict = field(repr=False, default_factory=dict)
    gaussians: int = 0  # in the model (for the memory bound)

    def frame_path(self, index: int) -> Path:
        return self.frames_dir / frame_name(index, self.job.frame_format)


@dataclass
class VideoReport:
    output: Path | None
    frames_dir: Path
    frames: int
    rendered: int
    skipped: int
    width: int
    height: int
    fps: float
    render_seconds: float
    encode_seconds: float
    encoder: str
    kept_frames: bool
    workers: str = ""


# ---------------------------------------------------------------------------------------------
# planning


def scene_reference(scene) -> tuple[Reference, tuple]:
    """(Reference, default background) of an opened scene (runtime/scene.py)."""
    time_range = tuple(scene.time_range) if scene.dynamic else None
    return Reference(scene.default_camera, scene.aabb, time_range), \
        tuple(scene.default_background)


def _plan_hash(frames) -> str:
    h = hashlib.sha256()
    for f in frames:
        c = f.camera
        h.update(np.asarray([c.width, c.height, c.fx, c.fy, c.cx, c.cy], np.float64).tobytes())
        h.update(np.asarray(c.world_to_camera, np.float64).tobytes())
        h.update(repr(f.time).encode())
        h.update(repr(f.ground_truth).encode())
    return h.hexdigest()


def _opt(key: str) -> str:
    """An input named in a message: a placeholder each caller shows in its own words
    (runtime/errors.py; the CLI's options, a jobs.yaml's keys)."""
    return "{" + key + "}"


def plan_video(job: VideoJob, threads: int | None = None) -> VideoPlan:
    """Validate `job` and turn it into frame tasks (nothing is rendered or written)."""
    o = _opt
    model = Path(job.model)
    out = Path(job.output) if job.output is not None else None
    if out is None and job.frames_dir is None:
        raise VideoError(f"give an output video ({o('output')} OUT.mp4), a frame folder "
                         f"({o('frames_dir')}), or both")
    if out is not None:
        if out.suffix.lower() not in VIDEO_SUFFIXES:
            raise VideoError(f"{o('output')} {out}: the video must end in "
                             f"{', '.join(VIDEO_SUFFIXES)}")
        if not out.parent.is_dir():
            raise VideoError(f"{o('output')} {out}: output folder {out.parent} does not exist")
        if out.is_dir():
            raise VideoError(f"{o('output')} {out}: is a folder")
    if job.frame_format not in FRAME_FORMATS:
        raise VideoError(f"{o('frame_format')} {job.frame_format!r}: expected one of "
                         f"{', '.join(FRAME_FORMATS)}")
    if not (isinstance(job.fps, (int, float)) and math.isfinite(job.fps) and 0 < job.fps <= 1000):
        raise VideoError(f"{o('fps')} {job.fps}: must be a number in (0, 1000]")
    if not 0 <= int(job.crf) <= 51:
        raise VideoError(f"{o('crf')} {job.crf}: must be in 0..51")
    if job.encoder not in ("auto", "pyav", "opencv"):
        raise VideoError(f"{o('encoder')} {job.encoder!r}: expected auto, pyav or opencv")
    if job.frames_dir is not None:
        fd = Path(job.frames_dir)
        if fd.exists() and not fd.is_dir():
            raise VideoError(f"{o('frames_dir')} {fd}: exists and is not a folder")
        if not fd.parent.is_dir():
            raise VideoError(f"{o('frames_dir')} {fd}: parent folder {fd.parent} does not exist")
    try:
        pspec = parse_path_spec(job.path)
    except PathError as e:
        raise PathError(f"{o('path')} {e.template}") from None
    try:
        tspec = parse_time_spec(job.time) if job.time is not None else None
    except PathError as e:
        raise PathError(f"{o('time')} {e.template}") from None
    if job.side_by_side and pspec.kind != "dataset":
        raise VideoError(f"{o('side_by_side')} needs a dataset path with ground truth (DATA:test), "
                         f"not {job.path!r}")
    from .scene import open_scene

    scene = open_scene(model, lod=job.lod, openers=tuple(job.openers))
    ref, default_bg = scene_reference(scene)
    n_gaussians = scene.num_gaussians
    bg = tuple(float(v) for v in (job.background or default_bg))
    frames = plan_frames(pspec, tspec, job.frames, job.size, ref, job.extrapolate,
                         {k: o(k) for k in ("path", "time", "frames", "extrapolate")})
    w, h = frames[0].camera.width, frames[0].camera.height
    if any((f.camera.width, f.camera.height) != (w, h) for f in frames):
        raise VideoError(f"{o('path')} {job.path}: the cameras have different image sizes; "
                         f"give {o('size')} WxH")
    fw = 2 * w if job.side_by_side else w  # an odd size is padded by the encoder (runtime/mp4.py)
    # one frame must fit here: it is drawn here, or read back here to be encoded (issue 15)
    check_frame_memory(w, h, n_gaussians, _size_input(job, o, w, h), out_width=fw)
    if job.frames_dir is not None:
        frames_dir, keep = Path(job.frames_dir), True
    else:
        frames_dir, keep = out.with_name(out.name + ".frames"), False
    frames_dir = frames_dir.absolute()
    model_abs = str(model.absolute())
    tasks = [FrameTask(model_abs, f.index, f.camera, f.time, bg,
                       str(frames_dir / frame_name(f.index, job.frame_format)),
                       f.ground_truth if job.side_by_side else None, threads,
                       lod=job.lod, openers=tuple(job.openers))
             for f in frames]
    manifest = {"format": MANIFEST_FORMAT, "model": model_abs,
                "model_sha256": scene.digest(), "lod": job.lod, "frames": len(frames), "width": fw,
                "height": h, "frame_format": job.frame_format, "background": list(bg),
                "side_by_side": bool(job.side_by_side), "plan_sha256": _plan_hash(frames)}
    return VideoPlan(job, frames, tasks, frames_dir, keep, fw, h, bg, manifest, n_gaussians)


def _size_input(job: VideoJob, o, w: int, h: int) -> str:
    """How the frame size was given, for messages: the size option, else the camera path."""
    if job.size is not None:
        return f"{o('size')} {job.size[0]}x{job.size[1]}"
    return f"{o('path')} {job.path} (frames of {w}x{h})"


def prepare_frames(plan: VideoPlan, resume: bool) -> list[int]:
    """Ready the frame folder (module doc, step 2); return the indices still to render."""
    from .images import atomic_path

    d = plan.frames_dir
    d.mkdir(exist_ok=True)
    for p in d.iterdir():
        if _TMP_RE.match(p.name):
            p.unlink(missing_ok=True)
    mpath = d / MANIFEST
    ours = [p for p in d.iterdir() if _FRAME_RE.match(p.name)]
    if resume:
        old = None
        if mpath.is_file():
            try:
                old = json.loads(mpath.read_text(encoding="utf-8"))
            except (OSError, ValueError, RecursionError):
                old = None
            if not isinstance(old, dict):  # a list, a number: not a manifest either
                old = None
        if old is None and ours:
            raise VideoError(f"{d}: holds frames but no readable {MANIFEST}; cannot tell what "
                             f"rendered them (remove them or leave out resume)")
        if old is not None:
            # the model is compared by content (model_sha256): a moved copy resumes too
            differ = [k for k in plan.manifest if k != "model" and old.get(k) != plan.manifest[k]]
            if differ:
                raise VideoError(f"{d}: the frames there were rendered with other settings "
                                 f"({', '.join(differ)} differ); leave out resume to re-render, "
                                 f"or use another frame folder")
    else:
        for p in ours:
            p.unlink(missing_ok=True)
    with atomic_path(mpath, VideoError) as tmp:
        Path(tmp).write_text(json.dumps(plan.manifest, indent=1) + "\n", encoding="utf-8")
    return [t.index for t in plan.tasks if not os.path.exists(t.output)]


# ---------------------------------------------------------------------------------------------
# encoding


def encode_video(frames, output, fps: float = DEFAULT_FPS, crf: int = DEFAULT_CRF,
                 encoder: str = "auto") -> str:
    """Encode `frames` (image paths, or uint8/float (H, W, 3) arrays) into the mp4 `output`
    atomically, with the one encoder of runtime/mp4.py; returns the encoder used."""
    return encode(frames, output, fps, crf, encoder, error=VideoError)


def probe_video(path) -> dict:
    """What PyAV reads back from a video: frames (decoded and counted), codec, pix_fmt, fps,
    width, height."""
    import av

    with av.open(str(path)) as c:
        s = c.streams.video[0]
        info = {"codec": s.codec_context.name, "pix_fmt": s.codec_context.pix_fmt,
                "fps": float(s.average_rate) if s.average_rate else float("nan"),
                "width": s.codec_context.width, "height": s.codec_context.height}
        info["frames"] = sum(1 for _ in c.decode(video=0))
    return info


# ---------------------------------------------------------------------------------------------
# running


def _progress_bar(total: int, initial: int, desc: str, enabled: bool):
    from tqdm import tqdm

    # disable=None: shown on a terminal, left out of logs (like nehad synth's and train's bars)
    return tqdm(total=total, initial=initial, desc=desc, unit="frame",
                disable=None if enabled else True, file=sys.stderr, leave=False,
                dynamic_ncols=True)


def run_video(job: VideoJob, backend, resume: bool = False, progress: bool = True,
              on_result=None, plan: VideoPlan | None = None) -> VideoReport:
    """Plan, render (with `backend`: a Serial/Pool/Dask backend) and encode `job`; with
    `resume`, frames already in the frame folder are kept (module doc). `on_result` is called
    with each :class:`FrameResult`; `plan` is `plan_video(job)` when the caller made it already.
    A KeyboardInterrupt leaves the whole frames in place.

    The output and the frame folder are locked for the run (:mod:`nehad.runtime.lock`): a second
    run with either of them refuses at once. With a local pool, the frames the workers draw at
    once must fit in memory together (:mod:`nehad.runtime.memory`)."""
    plan = plan if plan is not None else plan_video(job)
    workers = min(backend.workers, len(plan.tasks)) if isinstance(backend, PoolBackend) else 1
    if workers > 1:
        f0 = plan.frames[0].camera
        check_frame_memory(f0.width, f0.height, plan.gaussians,
                           _size_input(job, _opt, f0.width, f0.height),
                           parallel=workers, out_width=plan.width)
    with contextlib.ExitStack() as locks:
        for target in ([Path(job.output)] if job.output is not None else []) + [plan.frames_dir]:
            locks.enter_context(output_lock(target, f"nehad batch (job {job.name!r})"
                                            if job.name else "nehad video"))
        try:
            return _run_locked(job, plan, backend, resume, progress, on_result)
        except Exception:
            # a failure before the first frame (a full disk): no frame folder is left behind;
            # whole frames stay for --resume (issue 26)
            if plan.frames_dir.is_dir() and count_frames(plan.frames_dir) == 0:
                _remove_frames(plan)
            raise


def _run_locked(job: VideoJob, plan: VideoPlan, backend, resume: bool, progress: bool,
                on_result) -> VideoReport:
    from .tempfiles import remove_stale_temps

    n = len(plan.tasks)
    if job.output is not None:  # a killed encoder's partial video (issue 15)
        remove_stale_temps(Path(job.output).parent, Path(job.output).name)
    if (resume and job.output is not None and Path(job.output).is_file() and not plan.keep_frames
            and not plan.frames_dir.exists()):
        # finished by an earlier run (its work folder is gone): nothing to resume
        return VideoReport(Path(job.output), plan.frames_dir, n, 0, n, plan.width, plan.height,
                           job.fps, 0.0, 0.0, "kept (already finished)", False,
                           getattr(backend, "name", ""))
    todo = prepare_frames(plan, resume)
    skipped = n - len(todo)
    tasks = [plan.tasks[i] for i in todo]
    start = time.perf_counter()
    with _progress_bar(n, skipped, job.name or "frames", progress) as bar:
        def done(r: FrameResult):
            bar.update(1)
            if on_result:
                on_result(r)

        if tasks:
            backend.run(tasks, done)
    render_s = time.perf_counter() - start
    # (a result says "skipped" when a lost worker had written the frame before it died and the
    # scheduler ran the task again: that frame still counts as rendered by this run)
    missing = [i for i in range(n) if not plan.frame_path(i).is_file()]
    if missing:
        raise VideoError(f"{plan.frames_dir}: frames {missing[:5]} are missing after rendering")
    encode_s, encoder = 0.0, ""
    if job.output is not None:
        t0 = time.perf_counter()
        encoder = encode_video([plan.frame_path(i) for i in range(n)], job.output, job.fps,
                               job.crf, job.encoder)
        encode_s = time.perf_counter() - t0
        if not plan.keep_frames:
            _remove_frames(plan)
    return VideoReport(Path(job.output) if job.output is not None else None, plan.frames_dir, n,
                       n - skipped, skipped, plan.width, plan.height, job.fps, render_s, encode_s,
                       encoder, plan.keep_frames, getattr(backend, "name", ""))


def _remove_frames(plan: VideoPlan) -> None:
    d = plan.frames_dir
    for p in d.iterdir():
        if _FRAME_RE.match(p.name) or _TMP_RE.match(p.name) or p.name == MANIFEST:
            p.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        d.rmdir()


def count_frames(frames_dir) -> int:
    """Whole frames in a frame folder (for the message after an interruption)."""
    d = Path(frames_dir)
    if not d.is_dir():
        return 0
    return sum(1 for p in d.iterdir() if _FRAME_RE.match(p.name))
