"""Image files through OpenImageIO (docs/design.md section 10): PNG 8/16-bit, JPEG, EXR float.

Writes are atomic: a temporary file in the same folder is renamed over the target, so a crash
never leaves a half-written image behind. :func:`atomic_path` is the helper the other writers of
the runtime (PLY, cam.json) share.

The image file suffixes every reader and writer checks against are defined in
:mod:`runtime.suffixes` (re-exported here).
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path

import numpy as np

from .errors import InputProblem
from .suffixes import (ALPHA_SUFFIXES, CAMERA_IMAGE_SUFFIXES, DNERF_IMAGE_SUFFIXES,  # noqa: F401
                       IMAGE_SUFFIXES, STILL_SUFFIXES)


class ImageError(InputProblem, OSError):
    """An image could not be read or written; the message names the file."""


def _current_umask() -> int:
    # Read once at import: os.umask() can only be queried by setting it, which is not thread-safe.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


@contextlib.contextmanager
def atomic_path(path, error=OSError, sweep: bool = True):
    """Yield a temporary path in `path`'s folder; on success it is renamed over `path`.

    The temporary file has the same extension as `path` (format detection by extension), a name
    that says which process wrote it (:mod:`nehad.runtime.tempfiles`) and the permissions an
    ordinary new file would have (mkstemp makes 0600 files). On any exception the temporary file
    is removed and nothing is left at `path` (docs/design.md section 10). With `sweep`, the stale
    temporary files of the same target that a killed writer left are removed first (issue 15);
    writers of many files into one folder (video frames) pass False and sweep the folder once.
    """
    from .errors import write_failure
    from .tempfiles import make_temp, remove_stale_temps

    path = Path(path)
    if not path.parent.is_dir():
        raise error(f"{path}: folder {path.parent} does not exist")
    if sweep:
        remove_stale_temps(path.parent, path.name)
    try:
        tmp = make_temp(path)
    except OSError as e:  # a folder that refuses new files, a full inode table
        raise write_failure(path, e, f"cannot create a file in {path.parent}") from None
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, InputProblem):
            # the system refused the write (disk full, quota, file size limit, I/O error):
            # one message naming the target, not the temporary file (issue 26)
            raise write_failure(path, e) from None
        if isinstance(e, Exception) and _disk_full(path.parent):
            # a library that reports the write failure in its own words (OpenEXR, PyAV)
            raise write_failure(path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) from None
        raise


def _disk_full(folder) -> bool:
    """Whether the file system of `folder` has no block left for this user."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail == 0


#: the last bytes of a complete file, by format: OpenImageIO's PNG and JPEG writers do not
#: report a failed write (a full disk gave an empty x.png and exit status 0; issue 26)
_TRAILERS = {".png": b"IEND\xaeB`\x82", ".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9"}


