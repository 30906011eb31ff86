"""`nehad prepare`: a user's own capture (videos or images, no poses) to a scene `nehad train`
reads (issue 30; docs/capture.md has the why and the limits).

Phases, each with its own progress bar and its time in ``prepare.json``:

1. **decode** (:mod:`nehad.data.capture_inputs`): every kept frame to a PNG in the work folder;
2. **features**, 3. **matching**, 4. **mapping** (:mod:`nehad.data.sfm`, pycolmap): a rig is
   posed from a few synchronised instants (`instants`, spread over the video: the cameras do
   not move, so each camera's pose is the mean over the instants it registered at); a monocular
   capture from every kept frame;
5. **write**: the scene folder in the **D-NeRF layout**, chosen because it is the one layout
   nehad reads in which every image has its own camera and time (a rig and a moving camera
   alike) and the layout of the MuJoCo scenes the recipe is tuned on: ``train/``, ``test/``
   (PNG frames, undistorted when the camera model has distortion), ``transforms_{train,val,
   test}.json`` (pinhole ``fl_x, fl_y, cx, cy``, each frame's ``time`` and camera-to-world
   matrix in OpenGL axes; val names the test frames), ``points3d.ply`` (the sparse points: the
   initial cloud) and ``prepare.json`` (what was done).

Splits: a rig holds out whole cameras (`test_cameras`, by default the middle one of the list);
a monocular capture every `test_every`-th frame. The scene is normalised by
:func:`nehad.data.sfm.normalisation` (centred, z up, cameras at distance ~4).

Bad input ends in one :class:`PrepareError` and leaves nothing in SCENE: the scene is written
to a temporary folder beside it and renamed at the end. The work folder (decoded frames, the
COLMAP database) is kept after a failure so that ``resume`` reuses them, and removed after a
success unless `keep_work`.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nehad.data.capture_inputs import PrepareError, Source, decode, find_sources
from nehad.runtime.images import atomic_write_bytes

__all__ = ["PrepareOptions", "PrepareError", "prepare_capture", "work_folder"]


@dataclass(frozen=True)
class PrepareOptions:
    """Every knob of `nehad prepare`, with its default."""

    kind: str = "auto"  # "rig", "monocular" or "auto" (from what INPUT holds)
    fps: float | None = None  # monocular video: frames kept per second (None: every frame)
    instants: int = 3  # rig: synchronised instants posed by structure from motion
    test_cameras: tuple[str, ...] = ()  # rig: cameras held out for testing (default: middle one)
    test_every: int = 8  # monocular: every this-many-th frame is a test frame
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP camera model
    shared_intrinsics: bool = True  # one camera model for every image (same phones)
    min_registered: int | None = None  # cameras (rig) or frames (monocular) that must register
    min_features: int = 200  # an image with fewer SIFT features than this is "featureless"
    trim: bool = False  # rig: cut every camera to the shortest instead of refusing
    min_parallax: float = 0.02  # camera baseline / distance to the scene under which to refuse
    threads: int = 2
    seed: int = 0


@dataclass
class _Run:
    """What the phases hand each other (and prepare.json records)."""

    kind: str
    sources: list[Source]
    frames: int
    work: Path
    options: PrepareOptions
    files: dict[str, list[Path]] = field(default_factory=dict)  # per camera: decoded frames
    times: dict[str, list[float]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    record: dict = field(default_factory=dict)


def work_folder(scene: Path) -> Path:
    """Where a prepare of `scene` keeps its decoded frames and COLMAP database."""
    scene = Path(scene)
    return scene.parent / f".{scene.name}.prepare"


@contextlib.contextmanager
def _phase(run: _Run, name: str, progress, total: int):
    """A progress bar of `total` steps for phase `name` (a no-op without `progress`); yields
    its `tick(n=1)` and records the phase's seconds."""
    bar = progress(name, total) if progress is not None else None
    start = time.perf_counter()
    try:
        yield (lambda n=1: bar.update(n)) if bar is not None else (lambda n=1: None)
    finally:
        if bar is not None:
            bar.close()
        run.seconds[name] = round(time.perf_counter() - start, 2)


