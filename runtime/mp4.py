"""The project's one mp4 encoder: frames (arrays or image files) in, an mp4 out, written atomically.

    with Mp4Writer("orbit.mp4", fps=29.97) as video:      # streaming, one frame at a time
        for frame in frames:
            video.write(frame)                            # uint8 or float (H, W, 3)
    encode(["f0.png", "f1.png"], "clip.mp4")              # an iterable of arrays or image files
    encode(frames_u8, "cam00.mp4", lossless=True)         # exact 8-bit RGB (test fixtures)

Every video of the project (``nehad video``, trajectory videos, the synthetic DyNeRF fixtures)
goes through here, so the rules below hold for all of them (docs/design.md section 10.1):

* **Encoders.** ``encoder="auto"`` uses PyAV (libx264, H.264 yuv420p, quality `crf`, preset
  medium) and falls back to OpenCV's ``mp4v`` (MPEG-4 part 2, yuv420p; `crf` unused) when PyAV is
  missing; ``"pyav"`` / ``"opencv"`` ask for one.
* **Reproducible.** ``reproducible=True`` turns x264's macroblock-tree rate control off: with
  it on, this libx264 (PyAV 18.1) writes other bytes for the same frames from run to run, even
  on one thread (decoded frames up to 48 levels apart; 2026-11-28), so the made-up captures of
  :mod:`nehad.data.synth_capture`, which tests pose, ask for it. Off by default: what it does to
  size and quality depends on the content (on an orbiting capture at crf 18: 11% smaller and
  0.5 dB under; on frames that jump between cameras: 50% larger, 0.9 dB over). PyAV only;
  OpenCV's mp4v ignores it.
* **Lossless.** ``lossless=True`` writes H.264 in its RGB profile (``libx264rgb``, crf 0, preset
  ultrafast; `crf` unused): decoding with PyAV as ``rgb24`` gives back every 8-bit value exactly
  (yuv444p at qp 0 would not: its RGB -> YUV conversion changes values by up to 2). PyAV only;
  OpenCV has no lossless mp4 encoder, so asking for it there is an error.
* **Frame rate.** :func:`video_rate`: whole numbers exactly, the NTSC rates (29.97, 59.94, 23.976
  ...) as N*1000/1001, anything else to the nearest fraction with a denominator of at most 1000.
  PyAV stores that rate exactly; OpenCV stores its own rounding (29.97 -> 2997/100).
* **Sizes.** All frames must have the size of the first (an error names the frame index). A
  width or height that the pixel format cannot hold is padded, never refused: yuv420p (the
  default H.264 and mp4v) stores chroma at half resolution and needs even sizes, so an odd frame
  gets one more column (right) and/or row (bottom) repeating its last one -- the decoded video is
  then e.g. 48x34 for 47x33 frames, and cropping that column/row gives the frames back. The
  lossless RGB mode has no chroma subsampling and keeps any size exactly (a data set read back
  from it must have the size its cameras say), so it never pads. (OpenCV would otherwise crop odd
  sizes silently and libx264 refuses them.)
* **Pixels.** uint8 arrays are used as they are; float arrays are clipped to [0, 1] (NaN -> 0)
  and rounded to 8 bits exactly as a PNG is written; (H, W) and (H, W, 1) are grey, a fourth
  channel (alpha) is dropped. Image files are read with :func:`nehad.runtime.images.read_image`.
  Other dtypes are refused.
* **Atomic.** The video is encoded into a temporary file beside the output and renamed over it
  when complete (:func:`nehad.runtime.images.atomic_path`); on any error, or a writer closed
  without frames, nothing is left at the output.

Problems with the input raise :class:`Mp4Error` (a ValueError and an
:class:`nehad.runtime.errors.InputProblem`; or the class given as `error`), with a message that
starts with the output file.
"""

from __future__ import annotations

import contextlib
import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from .errors import InputProblem

__all__ = ["DEFAULT_CRF", "DEFAULT_FPS", "ENCODERS", "MAX_FPS", "MIN_FPS", "Mp4Error",
           "Mp4Writer", "encode", "encoded_size", "video_rate"]

#: Frames per second of a video when none is asked for.
DEFAULT_FPS = 30.0
#: libx264's constant rate factor when none is asked for (0 = lossless in YUV .. 51 = worst).
DEFAULT_CRF = 18
#: The highest frame rate accepted.
MAX_FPS = 1000.0
#: The lowest frame rate a video stores (`video_rate` keeps rates to 1/1000 of a frame).
MIN_FPS = 0.001
#: Values of `encoder`.
ENCODERS = ("auto", "pyav", "opencv")

