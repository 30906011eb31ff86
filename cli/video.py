"""`nehad video`: a thin wrapper around :mod:`nehad.runtime.video`
and :mod:`nehad.runtime.distribute`; its backend helpers serve `nehad batch` too.

Ctrl-C stops a run with exit status 130 and a line saying how many frames are kept and how to
finish (``--resume``); frames already written are whole (atomic writes).
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from .errors import user_errors
from .params import BACKGROUND, FiniteFloat, SIZE

#: Most pool workers chosen by default (more can be asked for with --workers).
DEFAULT_WORKERS_CAP = 8
#: Fewer frames than this render in the calling process unless --workers says otherwise.
SMALL_JOB = 16


def default_workers() -> int:
    """One pool worker per core (at most DEFAULT_WORKERS_CAP)."""
    return max(1, min(os.cpu_count() or 1, DEFAULT_WORKERS_CAP))


def make_cli_backend(workers, scheduler, threads, frames: int | None = None):
    """The backend of --workers / --scheduler / --threads; with neither, a local pool of
    :func:`default_workers` processes, or this process alone for fewer than
    :data:`SMALL_JOB` frames (starting a pool takes about a second or two)."""
    from nehad.runtime.distribute import make_backend

    if scheduler is not None and workers is not None:
        raise click.UsageError("--workers and --scheduler exclude each other (the Dask cluster "
                               "has its own workers)")
    if scheduler is not None and "://" not in scheduler:
        raise click.BadParameter(f"{scheduler!r}: expected an address like tcp://HOST:8786",
                                 param_hint="'--scheduler'")
    if scheduler is None and workers is None:
        workers = 1 if frames is not None and frames < SMALL_JOB else default_workers()
    backend = make_backend(workers, scheduler, threads)
    if scheduler is not None:
        backend.client  # connect now: an unreachable scheduler is one error, not one per job
    return backend


def report_interrupted(frames_dir, total: int | None) -> None:
    from nehad.runtime.video import count_frames

    n = count_frames(frames_dir)
    of = f" of {total}" if total else ""
    click.echo(f"interrupted: {n}{of} frames are kept in {frames_dir}; run the same command with "
               f"--resume to render only the missing ones", err=True)
    from nehad.runtime.interrupts import exit_interrupted

    exit_interrupted(130)


@click.command()
@click.argument("model", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The .mp4 to write (H.264 yuv420p; atomically). May be left out with "
                   "--frames-dir (frames only).")
@click.option("--path", "path_spec", default="orbit", show_default=True, metavar="PATH",
              help="Camera path: orbit[:key=value,...], spiral[:...], default (the model's camera, "
                   "frozen), a camera file (FILE, or FILE.json:K for one camera), or DATA:test "
                   "(a dataset split, each view at its own time).")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Frames of an orbit, spiral or frozen camera (default 120); a camera list or "
                   "dataset split has its own count.")
@click.option("--fps", type=FiniteFloat(0.001, 1000), default=None,
              help="Frames per second of the video [default: 30].")
@click.option("--time", "time_spec", default=None, metavar="A:B|T|own",
              help="Time schedule: A:B sweeps t over the frames, T freezes it (bullet time), own "
                   "uses the views' times. Default: the views' own times for a dataset split, "
                   "else a sweep over the model's time range.")
@click.option("--size", type=SIZE, default=None, metavar="WxH",
              help="Frame size (same field of view); even numbers for H.264.")
@click.option("--background", type=BACKGROUND, default=None, metavar="R,G,B",
              help="Background colour (default: the model's).")
@click.option("--frames-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Keep the frames in this folder (frame_00000.png ...). Default: OUT.mp4.frames, "
                   "removed once the video is written.")
@click.option("--frame-format", type=click.Choice(["png", "exr"]), default=None,
              help="Frame files: 8-bit PNG or float EXR (linear) [default: png].")
@click.option("--resume", is_flag=True,
              help="Keep the frames an interrupted run left and render only the missing ones.")
@click.option("--side-by-side", is_flag=True,
              help="With a DATA:SPLIT path: the render and the dataset image side by side.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Local pool size (default: one per core, at most 8, or 1 for fewer than 16 "
                   "frames; 1 renders in this process).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Render on this Dask scheduler's workers instead of a local pool.")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="Threads per frame (default: cores / workers locally; on Dask each worker's "
                   "share of its cores, or its $NEHAD_THREADS).")
@click.option("--crf", type=click.IntRange(0, 51), default=None,
              help="H.264 quality (lower: better, larger) [default: 18].")
@click.option("--extrapolate", is_flag=True, help="Allow times outside the trained range.")
@click.option("--lod", type=click.IntRange(min=0), default=None, metavar="K",
              help="Render streaming layers 0..K only (as nehad render --lod).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def video(model, output, path_spec, frames, fps, time_spec, size, background, frames_dir,
          frame_format, resume, side_by_side, workers, scheduler, threads, crf, extrapolate,
          lod, quiet):
    """Render a video of MODEL: any scene `nehad render` takes (an exported .onnx, a split
    layers folder, a training run folder, or a static 3DGS .ply).

    \b
    Examples:
      nehad video model.onnx -o orbit.mp4 --frames 120 --size 800x800
      nehad video model.onnx -o bullet.mp4 --path spiral --time 0.5
      nehad video model.onnx -o test.mp4 --path data/lego:test --side-by-side
      nehad video model.onnx -o t.mp4 --path cams.json:0 --time 0:1 --frames 60
      nehad video model.onnx -o big.mp4 --scheduler tcp://head:8786

    Frames are rendered as independent tasks, written atomically to the frame folder, then
    encoded; an interrupted run continues with --resume.
    """
    from nehad.runtime.video import VideoJob, plan_video, run_video

    from .scenes import SCENE_OPENERS

    # VideoJob owns the defaults (the [default: ...] texts above are checked against it by
    # tests/test_video.py): an option left out is not passed
    given = {k: v for k, v in dict(fps=fps, frame_format=frame_format, crf=crf).items()
             if v is not None}
    job = VideoJob(model=model, output=output, path=path_spec, time=time_spec, frames=frames,
                   size=size, frames_dir=frames_dir, side_by_side=side_by_side,
                   background=background, extrapolate=extrapolate, lod=lod,
                   openers=SCENE_OPENERS, **given)
    plan = None
    try:
        with user_errors():
            from nehad.runtime.outputs import check_outputs

            check_outputs([("-o", output), ("--frames-dir", frames_dir, "frame_*")],
                          [("MODEL", model), ("--path", path_spec)])
            plan = plan_video(job)
            with make_cli_backend(workers, scheduler, threads, len(plan.tasks)) as backend:
                rep = run_video(job, backend, resume=resume, progress=not quiet, plan=plan)
    except KeyboardInterrupt:
        if plan is None:
            raise
        report_interrupted(plan.frames_dir, len(plan.tasks))
    _echo_report(rep, job.frame_format)


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _echo_report(rep, fmt: str) -> None:
    if rep.output is not None:
        click.echo(f"{rep.output}: {_plural(rep.frames, 'frame')} {rep.width}x{rep.height} at "
                   f"{rep.fps:g} fps ({rep.frames / rep.fps:.1f} s), {rep.encoder}")
    if rep.rendered:
        line = (f"rendered {_plural(rep.rendered, 'frame')} in {rep.render_seconds:.1f} s "
                f"({rep.rendered / rep.render_seconds:.1f} frames/s, {rep.workers})")
    else:
        line = "rendered 0 frames"
    if rep.skipped:
        line += f", {rep.skipped} already there kept"
    if rep.output is not None and rep.encode_seconds:
        line += f"; encoded in {rep.encode_seconds:.1f} s"
    click.echo(line)
    if rep.kept_frames:
        click.echo(f"frames: {rep.frames_dir}/frame_00000.{fmt} .. frame_{rep.frames - 1:05d}.{fmt}")


__all__ = ["video", "default_workers", "make_cli_backend", "report_interrupted"]