def _decode_all(run: _Run, progress) -> None:
    fps = run.options.fps if run.kind == "monocular" else None
    with _phase(run, "decode", progress, run.frames * len(run.sources)) as tick:
        for s in run.sources:
            files, times = decode(s, run.work / "frames" / s.name, run.frames, fps, tick)
            run.files[s.name], run.times[s.name] = files, times


def _sfm_images(run: _Run) -> dict[str, tuple[str, int]]:
    """SfM image name -> (camera, frame index); the images linked into work/sfm/images."""
    folder = run.work / "sfm" / "images"
    folder.mkdir(parents=True, exist_ok=True)
    chosen = {}
    for name, files in run.files.items():
        n = len(files)
        if run.kind == "rig":
            k = max(1, min(run.options.instants, n))
            picks = sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})
        else:
            picks = list(range(n))
        for i in picks:
            image = f"{name}_{i:06d}.png"
            link = folder / image
            if not link.exists():
                os.symlink(os.path.relpath(files[i], folder), link)
            chosen[image] = (name, i)
    return chosen


def _check_features(counts: dict[str, int], names, minimum: int) -> None:
    poor = sorted((counts.get(n, 0), n) for n in names if counts.get(n, 0) < minimum)
    if len(poor) > len(names) // 2:
        shown = ", ".join(f"{n} ({c})" for c, n in poor[:4])
        raise PrepareError(f"too few features: {len(poor)} of {len(names)} images hold fewer "
                           f"than {minimum} SIFT features (e.g. {shown}); the scene needs "
                           f"texture, focus and light (docs/capture.md)")


def _structure_from_motion(run: _Run, progress):
    from nehad.data import sfm

    chosen = _sfm_images(run)
    names = sorted(chosen)
    db, images = run.work / "sfm" / "database.db", run.work / "sfm" / "images"
    opts = run.options
    with _phase(run, "features", progress, len(names)) as tick:
        sfm.extract(db, images, names, opts.camera_model, opts.shared_intrinsics, opts.threads, tick)
    counts = sfm.feature_counts(db)
    _check_features(counts, names, opts.min_features)
    pairs = sfm.image_pairs(names, {k: v[0] for k, v in chosen.items()}
                            if run.kind == "rig" else None)
    with _phase(run, "matching", progress, len(pairs)) as tick:
        sfm.match(db, pairs, opts.threads, tick)
    run.record["matched_pairs"] = len(pairs)
    _check_pairs(sfm.pair_geometries(db))
    with _phase(run, "mapping", progress, len(names)) as tick:
        shutil.rmtree(run.work / "sfm" / "sparse", ignore_errors=True)
        model = sfm.reconstruct(db, images, run.work / "sfm" / "sparse", opts.threads, opts.seed,
                                lambda: tick())
    if model is None or model.num_reg_images() < 2:
        _no_model(db, len(names))
    run.record.update(sfm_images=len(names), features_median=int(np.median(list(counts.values()))),
                      registered_images=int(model.num_reg_images()),
                      reprojection_error_px=round(float(model.compute_mean_reprojection_error()), 4),
                      sparse_points=int(model.num_points3D()))
    return model, chosen


#: Under this fraction of matched image pairs with an epipolar geometry (the others explained
#: by a homography: a rotation about the camera centre, or one plane), the capture has no
#: parallax. Good captures of the test scenes: 35-47% (their ground plane makes the rest).
MIN_EPIPOLAR_PAIRS = 0.05


def _check_pairs(configs: dict[str, int]) -> None:
    pairs = sum(configs.values())
    epipolar = configs.get("CALIBRATED", 0) + configs.get("UNCALIBRATED", 0)
    if pairs and epipolar < MIN_EPIPOLAR_PAIRS * pairs:
        raise PrepareError(f"no parallax: {pairs - epipolar} of {pairs} matched image pairs "
                           f"differ by a rotation about one point (or see one plane) and "
                           f"{epipolar} by a camera move; film from several positions "
                           f"(docs/capture.md)")


