"""Helpers shared by the HyperNeRF and DyNeRF readers and their synthetic writers (numpy only).

Conventions are those of docs/design.md section 3: cameras are :class:`~nehad.runtime.cameras.Camera`
objects (OpenCV axes, pixel (i, j) centred at (i + 0.5, j + 0.5)); images are float32 (H, W, 3) in
[0, 1]; every problem with a file is a :class:`~nehad.data.dnerf.DatasetError` naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nehad.data.dnerf import (DatasetError, _area_downscale, _number, _read_json,
                               _read_ply_points)
from nehad.runtime.images import atomic_write_bytes, read_image

__all__ = ["read_json", "read_rgb", "area_downscale", "check_rotation", "find_point_cloud",
           "distort_normalized", "undistort_normalized", "undistortion_maps", "remap",
           "atomic_write_bytes", "atomic_write_json", "check_background", "check_stride"]

#: |R^T R - I| (max abs) and |det R - 1| allowed in a rotation read from a dataset file.
ROTATION_TOLERANCE = 1e-4

area_downscale = _area_downscale
read_json = _read_json
number = _number


def vector(value, n: int, path: Path, field: str) -> np.ndarray:
    """`n` finite numbers (a list) as float64."""
    if (not isinstance(value, (list, tuple)) or len(value) != n
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)):
        raise DatasetError(f"{path}: field '{field}': expected a list of {n} numbers, got {value!r}")
    out = np.asarray(value, dtype=np.float64)
    if not np.isfinite(out).all():
        raise DatasetError(f"{path}: field '{field}': holds NaN or infinite values")
    return out


def check_rotation(r: np.ndarray, path, field: str) -> None:
    """A proper rotation (orthonormal, det +1) to ROTATION_TOLERANCE, else a DatasetError."""
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise DatasetError(f"{path}: {field}: expected a finite 3x3 rotation")
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if err > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise DatasetError(f"{path}: {field}: not a rotation (|R^T R - I| = {err:.2g}, "
                           f"det = {det:.6g})")


def read_rgb(path: Path, background: np.ndarray, named_by: str = ""):
    """(rgb (H, W, 3) float32, alpha (H, W) or None) of an image file; RGBA is composited over
    `background` as the D-NeRF reader does (read_image hands colour over premultiplied)."""
    try:
        pixels = read_image(path)
    except Exception as exc:  # ImageError and OpenImageIO failures
        by = f" ({named_by})" if named_by else ""
        raise DatasetError(f"{path}: cannot read image{by}: {exc}") from None
    c = pixels.shape[2]
    if c in (1, 2):
        rgb, alpha = np.repeat(pixels[:, :, :1], 3, axis=2), (pixels[:, :, 1] if c == 2 else None)
    elif c in (3, 4):
        rgb, alpha = pixels[:, :, :3], (pixels[:, :, 3] if c == 4 else None)
    else:
        raise DatasetError(f"{path}: expected 1 to 4 channels, got {c}")
    if alpha is not None:
        rgb = rgb + np.asarray(background, np.float32) * (1.0 - alpha[:, :, None])
    return np.ascontiguousarray(rgb, dtype=np.float32), alpha


def find_point_cloud(root: Path, names) -> Path | None:
    """The first of `names` that is a file in `root` (exact case), or None."""
    present = {p.name for p in root.iterdir()} if root.is_dir() else set()
    for name in names:
        if name in present and (root / name).is_file():
            return root / name
    return None


def read_points(path: Path):
    """(points (M, 3) float32, colours (M, 3) float32 in [0, 1] or None) of a PLY or .npy file."""
    if path.suffix.lower() == ".npy":
        try:
            pts = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise DatasetError(f"{path}: cannot read points ({exc})") from None
        if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0 or pts.dtype.kind not in "fiu":
            raise DatasetError(f"{path}: expected an (N, 3) array of numbers, got shape "
                               f"{pts.shape} {pts.dtype}")
        pts = np.asarray(pts[:, :3], np.float64)
        if not np.isfinite(pts).all():
            raise DatasetError(f"{path}: holds NaN or infinite values")
        return pts, None
    pts, cols = _read_ply_points(path)
    return pts.astype(np.float64), cols


def check_background(background) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.size != 3 or not np.isfinite(bg).all():
        raise ValueError(f"background: expected three finite numbers, got {background!r}")
    return bg


def check_stride(frame_stride) -> int:
    if isinstance(frame_stride, bool) or int(frame_stride) != frame_stride or int(frame_stride) < 1:
        raise ValueError(f"frame_stride: expected an integer >= 1, got {frame_stride!r}")
    return int(frame_stride)


def check_downscale(downscale) -> int:
    if isinstance(downscale, bool) or int(downscale) != downscale or int(downscale) < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale!r}")
    return int(downscale)


# --------------------------------------------------------------------------------------------
# lens distortion: the radial (k1, k2, k3) + tangential (p1, p2) model of nerfies / HyperNeRF
# `camera.py`, which is also OpenCV's (k1, k2, p1, p2, k3) model, plus nerfies' skew term.


def distort_normalized(x, y, k, p):
    """Distorted normalised coordinates of the undistorted ones (x, y); k = (k1, k2, k3),
    p = (p1, p2)."""
    r2 = x * x + y * y
    d = 1.0 + r2 * (k[0] + r2 * (k[1] + k[2] * r2))
    xd = x * d + 2.0 * p[0] * x * y + p[1] * (r2 + 2.0 * x * x)
    yd = y * d + 2.0 * p[1] * x * y + p[0] * (r2 + 2.0 * y * y)
    return xd, yd


def undistort_normalized(xd, yd, k, p, iterations: int = 20):
    """Inverse of :func:`distort_normalized` by Newton's method (as nerfies does), from (xd, yd)."""
    x, y = np.array(xd, np.float64), np.array(yd, np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        d = 1.0 + r2 * (k[0] + r2 * (k[1] + k[2] * r2))
        fx = d * x + 2 * p[0] * x * y + p[1] * (r2 + 2 * x * x) - xd
        fy = d * y + 2 * p[1] * x * y + p[0] * (r2 + 2 * y * y) - yd
        d_r = k[0] + r2 * (2.0 * k[1] + 3.0 * k[2] * r2)
        d_x, d_y = 2.0 * x * d_r, 2.0 * y * d_r
        fx_x = d + d_x * x + 2.0 * p[0] * y + 6.0 * p[1] * x
        fx_y = d_y * x + 2.0 * p[0] * x + 2.0 * p[1] * y
        fy_x = d_x * y + 2.0 * p[1] * y + 2.0 * p[0] * x
        fy_y = d + d_y * y + 2.0 * p[1] * x + 6.0 * p[0] * y
        den = fy_x * fx_y - fx_x * fy_y
        ok = np.abs(den) > 1e-12
        safe = np.where(ok, den, 1.0)
        x = x + np.where(ok, (fx * fy_y - fy * fx_y) / safe, 0.0)
        y = y + np.where(ok, (fy * fx_x - fx * fy_x) / safe, 0.0)
    return x, y


def undistortion_maps(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                      skew: float, k, p):
    """cv2.remap maps that resample a distorted (and skewed) image into the pinhole image of the
    same size with intrinsics (fx, fy, cx, cy) and no skew: output pixel centre (u, v) looks up
    the source at ``(fx xd + skew yd + cx, fy yd + cy)`` where (xd, yd) is the distorted image of
    its normalised ray (nerfies `Camera.project`). OpenCV puts pixel centres at integers, so both
    coordinates shift by 0.5 (docs/design.md section 3 puts them at i + 0.5)."""
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    x = ((u - cx) / fx)[None, :].repeat(height, 0)
    y = ((v - cy) / fy)[:, None].repeat(width, 1)
    xd, yd = distort_normalized(x, y, k, p)
    map_x = (fx * xd + skew * yd + cx - 0.5).astype(np.float32)
    map_y = (fy * yd + cy - 0.5).astype(np.float32)
    return map_x, map_y


def remap(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear resampling with OpenCV; samples outside the source repeat its edge pixels."""
    import cv2

    out = cv2.remap(np.ascontiguousarray(image, np.float32), map_x, map_y,
                    interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(map_x.shape + image.shape[2:]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# atomic writes (docs/design.md section 10)


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2) + "\n").encode("utf-8"))