def check_complete(tmp, path) -> None:
    """Raise WriteError unless the file `tmp`, written for `path`, is complete: not empty, and
    ending as its format must (PNG's IEND chunk, JPEG's end marker)."""
    from .errors import write_failure

    trailer = _TRAILERS.get(Path(path).suffix.lower(), b"")
    try:
        size = os.path.getsize(tmp)
        with open(tmp, "rb") as f:
            f.seek(max(0, size - len(trailer)))
            tail = f.read()
    except OSError as e:
        raise write_failure(path, e) from None
    if size == 0 or (trailer and tail != trailer):
        if _disk_full(Path(path).parent):
            raise write_failure(path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
        raise write_failure(path, OSError(errno.EIO, "the file was written incompletely"))


def atomic_write_bytes(path, data: bytes, error=OSError, sweep: bool = True) -> None:
    """Write `data` to `path` atomically (through :func:`atomic_path`)."""
    with atomic_path(path, error, sweep) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_cut_short(path) -> str | None:
    """Why the PNG at `path` ends before its IEND chunk (a copy or download cut short), or
    None when its chunks reach IEND (or it is not a PNG). Walks the chunk headers only; read
    before decoding because libpng prints its own line to the terminal on such a file, beside
    the error we raise."""
    with open(path, "rb") as f:
        if f.read(8) != _PNG_SIGNATURE:
            return None
        size = os.fstat(f.fileno()).st_size
        at = 8
        while True:
            head = f.read(8)
            if len(head) < 8:
                return f"the file ends at byte {size} inside its chunks, before IEND"
            length = int.from_bytes(head[:4], "big")
            if head[4:8] == b"IEND":
                return None
            at += 12 + length  # length, type, data, CRC
            if at > size:
                return (f"chunk {head[4:8].decode('latin-1')!r} needs {at - size} more bytes "
                        f"than the file's {size}")
            f.seek(at)


def read_image(path) -> np.ndarray:
    """Read an image as float32 (H, W, C): PNG/JPEG scaled to [0, 1], EXR values as stored.

    Alpha follows OpenImageIO's convention: in memory, colour is associated (premultiplied) with
    alpha. A straight-alpha PNG (D-NeRF, Blender) therefore comes back as rgb * a, and the
    composite over a background is ``rgb + bg * (1 - a)``.
    """
    import OpenImageIO as oiio

    path = str(path)
    if not os.path.isfile(path):
        raise ImageError(f"{path}: no such image file")
    short = png_cut_short(path)
    if short is not None:
        raise ImageError(f"{path}: cannot decode image (a PNG cut short: {short})")
    # Ask for the stored (straight) colour and premultiply in float below: OpenImageIO's own
    # premultiplication of an 8-bit PNG happens in 8 bits and rounds the colour a second time.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(path, config)
    if inp is None:
        raise ImageError(f"{path}: cannot read image ({oiio.geterror()})")
    try:
        spec = inp.spec()
        straight = spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 1
        alpha = spec.alpha_channel
        pixels = inp.read_image("float")
        if pixels is None:
            raise ImageError(f"{path}: cannot decode image ({inp.geterror()})")
    finally:
        inp.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if straight and 0 <= alpha < pixels.shape[2]:
        colour = [i for i in range(pixels.shape[2]) if i != alpha]
        pixels[:, :, colour] *= pixels[:, :, alpha:alpha + 1]
    return pixels


def write_image(path, image: np.ndarray, bit_depth: int = 8,
                png_compression: int | None = None, sweep: bool = True) -> Path:
    """Write (H, W) or (H, W, C) data atomically; the extension picks the format.

    PNG/JPEG values are clipped to [0, 1] (NaN -> 0) and quantised to `bit_depth` (8, or 16 for
    PNG only); JPEG keeps at most 3 channels (OpenImageIO drops alpha). EXR keeps float32 values as
    they are (depth, linear colour). RGBA (and gray+alpha) input is associated (premultiplied)
    colour, as a render over a black background gives; a PNG stores straight alpha, so colour is
    divided by alpha (in float, before quantisation) and :func:`read_image` multiplies it back.
    `png_compression` (0..9, zlib level) trades PNG size for speed (video frames use 1: about
    half the write time of the default for a quarter more bytes). `sweep`: see
    :func:`atomic_path`. Returns the path.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.parent.is_dir():
        raise ImageError(f"{path}: folder {path.parent} does not exist")
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or 0 in image.shape:
        raise ImageError(f"{path}: expected an (H, W) or (H, W, C) image, got shape {image.shape}")
    h, w, c = image.shape
    ext = path.suffix.lower()
    straight_alpha = False
    if ext == ".exr":
        fmt, data = "float", np.ascontiguousarray(image)
    else:
        if c > 4:
            raise ImageError(f"{path}: {c} channels cannot be stored as {ext or 'this format'}")
        if bit_depth not in (8, 16) or (bit_depth == 16 and ext != ".png"):
            raise ImageError(f"{path}: bit depth {bit_depth} is not supported for {ext or 'this format'}")
        scale = 255.0 if bit_depth == 8 else 65535.0
        dtype = np.uint8 if bit_depth == 8 else np.uint16
        clean = np.clip(np.nan_to_num(image, nan=0.0), 0.0, 1.0)
        if straight_alpha := (ext == ".png" and c in (2, 4)):
            # PNG stores straight alpha: divide in float here (OpenImageIO would do it on the
            # already quantised values); colour under alpha 0 is stored as 0.
            a = clean[:, :, c - 1:]
            clean = clean.copy()
            with np.errstate(divide="ignore", invalid="ignore"):
                clean[:, :, :c - 1] = np.where(a > 0, np.minimum(clean[:, :, :c - 1] / a, 1.0), 0.0)
        data = np.ascontiguousarray(np.round(clean * scale).astype(dtype))
        fmt = "uint8" if bit_depth == 8 else "uint16"
    with atomic_path(path, ImageError, sweep) as tmp:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ImageError(f"{path}: no writer for {ext!r} ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        if png_compression is not None and ext == ".png":
            spec.attribute("png:compressionLevel", int(png_compression))
        if straight_alpha:
            spec.alpha_channel = c - 1
            spec.attribute("oiio:UnassociatedAlpha", 1)
        if not out.open(tmp, spec):
            msg = out.geterror()
            out.close()
            raise ImageError(f"{path}: cannot open for writing ({msg})")
        ok = out.write_image(data)
        msg = "" if ok else out.geterror()
        closed = out.close()
        if not ok or not closed:
            msg = (msg or out.geterror()).replace(str(tmp), str(path))
            raise ImageError(f"{path}: write failed ({msg})")
        check_complete(tmp, path)
    return path
