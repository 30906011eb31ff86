"""`nehad render` and `nehad ply`: one view of a scene as an image, or its Gaussians at a time
as 3DGS PLY / .splat files. Both parse, then call the runtime's scene (runtime/scene.py) and its
all-or-nothing writer (runtime/render.py)."""

from __future__ import annotations

from pathlib import Path

import click

from .errors import InputError, user_errors
from .params import BACKGROUND, FINITE, SIZE
from .scenes import open_cli_scene


@click.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--view", "view", required=True, metavar="CAMERA",
              help="Camera: a cam.json, a 3DGS cameras.json entry, or a D-NeRF transforms file "
                   "with a frame index (transforms_test.json:3); 'default': the model's own.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Image to write (.png, .jpg, .exr, .tif); written atomically.")
@click.option("--depth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the expected view depth as a float32 .exr (0 where nothing is drawn).")
@click.option("--alpha", is_flag=True,
              help="Write RGBA (PNG/EXR/TIFF): colour over a transparent background.")
@click.option("--background", type=BACKGROUND, default=None, metavar="R,G,B",
              help="Background colour, values in [0, 1]. Default: 0,0,0 for a PLY.")
@click.option("--size", type=SIZE, default=None, metavar="WxH",
              help="Render at this size instead of the camera's, same field of view.")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None,
              help="Use SH up to this degree (default: all the scene has).")
@click.option("--time", "time_", type=FINITE, default=None,
              help="Time t in [0, 1] for a dynamic scene (a run directory or .onnx); default: the view's "
                   "own time when it has one (a D-NeRF frame).")
@click.option("--extrapolate", is_flag=True,
              help="Allow --time outside the trained time range.")
@click.option("--lod", type=click.IntRange(min=0), default=None, metavar="K",
              help="Render streaming layers 0..K only (a run trained with --lod-levels, its "
                   "export, or a --split-layers folder; default: all layers there are).")
def render(scene, view, output, depth, alpha, background, size, sh_degree, time_, extrapolate,
           lod):
    """Render SCENE through one camera to an image.

    SCENE is a standard 3DGS Gaussian PLY, an exported model (.onnx, rendered at --time with
    onnxruntime, no torch needed), a --split-layers folder, or a training run directory
    (rendered at --time by its torch model). All go through the same rasterizer.
    """
    from nehad.runtime.render import (ALPHA_SUFFIXES, IMAGE_SUFFIXES, check_output,
                                      render_view, write_all)
    from nehad.runtime.scene import choose_camera, scene_time

    if alpha and background is not None:
        raise click.UsageError("--alpha and --background exclude each other: an RGBA image "
                               "has a transparent background")
    with user_errors():
        check_output(output, IMAGE_SUFFIXES, "the image")
        if alpha and output.suffix.lower() not in ALPHA_SUFFIXES:
            raise InputError(f"-o {output}: --alpha needs a format with an alpha channel "
                             f"({', '.join(ALPHA_SUFFIXES)})")
        if depth is not None:
            check_output(depth, (".exr",), "the depth map", input="depth")
            if depth.resolve() == output.resolve():
                raise InputError(f"--depth {depth}: same file as -o")
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output), ("--depth", depth)], [("SCENE", scene), ("--view", view)])
        source = open_cli_scene(scene, lod=lod)
        camera = choose_camera(source, view, size)
        t = scene_time(source, camera, time_, extrapolate)
        if time_ is not None and not source.dynamic:
            click.echo(f"note: --time {time_:g} is ignored: {scene} is a static 3DGS PLY (the "
                       f"same Gaussians at every time)", err=True)
        drawn = render_view(source, camera, t, background, sh_degree, alpha,
                            check_memory=f"--size {size[0]}x{size[1]}" if size else
                            f"--view {view}")
        outputs = [(output, drawn.image)]
        if depth is not None:
            outputs.append((depth, drawn.depth))
        write_all(outputs)
    channels = "RGBA" if alpha else "RGB"
    click.echo(f"{output}: {camera.width}x{camera.height} {channels}, {source.describe()}, "
               f"rendered in {drawn.seconds:.2f} s")
    if depth is not None:
        click.echo(f"{depth}: depth (float32 EXR)")
    if not drawn.covered:
        click.echo("warning: no Gaussian is in front of the camera; the image is the background",
                   err=True)


