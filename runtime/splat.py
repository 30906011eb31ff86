"""The `.splat` format of antimatter15's WebGL viewer (github.com/antimatter15/splat), read by
most web 3DGS viewers (SuperSplat, Spark, mkkellogg's GaussianSplats3D, Babylon.js, ...).

No header; 32 bytes per Gaussian, little endian:

    offset  0  position   3 x float32   x, y, z (world)
    offset 12  scale      3 x float32   activated (exp of the log-scale)
    offset 24  colour     4 x uint8     rgb = (0.5 + C0 * f_dc) * 255, a = sigmoid(opacity) * 255
    offset 28  rotation   4 x uint8     (q / |q|) * 128 + 128 for q = (w, x, y, z)

Bytes are rounded to the nearest integer (half to even) and clamped to 0..255, as the viewer's
own PLY converter does by storing into a Uint8ClampedArray. Gaussians are sorted as that
converter sorts them: by decreasing exp(s0 + s1 + s2) * sigmoid(opacity) (volume times opacity),
so the most important come first and a viewer that streams the file shows them first.

Only the DC colour survives (no view-dependent SH), colour is clamped to [0, 1], and the
quaternion keeps about 7 bits per component; positions and scales are exact float32.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .gaussians import SH_C0, GaussianCloud
from .errors import InputProblem

ROW_BYTES = 32
SPLAT_DTYPE = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)),
                        ("rgba", "u1", (4,)), ("rot", "u1", (4,))])
assert SPLAT_DTYPE.itemsize == ROW_BYTES


class SplatError(InputProblem):
    """A .splat file cannot be written or read (the message names the file)."""


def _u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def splat_order(cloud: GaussianCloud) -> np.ndarray:
    """The viewer's order: decreasing volume x opacity (a stable sort: ties keep their order)."""
    importance = (np.prod(cloud.scales.astype(np.float64), axis=1)
                  * cloud.opacities.astype(np.float64))
    return np.argsort(-importance, kind="stable")


def splat_records(cloud: GaussianCloud, sort: bool = True) -> np.ndarray:
    """The Gaussians as a structured array of SPLAT_DTYPE rows (sorted unless `sort` is False)."""
    n = len(cloud)
    rec = np.zeros(n, SPLAT_DTYPE)
    rec["position"] = cloud.means
    rec["scale"] = cloud.scales
    rec["rgba"][:, :3] = _u8(cloud.base_rgb() * 255.0)
    rec["rgba"][:, 3] = _u8(cloud.opacities.astype(np.float64) * 255.0)
    q = cloud.quats.astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    rec["rot"] = _u8(q / np.where(norm > 0, norm, 1.0) * 128.0 + 128.0)
    return rec[splat_order(cloud)] if sort else rec


def _check(cloud: GaussianCloud, source: str) -> None:
    for name in ("means", "scales", "quats", "opacities", "sh"):
        arr = getattr(cloud, name)
        bad = int((~np.isfinite(arr)).sum())
        if bad:
            raise SplatError(f"{source}: cloud.{name} holds {bad} NaN or infinite values")
    if (cloud.scales < 0).any():
        raise SplatError(f"{source}: cloud.scales holds negative values")
    if (np.abs(cloud.quats).sum(axis=1) == 0).any():
        raise SplatError(f"{source}: cloud.quats holds zero-norm quaternions")


def splat_bytes(cloud: GaussianCloud) -> bytes:
    """The file's content for `cloud`."""
    _check(cloud, "splat")
    return splat_records(cloud).tobytes()


def write_splat(path, cloud: GaussianCloud) -> Path:
    """Write `cloud` as a .splat file, atomically (docs/design.md section 10). Returns the path."""
    from .images import atomic_path

    path = Path(path)
    _check(cloud, str(path))
    data = splat_records(cloud).tobytes()
    with atomic_path(path, SplatError) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return path


def read_splat(path) -> GaussianCloud:
    """Read a .splat file as a GaussianCloud (SH degree 0 from the stored colour; opacities and
    quaternions as stored, quaternions normalised)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SplatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise SplatError(f"{path}: is a folder, not a .splat file") from None
    if len(data) % ROW_BYTES:
        raise SplatError(f"{path}: {len(data)} bytes is not a whole number of {ROW_BYTES}-byte "
                         f"Gaussians (truncated, or not a .splat file)")
    rec = np.frombuffer(data, SPLAT_DTYPE)
    rgba = rec["rgba"].astype(np.float32) / 255.0
    sh = ((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]
    q = (rec["rot"].astype(np.float32) - 128.0) / 128.0
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if (norm == 0).any():
        raise SplatError(f"{path}: {int((norm == 0).sum())} Gaussians have a zero quaternion")
    return GaussianCloud(rec["position"].copy(), rec["scale"].copy(), q / norm, rgba[:, 3], sh)


__all__ = ["ROW_BYTES", "SPLAT_DTYPE", "SplatError", "read_splat", "splat_bytes", "splat_order",
           "splat_records", "write_splat"]
