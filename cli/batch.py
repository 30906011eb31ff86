"""`nehad batch JOBS.yaml`: a thin wrapper around :mod:`nehad.runtime.batch`; the file's format
is described there and in docs/video.md."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from .errors import user_errors
from .scenes import SCENE_OPENERS
from .video import make_cli_backend


@click.command()
@click.argument("jobs_file", metavar="JOBS.yaml", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Local pool size (default: the file's workers, else one per core, at most 8).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Render on this Dask scheduler's workers (default: the file's scheduler).")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="Threads per frame (see nehad video --help).")
@click.option("--resume", is_flag=True,
              help="Keep frames and images that an interrupted run left; render the rest.")
@click.option("--check", is_flag=True, help="Only check the jobs file and exit.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def batch(jobs_file, workers, scheduler, threads, resume, check, quiet):
    """Run the renders and videos listed in JOBS.yaml, one after the other.

    \b
    jobs:
      - {name: orbit, model: model.onnx, output: orbit.mp4, frames: 120, size: 400x400}
      - {name: still, model: model.onnx, output: still.png, view: cam.json, time: 0.5}

    A failing job is reported and the others still run; the summary table lists every job and
    the exit status is 1 when one failed. A mistake in the file (unknown key, bad value) is
    reported with the job and the key before anything runs. See docs/video.md for every key.
    """
    from nehad.runtime.batch import format_summary, load_batch, run_batch

    with user_errors():
        spec = load_batch(jobs_file, check_files=check)
    if check:
        kinds = ", ".join(f"{j.name} ({j.type})" for j in spec.jobs)
        click.echo(f"{jobs_file}: {len(spec.jobs)} jobs: {kinds}")
        return
    if scheduler is None and workers is None:
        scheduler = spec.scheduler
        workers = spec.workers if spec.scheduler is None else None
    if threads is None:
        threads = spec.threads

    def report(r):
        if not quiet:
            status = "ok" if r.ok else f"FAILED: {r.error}"
            click.echo(f"[{r.job.index + 1}/{len(spec.jobs)}] {r.job.name}: {status}", err=True)

    try:
        with user_errors():
            with make_cli_backend(workers, scheduler, threads) as backend:
                results = run_batch(spec, backend, resume=resume, progress=not quiet,
                                    on_job=report, openers=SCENE_OPENERS)
    except KeyboardInterrupt:
        click.echo("interrupted: run the same command with --resume to render only what is "
                   "missing", err=True)
        from nehad.runtime.interrupts import exit_interrupted

        exit_interrupted(130)
    click.echo(format_summary(results))
    failed = [r.job.name for r in results if not r.ok]
    if failed:
        click.echo(f"Error: {len(failed)} of {len(results)} jobs failed: {', '.join(failed)} "
                   f"(each one's error is in the table above)", err=True)
        sys.exit(1)


__all__ = ["batch"]