_PRESET = "medium"
_LOSSLESS_PRESET = "ultrafast"  # lossless output is the same at any preset; only the size differs


class Mp4Error(InputProblem):
    """An mp4 cannot be written from the given frames or settings (a ValueError, and a bad input
    of the runtime, runtime/errors.py); the message starts with the output file and names no
    option."""


def video_rate(fps: float) -> Fraction:
    """The exact frame rate of `fps`: whole numbers as they are, 29.97 / 59.94 / 23.976 as the
    NTSC rates N*1000/1001, anything else to 1/1000."""
    whole = round(fps)
    if abs(fps - whole) < 1e-9:
        return Fraction(whole)
    ntsc = round(fps * 1.001)
    if ntsc >= 1 and abs(fps - ntsc / 1.001) < 5e-3:  # (not a rate under 1/2 fps: 0/1001)
        return Fraction(ntsc * 1000, 1001)
    return Fraction(fps).limit_denominator(1000)


def encoded_size(width: int, height: int, lossless: bool = False) -> tuple[int, int]:
    """The (width, height) the video stores for frames of `width` x `height`: rounded up to even
    numbers (yuv420p), or as they are with `lossless` (RGB)."""
    if lossless:
        return int(width), int(height)
    return int(width) + int(width) % 2, int(height) + int(height) % 2


def _have_pyav() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True


def _quantise(img: np.ndarray) -> np.ndarray:
    """uint8 exactly as write_image stores a float image in an 8-bit PNG."""
    clean = np.clip(np.nan_to_num(np.asarray(img, np.float32), nan=0.0), 0.0, 1.0)
    return np.round(clean * 255.0).astype(np.uint8)


