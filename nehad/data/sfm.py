"""Structure from motion for `nehad prepare`, through pycolmap (COLMAP as a Python wheel, CPU).

Three steps on a folder of still images, each resumable from COLMAP's database:

1. SIFT features (:func:`extract`), one shared camera for every image (``shared=True``: a rig of
   the same phones, or one moving phone) or one per image;
2. matches verified by two-view geometry (:func:`match`) on the pairs of
   :func:`image_pairs`: every pair for small sets, a video's neighbours for a long one, never
   two images of one static camera;
3. incremental mapping (:func:`reconstruct`): the largest model found.

Then :func:`poses` reads each registered image's camera (OpenCV axes: x right, y down, z forward)
and :func:`normalisation` finds the similarity that puts the scene where the readers expect it:
centred on the point the cameras look at, the direction orthogonal to the cameras' x axes
(cameras held level) as +z (the synthetic and Blender scenes are z-up), and the cameras at a mean distance of 4 from the centre (the
D-NeRF synthetic scenes' radius; docs/capture.md).

COLMAP's own log (glog) is silenced: what went wrong reaches the user as one PrepareError
(:mod:`nehad.data.prepare`). Numpy and pycolmap only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nehad.runtime.paths import nearest_point_to_axes

__all__ = ["CameraPose", "extract", "feature_counts", "image_pairs", "match", "reconstruct", "poses",
           "pair_geometries", "normalisation", "similarity", "TARGET_RADIUS"]

#: Mean camera distance from the scene centre after normalisation (D-NeRF's synthetic radius).
TARGET_RADIUS = 4.0
#: Above this many images, each image is matched with its `SEQUENTIAL_OVERLAP` successors and a
#: few far ones (a monocular video), not with every other image.
EXHAUSTIVE_MAX = 80
SEQUENTIAL_OVERLAP = 12


def _pycolmap():
    import pycolmap

    try:  # glog: nothing below FATAL on the terminal (the CLI reports what went wrong)
        pycolmap.logging.minloglevel = 3
        pycolmap.logging.stderrthreshold = 3
    except Exception:  # older bindings without the logging module: leave COLMAP's defaults
        pass
    return pycolmap


@dataclass(frozen=True)
class CameraPose:
    """A registered image: camera-to-world rotation (OpenCV axes) and centre, and its camera
    (COLMAP model name and parameters, e.g. SIMPLE_RADIAL: f, cx, cy, k)."""

    rotation: np.ndarray  # (3, 3), columns: the camera's x, y, z axes in world coordinates
    centre: np.ndarray  # (3,)
    model: str
    params: tuple[float, ...]
    width: int
    height: int


def extract(db: Path, image_dir: Path, names: list[str], camera_model: str, shared: bool,
            threads: int, progress=None, chunk: int = 8, max_features: int = 2048) -> None:
    """SIFT features of `names` (files in `image_dir`) into the database `db`, at most
    `max_features` per image (COLMAP's default 8192 makes matching 4x slower and posed the
    test captures no better); images already there are skipped (a resumed run).
    `progress(n)` after every `chunk` images."""
    pycolmap = _pycolmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = int(threads)
    options.sift.max_num_features = int(max_features)
    mode = pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE
    done, camera = _extracted(pycolmap, db)
    todo = [n for n in names if n not in done]
    if progress is not None and len(names) > len(todo):
        progress(len(names) - len(todo))
    for k in range(0, len(todo), chunk):
        part = todo[k:k + chunk]
        if shared and camera is not None:  # one camera across the calls, not one per call
            reader.existing_camera_id = camera
        pycolmap.extract_features(str(db), str(image_dir), image_names=part, camera_mode=mode,
                                  reader_options=reader, extraction_options=options,
                                  device=pycolmap.Device.cpu)
        if camera is None:
            camera = _extracted(pycolmap, db)[1]
        if progress is not None:
            progress(len(part))


def _extracted(pycolmap, db: Path) -> tuple[set[str], int | None]:
    """(names of the images with features in `db`, the camera id of the first image)."""
    if not db.exists():
        return set(), None
    database = pycolmap.Database.open(str(db))
    try:
        images = database.read_all_images()
        done = {im.name for im in images if database.exists_keypoints(im.image_id)}
        return done, (int(images[0].camera_id) if images else None)
    finally:
        database.close()


def feature_counts(db: Path) -> dict[str, int]:
    """Keypoints per image name in the database."""
    pycolmap = _pycolmap()
    database = pycolmap.Database.open(str(db))
    try:
        return {im.name: int(database.num_keypoints_for_image(im.image_id))
                for im in database.read_all_images()}
    finally:
        database.close()


def image_pairs(names: list[str], camera_of: dict[str, str] | None = None) -> list[tuple]:
    """The image pairs to match: every pair when there are at most EXHAUSTIVE_MAX images, else
    each image with its SEQUENTIAL_OVERLAP successors and then every 2^k-th one (a video's
    neighbours and a few far frames to close loops). With `camera_of` (a rig: image -> camera)
    two images of the same camera are never paired: a static camera sees the same picture at
    every instant, a pair without baseline that would only mislead the mapper."""
    names = sorted(names)
    n = len(names)
    if n <= EXHAUSTIVE_MAX:
        pairs = [(names[i], names[j]) for i in range(n) for j in range(i + 1, n)]
    else:
        steps = set(range(1, SEQUENTIAL_OVERLAP + 1))
        steps |= {2 ** k for k in range(4, 12) if 2 ** k < n}
        pairs = [(names[i], names[i + d]) for i in range(n) for d in sorted(steps) if i + d < n]
    if camera_of is not None:
        pairs = [(a, b) for a, b in pairs if camera_of[a] != camera_of[b]]
    return pairs


def match(db: Path, pairs: list[tuple], threads: int, progress=None, chunk: int = 48) -> None:
    """Match and verify `pairs` (image names) in `db`, `chunk` pairs at a time
    (`progress(n)` after each); pairs matched by an earlier run are skipped by COLMAP."""
    pycolmap = _pycolmap()
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = int(threads)
    pairing = pycolmap.ImportedPairingOptions()
    listing = db.parent / "pairs.txt"
    for k in range(0, len(pairs), chunk):
        part = pairs[k:k + chunk]
        listing.write_text("".join(f"{a} {b}\n" for a, b in part))
        pairing.match_list_path = str(listing)
        pycolmap.match_image_pairs(str(db), matching_options=options, pairing_options=pairing,
                                   device=pycolmap.Device.cpu)
        if progress is not None:
            progress(len(part))


def pair_geometries(db: Path) -> dict[str, int]:
    """How many verified image pairs have each two-view configuration (CALIBRATED,
    PANORAMIC, PLANAR_OR_PANORAMIC, ...): pure rotations between cameras show as PANORAMIC."""
    pycolmap = _pycolmap()
    database = pycolmap.Database.open(str(db))
    try:
        _, geometries = database.read_two_view_geometries()
    finally:
        database.close()
    counts: dict[str, int] = {}
    for g in geometries:
        if len(g.inlier_matches) == 0:
            continue
        try:
            name = pycolmap.TwoViewGeometryConfiguration(int(g.config)).name
        except (TypeError, ValueError):
            name = str(g.config).rsplit(".", 1)[-1]
        counts[name] = counts.get(name, 0) + 1
    return counts


def reconstruct(db: Path, image_dir: Path, out_dir: Path, threads: int, seed: int = 0,
                progress=None):
    """Incremental mapping; the reconstruction with the most registered images, or None.
    `progress()` is called as each image is registered."""
    pycolmap = _pycolmap()
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = int(threads)
    options.random_seed = int(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(str(db), str(image_dir), str(out_dir), options,
                                          next_image_callback=progress)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def poses(reconstruction) -> dict[str, CameraPose]:
    """Every registered image's :class:`CameraPose`, by image name."""
    out = {}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        m = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)  # world -> camera
        rot = m[:3, :3].T
        cam = reconstruction.cameras[image.camera_id]
        out[image.name] = CameraPose(rot, -rot @ m[:3, 3], cam.model.name,
                                     tuple(float(v) for v in cam.params), int(cam.width),
                                     int(cam.height))
    return out


