"""`nehad prepare`: pose a user's own capture with COLMAP and write a scene `nehad train` reads."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from .errors import InputError, user_errors
from .params import FiniteFloat

_MODELS = ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]


def _bars():
    """A tqdm bar per phase, on stderr, for nehad.data.prepare's `progress`."""
    from tqdm import tqdm

    def make(phase: str, total: int):
        return tqdm(total=total, desc=phase, unit="pair" if phase == "matching" else "image",
                    leave=False, disable=None, file=sys.stderr, delay=0.5)

    return make


@click.command()
@click.argument("input_path", metavar="INPUT",
                type=click.Path(exists=False, path_type=Path))
@click.option("-o", "--output", "scene", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Scene folder to write (D-NeRF layout); must not exist or be empty.")
@click.option("--kind", type=click.Choice(["auto", "rig", "monocular"]), default="auto",
              show_default=True,
              help="rig: static synchronised cameras (a folder of videos, or of image folders); "
                   "monocular: one moving camera (a video, or a folder of images). auto: from "
                   "what INPUT holds.")
@click.option("--fps", type=FiniteFloat(min=0.0, min_open=True), default=None,
              help="Monocular video: frames kept per second  [default: every frame]")
@click.option("--instants", type=click.IntRange(min=1), default=3, show_default=True,
              help="Rig: synchronised instants (spread over the videos) used to pose the "
                   "cameras; each camera's pose is the mean over them.")
@click.option("--test-cameras", default="",
              help="Rig: comma-separated camera names held out for testing  [default: the "
                   "middle camera]")
@click.option("--test-every", type=click.IntRange(min=2), default=8, show_default=True,
              help="Monocular: every this-many-th frame is a test frame.")
@click.option("--camera-model", type=click.Choice(_MODELS), default="SIMPLE_RADIAL",
              show_default=True,
              help="COLMAP camera model; frames are undistorted to a pinhole camera when it "
                   "has distortion.")
@click.option("--per-camera-intrinsics", is_flag=True,
              help="Rig: estimate intrinsics for each camera (different phones) instead of one "
                   "shared camera.")
@click.option("--min-registered", type=click.IntRange(min=2), default=None,
              help="Go on when at least this many cameras (rig) or frames (monocular) register; "
                   "the others are dropped and listed in prepare.json  [default: all]")
@click.option("--trim", is_flag=True,
              help="Rig: cut every camera to the shortest video instead of refusing videos of "
                   "different lengths.")
@click.option("--resume", is_flag=True,
              help="Reuse the decoded frames and the COLMAP database of an earlier run of the "
                   "same command (kept in a hidden folder beside SCENE until it succeeds).")
@click.option("--keep-work", is_flag=True,
              help="Keep that work folder after success too (decoded frames, database.db, "
                   "sparse/ model).")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="COLMAP threads  [default: the idle cores]")
def prepare(input_path, scene, kind, fps, instants, test_cameras, test_every, camera_model,
            per_camera_intrinsics, min_registered, trim, resume, keep_work, threads):
    """Pose a capture of a moving scene and write it as a scene folder `nehad train` reads.

    INPUT is a folder of videos (one per static camera of a synchronised rig), one video from
    a moving camera, a folder of image folders (a rig), or a folder of images (one moving
    camera). Frames are decoded with PyAV, the cameras posed with COLMAP (pycolmap, on the
    CPU), the scene centred, turned z-up and scaled, and written in the D-NeRF layout:
    train/ and test/ frames, transforms_*.json (each frame's camera and time), points3d.ply
    (the sparse points, the initial cloud) and prepare.json (what was done). How to film:
    docs/capture.md.
    """
    import os

    try:
        import pycolmap  # noqa: F401
    except ImportError:
        raise click.ClickException("nehad prepare needs pycolmap: pip install -e '.[prepare]'") \
            from None
    from nehad.data.prepare import PrepareOptions, prepare_capture

    cams = tuple(c.strip() for c in test_cameras.split(",") if c.strip())
    if threads is None:
        threads = max(1, int(os.environ.get("OMP_NUM_THREADS", os.cpu_count() or 1)))
    options = PrepareOptions(kind=kind, fps=fps, instants=instants, test_cameras=cams,
                             test_every=test_every, camera_model=camera_model,
                             shared_intrinsics=not per_camera_intrinsics,
                             min_registered=min_registered, trim=trim, threads=threads)
    start = time.perf_counter()
    with user_errors():
        if fps is not None and kind == "rig":
            raise InputError("--fps: a rig keeps every frame of its videos (--fps is for a "
                             "monocular video)")
        record = prepare_capture(input_path, scene, options, resume=resume, keep_work=keep_work,
                                 progress=_bars())
    _report(record, scene, time.perf_counter() - start)


def _report(record: dict, scene: Path, elapsed: float) -> None:
    split = record["splits"]
    click.echo(f"wrote {scene}/ ({record['kind']}, {elapsed:.1f} s): {split['train']} train and "
               f"{split['test']} test frames, transforms_*.json, points3d.ply "
               f"({record['sparse_points']} sparse points), prepare.json")
    click.echo(f"  registered {record['registered_images']} of {record['sfm_images']} images, "
               f"mean reprojection error {record['reprojection_error_px']:.2f} px")
    if record.get("dropped"):
        click.echo(f"  dropped: {', '.join(str(next(iter(d.values()))) for d in record['dropped'])}")
    if record.get("test_cameras"):
        click.echo(f"  test cameras: {', '.join(record['test_cameras'])}")
    secs = ", ".join(f"{k} {v:.1f}" for k, v in record["seconds"].items())
    click.echo(f"  seconds: {secs}")
    click.echo(f"try: nehad train {scene} --preset quick")