def _no_model(db: Path, n_images: int):
    from nehad.data import sfm

    pairs = sum(sfm.pair_geometries(db).values())
    raise PrepareError(f"structure from motion could not pose the capture: {pairs} image pairs "
                       f"of {n_images} images matched; film with more overlap between cameras "
                       f"and more texture (docs/capture.md)")


def prepare_capture(input_path, scene, options: PrepareOptions = PrepareOptions(),
                    resume: bool = False, keep_work: bool = False, progress=None) -> dict:
    """Prepare INPUT `input_path` into the scene folder `scene` (module doc); returns the
    record written to prepare.json. `progress(phase, total)` returns a bar with `update(n)` and
    `close()`."""
    from nehad.data.prepare_write import camera_poses_of, write_scene

    scene = Path(scene)
    if scene.exists() and (not scene.is_dir() or any(scene.iterdir())):
        raise PrepareError(f"{scene}: exists and is not an empty folder; choose another -o")
    kind, sources, frames = find_sources(input_path, options.kind, options.trim)
    _check_test_cameras(kind, sources, options)
    scene.parent.mkdir(parents=True, exist_ok=True)
    work = work_folder(scene)
    if work.exists() and not resume:
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    run = _Run(kind, sources, frames, work, options)
    run.record.update(input=str(Path(input_path).resolve()), kind=kind, cameras=len(sources),
                      frames_per_camera=frames, options=asdict(options))
    _decode_all(run, progress)
    model, chosen = _structure_from_motion(run, progress)
    from nehad.data.sfm import sparse_points

    points = sparse_points(model)[0]
    cams = camera_poses_of(run, model, chosen,
                           lambda found: _check_parallax(found, points, options.min_parallax))
    staging = Path(tempfile.mkdtemp(prefix=f".{scene.name}.", suffix=".tmp", dir=scene.parent))
    try:
        with _phase(run, "write", progress, sum(len(f) for f in run.files.values())) as tick:
            write_scene(run, cams, model, staging, tick)
        run.record["seconds"] = dict(run.seconds)
        atomic_write_bytes(staging / "prepare.json",
                           (json.dumps(run.record, indent=2) + "\n").encode("utf-8"))
        if scene.exists():
            scene.rmdir()
        os.rename(staging, scene)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    if not keep_work:
        shutil.rmtree(work, ignore_errors=True)
    return run.record


def _check_test_cameras(kind: str, sources: list[Source], options: PrepareOptions) -> None:
    names = {s.name for s in sources}
    if options.test_cameras and kind != "rig":
        raise PrepareError("test cameras: a monocular capture has one camera; its test frames "
                           "are every --test-every-th frame")
    unknown = [c for c in options.test_cameras if c not in names]
    if unknown:
        raise PrepareError(f"test cameras: {', '.join(unknown)} not among the capture's cameras "
                           f"({', '.join(sorted(names))})")
    if kind == "rig" and len(options.test_cameras) >= len(sources):
        raise PrepareError("test cameras: every camera held out leaves none to train on")


def _check_parallax(cams: dict, points: np.ndarray, minimum: float) -> None:
    """PrepareError when the posed cameras stand (nearly) at one point: the largest distance
    between two of them under `minimum` times their median distance to the scene (the median
    sparse point)."""
    centres = np.array([c.centre for c in cams.values()])
    if len(centres) < 2 or not len(points):
        return
    spread = float(max(np.linalg.norm(a - b) for a in centres for b in centres))
    depth = float(np.median(np.linalg.norm(centres - np.median(points, axis=0), axis=1)))
    if not math.isfinite(spread) or spread < minimum * depth:
        raise PrepareError(f"no parallax: the {len(centres)} posed cameras stand within "
                           f"{spread / max(depth, 1e-12):.2%} of their distance to the scene of "
                           f"each other; film from several positions (docs/capture.md)")
