"""`nehad synth`: write a synthetic dynamic scene (D-NeRF, HyperNeRF or DyNeRF layout)."""

from __future__ import annotations

import contextlib
import shlex
import shutil
import sys
import time
from pathlib import Path

import click

from .params import FiniteFloat
from .errors import InputError, user_errors


@click.command()
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scene", default="spheres", show_default=True,
              help="Which synthetic scene: spheres or boxes, or one scene of the stress suite "
                   "(occluder, crossing, scaling, split_merge, spinning_textures, thin_rod, "
                   "fast_few_frames; MuJoCo protocol, see --suite).")
@click.option("--suite", type=click.Choice(["stress"]), default=None,
              help="Write the whole stress suite into OUT/NAME, one scene per failure class of "
                   "dynamic scenes, in the MuJoCo protocol (12 fixed cameras, one per timestamp, "
                   "120 timestamps, label masks, fused.ply; --resolution defaults to 400 there, "
                   "--frames to 120).")
@click.option("--resolution", type=click.IntRange(min=4), default=None,
              help="Image width and height in pixels  [default: 64; 400 for stress scenes]")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Number of train frames (val and test get about 10% as many each); for "
                   "stress scenes the number of timestamps (14 of each 20 train)  [default: 50; "
                   "120 for stress scenes]")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Seed of the cameras and times.")
@click.option("--fixed-time", type=FiniteFloat(0.0, 1.0), default=None,
              help="Give every frame this time in [0, 1]: a static scene.")
@click.option("--gaussians", "num_gaussians", type=click.IntRange(min=0), default=5000,
              show_default=True,
              help="Number of Gaussians in gaussians.ply, a 3DGS PLY approximating the scene at "
                   "t = 0.5 (or --fixed-time); 0 writes none. D-NeRF format only.")
@click.option("--format", "fmt", type=click.Choice(["dnerf", "hypernerf", "dynerf"]),
              default="dnerf", show_default=True,
              help="Dataset layout: dnerf (transforms_*.json, RGBA PNGs), hypernerf (nerfies "
                   "camera/, rgb/1x, rgb/2x, dataset.json, ...) or dynerf (camXX.mp4 videos and "
                   "poses_bounds.npy; --frames is then the frames per video).")
@click.option("--cameras", type=click.IntRange(min=2), default=None,
              help="dynerf: number of cameras (cam00 is the test camera); --capture rig: number "
                   "of fixed cameras  [default: 4; 12 for --capture rig]")
@click.option("--capture", type=click.Choice(["rig", "orbit"]), default=None,
              help="Write what a user films instead of a dataset, for `nehad prepare`: "
                   "rig = OUT/videos/camNN.mp4 from fixed cameras, orbit = OUT/orbit.mp4 from a "
                   "camera walking 120 degrees around, both in front of a textured ground and "
                   "walls, with the true cameras in OUT/truth.json  [--resolution 400, --frames "
                   "60 per video]")