def sparse_points(reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 positions and (N, 3) uint8 colours of the reconstruction's points."""
    pts = [(p.xyz, p.color) for p in reconstruction.points3D.values()]
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    return (np.array([p for p, _ in pts], dtype=np.float64),
            np.array([c for _, c in pts], dtype=np.uint8))


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """A rotation taking the unit vector `up` to +z (Rodrigues about their cross product)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)
    s, c = np.linalg.norm(v), float(up @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = v / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = math.atan2(s, c)
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _up_direction(rotations: np.ndarray) -> np.ndarray:
    """World up from cameras held level (no roll): the direction orthogonal to every camera's
    x axis (the smallest singular vector of the stacked x axes), on the side of the cameras'
    mean up (-y in OpenCV axes). When the x axes do not span a plane (every camera turned the
    same way), the mean up with its component along the x axes removed."""
    rights = rotations[:, :, 0]
    mean_up = -rotations[:, :, 1].mean(axis=0)
    _, sig, vt = np.linalg.svd(rights)
    if len(rights) >= 2 and sig[1] > 0.1 * sig[0]:
        up = vt[2]
    else:
        r = rights.mean(axis=0)
        r = r / max(np.linalg.norm(r), 1e-12)
        up = mean_up - (mean_up @ r) * r
    up = up if up @ mean_up >= 0 else -up
    return up / max(np.linalg.norm(up), 1e-12)


def normalisation(centres: np.ndarray, rotations: np.ndarray,
                  points: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation, centre) of the similarity x -> scale * rotation @ (x - centre) that
    centres the scene on the point the cameras look at (the median of the sparse points when
    their axes are parallel), turns the world's up (:func:`_up_direction`) to +z and puts the
    cameras at a mean distance of TARGET_RADIUS."""
    forwards = rotations[:, :, 2]
    centre = nearest_point_to_axes(centres, forwards)
    if centre is None or not np.all(np.isfinite(centre)):
        centre = np.median(points, axis=0) if len(points) else centres.mean(axis=0)
    rot = _rotation_to_z(_up_direction(rotations))
    dist = float(np.linalg.norm(centres - centre, axis=1).mean())
    scale = TARGET_RADIUS / max(dist, 1e-12)
    return scale, rot, centre


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |s R src_i + t - dst_i|^2 over points (N, 3) (Umeyama 1991):
    how a reconstruction, known up to a similarity, is compared with true camera centres."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / max((a ** 2).sum(axis=1).mean(), 1e-300))
    return scale, rot, mu_d - scale * rot @ mu_s
