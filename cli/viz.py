"""`nehad viz trajectories|masks` and `nehad report` (issue 8): look at what a model learned.

Thin commands over :mod:`nehad.viz`. Like the rest of the CLI, nothing heavy is imported at
module level (``nehad --help`` loads neither numpy nor torch); torch is imported only when a
training run is opened.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from .errors import InputError, user_errors
from .params import BACKGROUND, FINITE, FiniteFloat, SIZE


def _check_out(path: Path, option: str, suffixes, what: str) -> None:
    if path.suffix.lower() not in suffixes:
        raise InputError(f"{option} {path}: {what} must end in {', '.join(suffixes)}")
    if not path.parent.is_dir():
        raise InputError(f"{option} {path}: output folder {path.parent} does not exist")
    if path.is_dir():
        raise InputError(f"{option} {path}: is a folder")


def _need_torch(run: Path, what: str) -> None:
    """A training run is read with torch: say so in one line when it is not installed."""
    try:
        import torch  # noqa: F401
    except ImportError:
        raise InputError(f"{run}: {what} needs torch to read a training run (pip install -e "
                         f"'.[train]' torch==2.13.0)") from None


def _dynamic_source(scene: Path):
    """A run folder or an exported .onnx (a static PLY has no motion)."""
    from .scenes import open_cli_scene

    if scene.suffix.lower() == ".ply" and not scene.is_dir():
        raise InputError(f"{scene}: a 3DGS PLY is static (no trajectories); give a training run "
                         f"folder or an exported .onnx model")
    if scene.is_dir():
        _need_torch(scene, "drawing trajectories from it")
    return open_cli_scene(scene)


def _view(view: str | None, source, size):
    """--view, else the scene's default camera (an .onnx file's metadata, a run's first test
    camera): runtime.scene.choose_camera, the rule of every command."""
    from nehad.runtime.memory import check_frame_memory
    from nehad.runtime.scene import choose_camera

    camera = choose_camera(source, view, size)
    # the pictures are drawn by the rasterizer as `nehad render` draws: the same memory bound
    # (--size 32768x32768 was killed by the kernel's OOM killer)
    check_frame_memory(camera.width, camera.height, int(getattr(source, "num_gaussians", 0)),
                       f"--size {size[0]}x{size[1]}" if size else f"--view {view or 'default'}")
    return camera


def _check_time(source, t: float, extrapolate: bool = False) -> float:
    from nehad.runtime.scene import check_time

    return check_time(source, t, extrapolate)


def _bar(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", delay=1.0, disable=None, leave=False,
                file=sys.stderr)


@click.group()
def viz():
    """Look at what a model learned: Gaussian trajectories and the BED static/dynamic split."""


# ---------------------------------------------------------------------------------------------
# nehad viz trajectories


@viz.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--view", default=None, metavar="CAMERA",
              help="Camera (as for `nehad render`); default: the model's default camera or the "
                   "run's first test camera.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Image (.png, .jpg) or, with --video, an .mp4; written atomically.")
@click.option("--video", is_flag=True, help="Write an animated version (H.264 .mp4).")
@click.option("--count", type=click.IntRange(min=1), default=300, show_default=True,
              help="How many Gaussians to track.")
@click.option("--times", "n_times", type=click.IntRange(min=2), default=None,
              help="Sampled times over the time range [default: 32, or 60 with --video].")
@click.option("--select", type=click.Choice(["moving", "random"]), default="moving",
              show_default=True, help="moving: favour Gaussians that travel far; random: uniform.")
@click.option("--color", "color_by", type=click.Choice(["time", "track"]), default="time",
              show_default=True, help="Colour the paths by time (blue -> red) or per track.")
@click.option("--time", "base_time", type=FINITE, default=None,
              help="Time of the render under the paths [default: the first time].")
@click.option("--size", type=SIZE, default=None, metavar="WxH",
              help="Render at this size instead of the camera's, same field of view.")
@click.option("--background", type=BACKGROUND, default=None, metavar="R,G,B",
              help="Background colour [default: the model's].")
@click.option("--min-opacity", type=FiniteFloat(0.0, 1.0), default=0.1, show_default=True,
              help="Track only Gaussians at least this opaque.")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Seed of the sample.")
@click.option("--fps", type=FiniteFloat(min=1.0, max=240.0), default=24.0,
              show_default=True, help="Frame rate of the video.")
@click.option("--trail", type=click.IntRange(min=1), default=None,
              help="With --video: draw only the last N segments of each path.")
def trajectories(scene, view, output, video, count, n_times, select, color_by, base_time, size,
                 background, min_opacity, seed, fps, trail):
    """Draw the centres of a sample of Gaussians of SCENE (a training run folder or an exported
    .onnx model) tracked over time as coloured paths over a render (the paper's trajectory
    figure); with --video, an animation where the paths grow frame by frame."""
    with user_errors():
        if video:
            _check_out(output, "-o", (".mp4",), "with --video the output")
        else:
            from nehad.runtime.suffixes import STILL_SUFFIXES

            _check_out(output, "-o", STILL_SUFFIXES, "the image")
        from nehad.runtime.memory import check_plan_memory
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output)], [("SCENE", scene), ("--view", view)])
        if n_times is not None:  # every time holds its positions of the tracked Gaussians
            check_plan_memory(n_times * max(1, count // 100), f"--times {n_times}",
                              f"tracking {count} Gaussians over {n_times} times")
        source = _dynamic_source(scene)
        camera = _view(view, source, size)
        if base_time is not None:
            _check_time(source, base_time)
        from nehad.viz.trajectories import (compute_tracks, track_times, trajectory_frames,
                                            trajectory_image, write_video)

        times = track_times(source.time_range, n_times or (60 if video else 32))
        tracks = compute_tracks(source.gaussians, camera, times, count=count, mode=select,
                                seed=seed, min_opacity=min_opacity)
        bg = background or source.default_background
        if video:
            with _bar(len(times), "video") as bar:
                def frames():
                    for f in trajectory_frames(source.gaussians, camera, tracks, bg,
                                               trail=trail, color_by=color_by):
                        bar.update(1)
                        yield f

                n = write_video(output, frames(), fps=fps)
            what = f"{n} frames at {fps:g} fps, H.264"
        else:
            from nehad.runtime.images import write_image

            img = trajectory_image(source.gaussians, camera, tracks, bg, base_time,
                                   color_by=color_by)
            write_image(output, img / 255.0)
            what = "PNG" if output.suffix.lower() == ".png" else "JPEG"
    lo, hi = float(times[0]), float(times[-1])
    import numpy as np

    click.echo(f"{output}: {camera.width}x{camera.height} {what}; {len(tracks)} Gaussians tracked "
               f"over {len(times)} times in [{lo:g}, {hi:g}], path length median "
               f"{float(np.median(tracks.path_length)):.3g} / max "
               f"{float(tracks.path_length.max()):.3g} world units")


# ---------------------------------------------------------------------------------------------
# nehad viz masks


def _parse_ids(text: str | None):
    if text is None:
        return None
    try:
        ids = sorted({int(p) for p in text.split(",") if p.strip()})
    except ValueError:
        raise InputError(f"--moving-ids {text}: expected comma-separated integer ids, "
                         f"e.g. 1,2") from None
    if not ids or min(ids) < 1:
        raise InputError(f"--moving-ids {text}: ids are labels >= 1 (0 is the background)")
    return ids


@viz.command()
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--view", default=None, metavar="CAMERA",
              help="Camera of the weight render; default: the run's first test camera.")
@click.option("--time", "time_", type=FINITE, default=None,
              help="Time of the weight render [default: the view's time, else mid-range].")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the weight render (.png/.jpg): each Gaussian coloured by its BED weight "
                   "1 - M_pos, blue static to red dynamic.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write a plot (.png) of the fraction of dynamic Gaussians over time.")
@click.option("--times", "n_times", type=click.IntRange(min=2), default=41, show_default=True,
              help="Times sampled for --plot.")
@click.option("--threshold", type=FiniteFloat(0.0, 1.0), default=0.5, show_default=True,
              help="A Gaussian (or pixel) is dynamic when its weight exceeds this.")
@click.option("--score", is_flag=True,
              help="Score the split against the moving objects on every frame of --split: IoU, "
                   "precision, recall, AUC, mean weights.")
@click.option("--split", type=click.Choice(["test", "val", "train"]), default="test",
              show_default=True, help="Frames to score.")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Dataset folder (default: the one the run was trained on).")
@click.option("--moving-ids", default=None, metavar="ID,ID",
              help="Label ids of the moving objects [default: detected from the train masks].")
@click.option("--synth-scene", default=None,
              help="For a `nehad synth` dataset: its scene (spheres, boxes) [default: recognised].")
@click.option("--max-frames", type=click.IntRange(min=0), default=0,
              help="Score only the first N frames (0 = all).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the scores (summary and per frame) as JSON.")
@click.option("--size", type=SIZE, default=None, metavar="WxH",
              help="Size of the weight render [default: the camera's].")
def masks(run, view, time_, output, plot, n_times, threshold, score, split, data_dir,
          moving_ids, synth_scene, max_frames, json_out, size):
    """Show and score the Boltzmann equilibrium (BED) split of a training RUN.

    -o renders the Gaussians coloured by their BED weight 1 - M_pos at --time (low: held at
    equilibrium, static; high: deformed); --plot draws the fraction of dynamic Gaussians over
    time; --score compares the split with the moving objects' masks (MuJoCo label
    masks, or the scene description of a `nehad synth` dataset). Needs a training run with the
    masks on (`--set field.bed_position=true`; off in the recipe since 2026-11-27): an exported
    .onnx model has no mask output.
    """
    if output is None and plot is None and not score:
        raise click.UsageError("nothing to do: give -o IMAGE, --plot PLOT and/or --score")
    with user_errors():
        if run.suffix.lower() == ".onnx" and not run.is_dir():
            raise InputError(f"{run}: BED masks need the training run folder (with model.pt); an "
                             f"exported .onnx model has no mask output")
        if not run.is_dir():
            raise InputError(f"{run}: not a training run folder")
        if output is not None:
            from nehad.runtime.suffixes import STILL_SUFFIXES

            _check_out(output, "-o", STILL_SUFFIXES, "the image")
        if plot is not None:
            _check_out(plot, "--plot", (".png",), "the plot")
        if json_out is not None:
            _check_out(json_out, "--json", (".json",), "the scores file")
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output), ("--plot", plot), ("--json", json_out)],
                      [("RUN", run), ("--view", view)])
        ids = _parse_ids(moving_ids)
        _need_torch(run, "the BED split")
        from .scenes import open_cli_scene

        source = open_cli_scene(run)  # a RunScene (nehad/run_scene.py): loads the torch model
        from nehad.viz.masks import bed_status

        why = bed_status(source.model)
        if why is not None:
            raise InputError(f"{run}: this run has no BED position mask: {why}")
        lines = []
        if output is not None:
            import numpy as np

            from nehad.runtime.images import write_image
            from nehad.viz.masks import bed_weights, render_weights, weight_image

            camera = _view(view, source, size)
            t = time_ if time_ is not None else camera.time
            if t is None:
                lo, hi = source.time_range
                t = 0.5 * (lo + hi)
            t = _check_time(source, t)
            w = bed_weights(source.model, t)
            wmap, alpha = render_weights(source.gaussians(t), w, camera)
            write_image(output, weight_image(wmap, alpha, source.default_background))
            seen = alpha > 0.5
            px = float((np.nan_to_num(wmap[seen]) > threshold).mean()) if seen.any() else 0.0
            lines.append(f"{output}: {camera.width}x{camera.height} BED weights at t = {t:g}; "
                         f"{float((w > threshold).mean()):.1%} of {len(w)} Gaussians dynamic "
                         f"(w > {threshold:g}), mean weight {float(w.mean()):.3f}; {px:.1%} of "
                         f"covered pixels dynamic")
        if plot is not None:
            from nehad.runtime.images import write_image
            from nehad.viz.masks import dynamic_fraction, fraction_plot
            from nehad.runtime.memory import check_plan_memory
            from nehad.viz.trajectories import track_times

            # as `viz trajectories --times`: 10**20 was a traceback of numpy's linspace
            check_plan_memory(n_times, f"--times {n_times}",
                              f"the BED weights of every Gaussian at {n_times} times")
            times = track_times(source.time_range, n_times)
            frac = dynamic_fraction(source.model, times, threshold)
            mean_w = dynamic_fraction(source.model, times, threshold, weighted=True)
            write_image(plot, fraction_plot(times, frac, threshold, mean_w) / 255.0)
            lines.append(f"{plot}: fraction of dynamic Gaussians over {n_times} times: min "
                         f"{float(frac.min()):.1%}, mean {float(frac.mean()):.1%}, max "
                         f"{float(frac.max()):.1%}")
        result = None
        if score:
            from nehad.viz.masks import score_run

            with _bar(None, f"score {split}") as bar:
                result = score_run(run, split, data_dir, threshold, ids, synth_scene, max_frames,
                                   model=source.model, run_info=source.info,
                                   progress=lambda: bar.update(1))
            if json_out is not None:
                import json

                from nehad.runtime.images import atomic_path
                from nehad.viz.masks import scores_json

                with atomic_path(json_out) as tmp:
                    Path(tmp).write_text(json.dumps(scores_json(result), indent=1) + "\n")
    for line in lines:
        click.echo(line)
    if result is not None:
        from nehad.viz.masks import format_scores

        click.echo(format_scores(result))
        if json_out is not None:
            click.echo(f"wrote {json_out}")
    elif json_out is not None:
        click.echo("note: --json is written only with --score", err=True)


# ---------------------------------------------------------------------------------------------
# nehad report


@click.command()
@click.argument("run", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The .html file to write (one self-contained page, images inlined).")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Dataset folder (default: the one the run was trained on).")
@click.option("--frames", type=click.IntRange(min=0), default=4, show_default=True,
              help="Test frames shown as render beside ground truth.")
@click.option("--no-score", is_flag=True,
              help="Skip scoring the BED split against the moving objects (renders every test "
                   "frame).")
@click.option("--max-side", type=click.IntRange(min=32), default=480, show_default=True,
              help="Longest side of the pictures in the page (renders are made at that size).")
def report(run, output, data_dir, frames, no_score, max_side):
    """Write one self-contained HTML page about the training RUN: its config, loss and PSNR
    curves, the metrics table (from `nehad eval`), test renders beside ground truth, Gaussian
    trajectories and the BED static/dynamic split with its score."""
    with user_errors():
        _check_out(output, "-o", (".html", ".htm"), "the report")
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output)], [("RUN", run)])
        from nehad.runtime.memory import check_frame_memory

        check_frame_memory(max_side, max_side, 0, f"--max-side {max_side}")
        if run.suffix.lower() == ".onnx" and not run.is_dir():
            raise InputError(f"{run}: a report needs the training run folder (config, logs, "
                             f"model.pt), not an exported .onnx model")
        if not (run / "model.pt").is_file():
            raise InputError(f"{run}: not a finished training run (no model.pt)")
        _need_torch(run, "the report")
        if data_dir is not None:  # given, it must be a dataset (the run's own may have moved)
            from nehad.data.loader import detect_format

            detect_format(data_dir)
        from nehad.viz.report import build_report

        info = build_report(run, output, data_dir=data_dir, frames=frames, score=not no_score,
                            max_side=max_side, log=lambda m: click.echo(m, err=True))
    click.echo(f"{output}: {info['bytes'] / 1e6:.2f} MB, {info['images']} images; "
               f"sections: {', '.join(info['sections'])}")