def synth(out, scene, suite, resolution, frames, seed, fixed_time, num_gaussians, fmt, cameras,
          capture):
    """Write a synthetic dynamic scene to the folder OUT (D-NeRF layout unless --format).

    D-NeRF: OUT gets train/, val/, test/ (RGBA PNGs, label masks in */masks/),
    transforms_{train,val,test}.json, class_mapping.json, points3d.ply (initial points) and
    gaussians.ply (a ready-made 3DGS PLY of the scene, to render). HyperNeRF and DyNeRF: the
    files of those releases, RGB over black (see README). Stress scenes (--suite stress, or a
    stress --scene): the MuJoCo layout with a random fused.ply (docs/usage.md).
    """
    from nehad.data.synth import SCENES, synthesize_scene
    from nehad.data.synth_stress import STRESS_SCENES

    if capture is not None:
        if scene not in SCENES:
            raise click.BadParameter(f"unknown scene {scene!r}; a capture draws one of "
                                     f"{', '.join(SCENES)}", param_hint="'--scene'")
        return _synth_capture(out, capture, scene, resolution or 400, frames or 60, cameras or 12)
    cameras = 4 if cameras is None else cameras
    if suite is not None or scene in STRESS_SCENES:
        if fmt != "dnerf" or fixed_time is not None:
            raise click.UsageError("stress scenes are written in the D-NeRF (MuJoCo) layout "
                                   "only, without --fixed-time")
        with user_errors():
            check_synth_memory(resolution or 400, frames or 120)
        return _synth_stress(out, STRESS_SCENES if suite is not None else (scene,),
                             suite is not None, resolution or 400, frames or 120, seed)
    resolution = 64 if resolution is None else resolution
    frames = 50 if frames is None else frames

    with user_errors():
        check_synth_memory(resolution, frames, cameras if fmt == "dynerf" else 1,
                           num_gaussians if fmt == "dnerf" else 0)
    if fmt != "dnerf":
        return _synth_other_format(out, fmt, scene, resolution, frames, seed, fixed_time, cameras)
    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}",
                                 param_hint="'--scene'")
    _check_out(out)
    held = max(1, int(round(0.1 * frames)))  # val/test frame count of synthesize_scene
    start = time.perf_counter()
    with user_errors(), _removed_on_failure(out):
        from tqdm import tqdm

        with tqdm(total=frames + 2 * held, desc="synth", unit="frame", delay=1.0, disable=None,
                  leave=False, file=sys.stderr) as bar:
            synthesize_scene(out, scene=scene, resolution=resolution, frames=frames, seed=seed,
                             fixed_time=fixed_time, progress=lambda: bar.update(1))
        t_ply = 0.5 if fixed_time is None else fixed_time
        if num_gaussians > 0:
            from nehad.data.synth_gaussians import scene_gaussians
            from nehad.runtime.ply import write_gaussian_ply

            cloud = scene_gaussians(scene, t_ply, num_gaussians)
            write_gaussian_ply(out / "gaussians.ply", cloud)
    elapsed = time.perf_counter() - start
    click.echo(f"wrote {out}/ (scene {scene!r}, seed {seed}, {elapsed:.1f} s):")
    click.echo(f"  train/ {frames} frames, val/ {held}, test/ {held}: {resolution}x{resolution} RGBA "
               f"PNGs, cameras in transforms_{{train,val,test}}.json")
    click.echo(f"  points3d.ply: initial points on the surfaces at t = {t_ply:g}")
    if num_gaussians > 0:
        click.echo(f"  gaussians.ply: {len(cloud)} Gaussians approximating the scene at t = {t_ply:g}")
        q = shlex.quote(str(out))
        click.echo(f"try: nehad render {q}/gaussians.ply --view {q}/transforms_test.json:0 "
                   f"-o render.png --background 1,1,1")


#: Peak memory of drawing one synthetic image, per pixel (measured: 826 MB at 1024x1024 against
#: 126 MB at 256x256, about 750 bytes a pixel, whatever the frame count; rounded up)
SYNTH_BYTES_PER_PIXEL = 800


def check_synth_memory(resolution: int, frames: int = 1, cameras: int = 1,
                       gaussians: int = 0) -> None:
    """Refuse sizes whose images, frame list or Gaussians cannot be held in the memory
    available, before anything is written (issue 26: --resolution 100000 asked numpy for
    671 GiB)."""
    from nehad.runtime.memory import (BYTES_PER_PLANNED_FRAME, check_cloud_memory,
                                      format_bytes, memory_limit)

    limit, where = memory_limit()
    for option, need, what in (
            (f"--resolution {resolution}", SYNTH_BYTES_PER_PIXEL * int(resolution) ** 2,
             f"drawing a {resolution}x{resolution} image"),
            (f"--frames {frames}" + (f" with --cameras {cameras}" if cameras > 1 else ""),
             BYTES_PER_PLANNED_FRAME * int(frames) * max(1, int(cameras)),
             f"the list of {int(frames) * max(1, int(cameras))} frames")):
        if limit is not None and need > limit:
            raise InputError(f"{option}: {what} needs about {format_bytes(need)} of memory, more "
                             f"than {where} ({format_bytes(limit)}); choose a smaller value")
    if gaussians:
        check_cloud_memory(gaussians, 0, f"--gaussians {gaussians}")


def _check_out(out: Path) -> None:
    """OUT must be a new or empty folder: writing a scene over another one would leave the old
    scene's images beside the new ones (a mixed dataset)."""
    if out.exists() and not out.is_dir():
        raise click.BadParameter(f"{out} exists and is not a folder", param_hint="'OUT'")
    if out.is_dir() and any(out.iterdir()):
        raise click.BadParameter(f"{out} is not empty; synth writes a scene into a new or empty "
                                 f"folder (remove it, or choose another)", param_hint="'OUT'")