class Mp4Writer:
    """An mp4 being written, one frame at a time; a context manager.

    ``with Mp4Writer(output, fps, crf, encoder, lossless=...) as w: w.write(frame) ...`` writes
    the video when the block ends without an exception; on an exception nothing is left at
    `output`. Without ``with``, call :meth:`close` (keep the video) or :meth:`abort` (discard it).
    `error` is the exception class raised for bad input (default :class:`Mp4Error`).

    After the first frame: ``size`` is the frames' (width, height), ``encoded_size`` the video's;
    ``frames`` counts the frames written; ``description`` names the encoder (as :func:`encode`
    returns it).
    """

    def __init__(self, output, fps: float = DEFAULT_FPS, crf: int = DEFAULT_CRF,
                 encoder: str = "auto", *, lossless: bool = False, reproducible: bool = False,
                 error=Mp4Error):
        from .images import atomic_path

        self.output = Path(output)
        self.error = error
        self.lossless, self.reproducible = bool(lossless), bool(reproducible)
        out = self.output
        if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
            raise error(f"{out}: frame rate {fps!r}: expected a number in "
                        f"[{MIN_FPS:g}, {MAX_FPS:g}]")
        self.rate = video_rate(float(fps))
        if self.rate <= 0:
            raise error(f"{out}: frame rate {fps!r}: too low (below 1/1000 frame per second)")
        if isinstance(crf, bool) or not isinstance(crf, (int, np.integer)) or not 0 <= crf <= 51:
            raise error(f"{out}: crf {crf!r}: expected an integer in 0..51")
        self.crf = int(crf)
        if encoder not in ENCODERS:
            raise error(f"{out}: encoder {encoder!r}: expected one of {', '.join(ENCODERS)}")
        if encoder == "auto":
            encoder = "pyav" if _have_pyav() else "opencv"
        if encoder == "opencv" and self.lossless:
            raise error(f"{out}: a lossless mp4 needs PyAV (libx264rgb); OpenCV's mp4v is lossy")
        if encoder == "pyav" and not _have_pyav():
            raise error(f"{out}: PyAV is not installed (pip install av)")
        self.encoder = encoder
        if encoder == "opencv":
            self.description = "mp4v (OpenCV)"
        elif self.lossless:
            self.description = "H.264 lossless RGB (PyAV)"
        else:
            self.description = "H.264 yuv420p (PyAV)"
        self.frames = 0
        self.size: tuple[int, int] | None = None
        self.encoded_size: tuple[int, int] | None = None
        self._container = self._stream = self._cv = None
        self._done = False
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(out, error))

    # -- context manager

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc)
        return False

    # -- frames

    def _image(self, frame) -> np.ndarray:
        """`frame` as a contiguous uint8 (H, W, 3) array (see the module doc)."""
        k = self.frames
        if isinstance(frame, (str, os.PathLike)):
            from .images import read_image

            a = read_image(frame)
        else:
            a = np.asarray(frame)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] < 1 or a.shape[1] < 1:
            raise self.error(f"{self.output}: frame {k}: expected an (H, W, 3) image, got shape "
                             f"{tuple(a.shape)}")
        if a.dtype != np.uint8:
            if not np.issubdtype(a.dtype, np.floating):
                raise self.error(f"{self.output}: frame {k}: pixel type {a.dtype}: expected uint8 "
                                 f"or float in [0, 1]")
            a = _quantise(a[:, :, :3])
        a = a[:, :, :3]
        if a.shape[2] == 1:
            a = np.repeat(a, 3, axis=2)
        return np.ascontiguousarray(a)

    def write(self, frame) -> None:
        """Add one frame: an (H, W, 3) uint8 or float array, or an image file."""
        if self._done:
            raise self.error(f"{self.output}: the video is already closed")
        img = self._image(frame)
        h, w = img.shape[:2]
        if self.size is None:
            self._open(w, h)
        elif (w, h) != self.size:
            raise self.error(f"{self.output}: frame {self.frames} is {w}x{h}, the first is "
                             f"{self.size[0]}x{self.size[1]}")
        ew, eh = self.encoded_size
        if (ew, eh) != (w, h):  # repeat the last column / row (see the module doc)
            img = np.pad(img, ((0, eh - h), (0, ew - w), (0, 0)), mode="edge")
        if self.encoder == "pyav":
            import av

            vf = av.VideoFrame.from_ndarray(img, format="rgb24")
            for packet in self._stream.encode(vf):
                self._container.mux(packet)
        else:
            self._cv.write(np.ascontiguousarray(img[:, :, ::-1]))
        self.frames += 1

    def _open(self, w: int, h: int) -> None:
        self.size = (w, h)
        self.encoded_size = encoded_size(w, h, self.lossless)
        ew, eh = self.encoded_size
        if self.encoder == "pyav":
            import av

            self._container = av.open(self._tmp, mode="w", format="mp4")
            if self.lossless:
                stream = self._container.add_stream("libx264rgb", rate=self.rate)
                stream.pix_fmt = "rgb24"
                stream.options = {"crf": "0", "preset": _LOSSLESS_PRESET}
            else:
                stream = self._container.add_stream("libx264", rate=self.rate)
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": str(self.crf), "preset": _PRESET,
                                  **({"x264-params": "mbtree=0"} if self.reproducible else {})}
            stream.width, stream.height = ew, eh
            self._stream = stream
        else:
            import cv2

            self._cv = cv2.VideoWriter(self._tmp, cv2.VideoWriter_fourcc(*"mp4v"),
                                       float(self.rate), (ew, eh))
            if not self._cv.isOpened():
                self._cv = None
                raise self.error(f"{self.output}: OpenCV cannot open an mp4v writer")

    # -- ending

    def close(self) -> None:
        """Finish the video and rename it over the output. With no frames written, nothing is
        written and :class:`Mp4Error` (or `error`) is raised."""
        if self._done:
            return
        try:
            if self.frames == 0:
                raise self.error(f"{self.output}: no frames to encode")
            if self._stream is not None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
            self._release()
        except BaseException as exc:
            self.abort(exc)
            raise
        self._done = True
        self._stack.close()  # renames the temporary file over the output

    def abort(self, exc: BaseException | None = None) -> None:
        """Discard the video: nothing is left at the output (an earlier file there is kept)."""
        if self._done:
            return
        self._done = True
        with contextlib.suppress(Exception):
            self._release()
        exc = exc if exc is not None else self.error(f"{self.output}: aborted")
        self._stack.__exit__(type(exc), exc, exc.__traceback__)  # removes the temporary file

    def _release(self) -> None:
        container, cv, self._container, self._cv, self._stream = self._container, self._cv, None, \
            None, None
        if container is not None:
            container.close()
        if cv is not None:
            cv.release()


def encode(frames, output, fps: float = DEFAULT_FPS, crf: int = DEFAULT_CRF,
           encoder: str = "auto", *, lossless: bool = False, reproducible: bool = False,
           error=Mp4Error) -> str:
    """Encode `frames` (an iterable of image files or uint8/float (H, W, 3) arrays) into the mp4
    `output`, atomically, by the rules of the module doc. Returns the encoder used, e.g.
    ``"H.264 yuv420p (PyAV)"`` or ``"mp4v (OpenCV)"``. Frames of another size than the first, an
    empty iterable and bad settings raise `error` (default :class:`Mp4Error`) naming `output`."""
    with Mp4Writer(output, fps, crf, encoder, lossless=lossless, reproducible=reproducible,
                   error=error) as video:
        for frame in frames:
            video.write(frame)
    return video.description
