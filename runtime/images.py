"""Image files through OpenImageIO (SPEC section 10): PNG 8/16-bit, JPEG, EXR float.

Writes are atomic: a temporary file in the same folder is renamed over the target, so a crash
never leaves a half-written image behind.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


class ImageError(IOError):
    """An image could not be read or written; the message names the file."""


def read_image(path) -> np.ndarray:
    """Read an image as float32 (H, W, C) in [0, 1] (EXR: values as stored)."""
    import OpenImageIO as oiio

    path = str(path)
    if not os.path.isfile(path):
        raise ImageError(f"{path}: no such image file")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageError(f"{path}: cannot read image ({oiio.geterror()})")
    try:
        pixels = inp.read_image("float")
    finally:
        inp.close()
    if pixels is None:
        raise ImageError(f"{path}: cannot decode image")
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    return pixels


def write_image(path, image: np.ndarray, bit_depth: int = 8) -> Path:
    """Write (H, W) or (H, W, C) data atomically; the extension picks the format.

    PNG/JPEG values are clipped to [0, 1] and quantised to `bit_depth` (8 or 16, PNG only);
    EXR keeps float32 values as they are (depth, linear colour).
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.parent.is_dir():
        raise ImageError(f"{path}: folder {path.parent} does not exist")
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[:, :, None]
    h, w, c = image.shape
    ext = path.suffix.lower()
    if ext == ".exr":
        fmt, data = "float", np.ascontiguousarray(image)
    else:
        if bit_depth not in (8, 16) or (bit_depth == 16 and ext != ".png"):
            raise ImageError(f"{path}: bit depth {bit_depth} is not supported for {ext or 'this format'}")
        scale = 255.0 if bit_depth == 8 else 65535.0
        dtype = np.uint8 if bit_depth == 8 else np.uint16
        data = np.ascontiguousarray(np.round(np.clip(image, 0.0, 1.0) * scale).astype(dtype))
        fmt = "uint8" if bit_depth == 8 else "uint16"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ImageError(f"{path}: no writer for {ext!r} ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        if not out.open(tmp, spec):
            raise ImageError(f"{path}: cannot open for writing ({out.geterror()})")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise ImageError(f"{path}: write failed")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path