def _check_sequence_space(folder: Path, frames: int, gaussians: int, sh_degree: int,
                          fmt: str) -> None:
    """Refuse `--frames N` when the N files would not fit on the disk of `folder` (a PLY
    Gaussian holds 14 + 3 (sh_degree + 1)^2 float32 values, a .splat one 32 bytes)."""
    import shutil

    per = 32 if fmt == "splat" else 4 * (14 + 3 * (sh_degree + 1) ** 2)
    need = frames * (gaussians * per + 1024)
    target = folder if folder.is_dir() else folder.parent
    try:
        free = shutil.disk_usage(target).free
    except OSError:
        return
    if need > free:
        import errno
        import os

        raise InputError(f"{folder}: {os.strerror(errno.ENOSPC)} for --frames {frames} "
                         f"({frames} {fmt} files of {gaussians} Gaussians need "
                         f"{need / 1e9:.3g} GB, {free / 1e9:.3g} GB are free)")


@click.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="The .ply (or .splat) to write; with --frames, a folder (created) for "
                   "frame_NNNN.ply.")
@click.option("--time", "time_", type=FINITE, default=None,
              help="Time t of the Gaussians (one frame).")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Write N frames at evenly spaced times over the time range instead.")
@click.option("--extrapolate", is_flag=True, help="Allow --time outside the trained time range.")
@click.option("--format", "fmt", type=click.Choice(["ply", "splat"]), default=None,
              help="ply (3DGS PLY, full SH) or splat (antimatter15 .splat for web viewers: DC "
                   "colour only); default: from -o's suffix, ply for --frames.")
@click.option("--lod", type=click.IntRange(min=0), default=None, metavar="K",
              help="Keep streaming layers 0..K only (as nehad render --lod).")
def ply(scene, output, time_, frames, extrapolate, fmt, lod):
    """Write the deformed Gaussians of SCENE (an exported .onnx, a split layers folder or a run
    folder) as standard 3DGS PLY (or .splat): one frame at --time, or --frames N evenly spaced
    frames into a folder."""
    import math

    import numpy as np

    from nehad.runtime.render import check_output, write_all, write_sequence
    from nehad.runtime.scene import check_time

    if (time_ is None) == (frames is None):
        raise click.UsageError("give exactly one of --time T and --frames N")
    with user_errors():
        if fmt is None:
            fmt = "splat" if frames is None and output.suffix.lower() == ".splat" else "ply"
        if frames is None:
            check_output(output, (f".{fmt}",), f"the {fmt.upper()} file")
        else:
            if output.exists() and not output.is_dir():
                raise InputError(f"-o {output}: exists and is not a folder")
            if not output.parent.is_dir():
                raise InputError(f"-o {output}: parent folder {output.parent} does not exist")
        if time_ is not None and not math.isfinite(time_):
            raise InputError(f"--time {time_}: not a finite number")
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output) if frames is None else ("-o", output, f"frame_*.{fmt}")],
                      [("SCENE", scene)])
        source = open_cli_scene(scene, lod=lod)
        from nehad.runtime.memory import check_cloud_memory
        from nehad.runtime.ply import write_gaussian_ply
        from nehad.runtime.splat import write_splat

        check_cloud_memory(source.num_gaussians, source.sh_degree, str(scene))
        if time_ is not None and not source.dynamic:
            click.echo(f"note: {scene} is a static 3DGS PLY: the Gaussians are the same at "
                       f"every time (--time {time_:g} changes nothing)", err=True)
        writer = write_splat if fmt == "splat" else write_gaussian_ply

        def frame(t):
            cloud = source.gaussians(t if source.dynamic else None)
            return len(cloud), lambda path: writer(path, cloud)

        if frames is None:
            if source.dynamic:
                check_time(source, time_, extrapolate)
            count, write = frame(time_)
            write_all([(output, write)])
            click.echo(f"{output}: {count} Gaussians at t = {time_:g}")
            return
        _check_sequence_space(output, frames, source.num_gaussians, source.sh_degree, fmt)
        lo, hi = source.time_range
        times = np.linspace(lo, hi, frames) if frames > 1 else np.array([lo])
        counts = []

        def items():
            for k, t in enumerate(times):
                count, write = frame(float(t))
                counts.append(count)
                yield f"frame_{k:04d}.{fmt}", write

        write_sequence(output, items())
        count = counts[-1]
    click.echo(f"{output}/: {frames} frames frame_0000.{fmt} .. frame_{frames - 1:04d}.{fmt} "
               f"at t = {lo:g} .. {hi:g}, {count} Gaussians each")


__all__ = ["render", "ply"]