@contextlib.contextmanager
def _removed_on_failure(out: Path):
    """OUT, when this command creates it, is removed again if the command fails or is
    interrupted: a failed synth leaves nothing behind."""
    created = not out.exists()
    try:
        yield
    except BaseException:
        if created and out.is_dir():
            shutil.rmtree(out, ignore_errors=True)
        raise


def _synth_stress(out, names, nested, resolution, frames, seed):
    from nehad.data.synth_stress import synthesize_stress_scene

    if frames < 20:
        raise click.BadParameter("stress scenes need at least 20 timestamps", param_hint="'--frames'")
    _check_out(out)
    start = time.perf_counter()
    with user_errors(), _removed_on_failure(out):
        from tqdm import tqdm

        with tqdm(total=frames * len(names), desc="synth", unit="frame", delay=1.0, disable=None,
                  leave=False, file=sys.stderr) as bar:
            for name in names:
                synthesize_stress_scene(out / name if nested else out, name, resolution=resolution,
                                        frames=frames, seed=seed, progress=lambda: bar.update(1))
    click.echo(f"wrote {out}/ ({', '.join(names)}; {frames} timestamps at {resolution}x{resolution}"
               f", {time.perf_counter() - start:.1f} s)")
    q = shlex.quote(str(out / names[0] if nested else out))
    click.echo(f"try: nehad train {q} -o run && nehad eval run   # scores every labelled object")


def _synth_capture(out, kind, scene, resolution, frames, cameras):
    from nehad.data.synth_capture import synthesize_capture

    if resolution < 16 or frames < 2:
        raise click.BadParameter("a capture needs --resolution >= 16 and --frames >= 2")
    _check_out(out)
    with user_errors():  # a rig draws frames x cameras images
        check_synth_memory(resolution, frames, cameras if kind == "rig" else 1)
    start = time.perf_counter()
    total = frames * (cameras if kind == "rig" else 1)
    with user_errors(), _removed_on_failure(out):
        from tqdm import tqdm

        with tqdm(total=total, desc="synth", unit="frame", delay=1.0, disable=None,
                  leave=False, file=sys.stderr) as bar:
            synthesize_capture(out, kind, scene, resolution, frames, cameras,
                               progress=lambda: bar.update(1))
    what = (f"videos/cam00.mp4 .. cam{cameras - 1:02d}.mp4 ({frames} frames each)"
            if kind == "rig" else f"orbit.mp4 ({frames} frames)")
    click.echo(f"wrote {out}/ ({kind} capture of {scene!r}, {resolution}x{resolution}, "
               f"{time.perf_counter() - start:.1f} s): {what}, truth.json (the true cameras)")
    src = shlex.quote(str(out / "videos" if kind == "rig" else out / "orbit.mp4"))
    click.echo(f"try: nehad prepare {src} -o {shlex.quote(str(out))}_scene")


def _synth_other_format(out, fmt, scene, resolution, frames, seed, fixed_time, cameras):
    from nehad.data.synth import SCENES
    from nehad.data.synth_formats import planned_images, synthesize_format

    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}",
                                 param_hint="'--scene'")
    _check_out(out)
    start = time.perf_counter()
    with user_errors(), _removed_on_failure(out):
        from tqdm import tqdm

        with tqdm(total=planned_images(fmt, frames, cameras), desc="synth", unit="frame",
                  delay=1.0, disable=None, leave=False, file=sys.stderr) as bar:
            synthesize_format(out, fmt, scene=scene, resolution=resolution, frames=frames,
                              seed=seed, fixed_time=fixed_time, cameras=cameras,
                              progress=lambda: bar.update(1))
    what = (f"{cameras} cameras x {frames} frames (cam00.mp4 .. is the test camera), "
            f"poses_bounds.npy, points3D_downsample2.ply" if fmt == "dynerf" else
            f"{planned_images(fmt, frames)} images in rgb/1x and rgb/2x, camera/*.json, "
            f"dataset.json, metadata.json, scene.json, points.npy")
    click.echo(f"wrote {out}/ ({fmt} layout, scene {scene!r}, seed {seed}, "
               f"{time.perf_counter() - start:.1f} s): {what}")
    click.echo(f"try: nehad train {shlex.quote(str(out))} -o run --preset test")


__all__ = ["synth"]
