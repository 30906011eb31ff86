"""What a user brings to `nehad prepare` (docs/capture.md): found, checked and decoded.

Four inputs, told apart by what INPUT holds (or named with ``kind``):

- a folder of two or more videos: a **rig** of static, synchronised cameras, one video each;
- one video file (or a folder with exactly one): a **monocular** capture from a moving camera;
- a folder of two or more sub-folders of images: a rig, one sub-folder per camera, the images
  of each in the same order (frame i of every camera taken at the same instant);
- a folder of images: a monocular capture, in file-name order.

:func:`find_sources` returns one :class:`Source` per camera (or the one moving camera) after the
checks that need no decoding: something found, and for a rig the same frame count and rate in
every video (or ``trim`` to the shortest). :func:`decode` writes each kept frame as a PNG into
the work folder, atomically per source (a folder renamed into place when complete), so a
resumed run reuses what was decoded. Frame times: a rig's frame i of N is at i / (N - 1); a
monocular video's frames at their timestamps, normalised to [0, 1].
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

from nehad.data.common import DatasetError
from nehad.runtime.suffixes import CAPTURE_VIDEO_SUFFIXES, STILL_SUFFIXES

__all__ = ["PrepareError", "Source", "find_sources", "decode", "KINDS"]

KINDS = ("auto", "rig", "monocular")


class PrepareError(DatasetError):
    """An input `nehad prepare` cannot use; the message names it and what to do."""


@dataclass
class Source:
    """One camera of the capture: a video or an ordered list of images."""

    name: str
    video: Path | None = None
    images: list[Path] = field(default_factory=list)
    frames: int = 0  # frames (or images) it holds
    rate: Fraction | None = None  # a video's frame rate

    @property
    def path(self) -> Path:
        return self.video if self.video is not None else self.images[0].parent


def _natural(p: Path):
    return [int(x) if x.isdigit() else x.lower() for x in re.split(r"(\d+)", p.name)]


def _videos(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in CAPTURE_VIDEO_SUFFIXES), key=_natural)


def _images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in STILL_SUFFIXES), key=_natural)


def _probe(video: Path) -> tuple[int, Fraction]:
    """(frame count, frame rate) of a video (nehad.data.dynerf.probe_video); PrepareError when
    it cannot be read."""
    from nehad.data.dynerf import probe_video

    try:
        return probe_video(video)
    except PrepareError:
        raise
    except DatasetError as exc:
        raise PrepareError(str(exc)) from None


def _layout(root: Path) -> tuple[str, list[Source]]:
    """(kind the layout suggests, sources) of INPUT `root`, before any check of their sizes."""
    if root.is_file():
        if root.suffix.lower() not in CAPTURE_VIDEO_SUFFIXES:
            raise PrepareError(f"{root}: not a video ({', '.join(CAPTURE_VIDEO_SUFFIXES)}) "
                               f"nor a folder")
        return "monocular", [Source(root.stem, video=root)]
    videos = _videos(root)
    if videos:
        kind = "rig" if len(videos) > 1 else "monocular"
        return kind, [Source(v.stem, video=v) for v in videos]
    subfolders = sorted((p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")),
                        key=_natural)
    cams = [Source(d.name, images=_images(d)) for d in subfolders]
    cams = [c for c in cams if c.images]
    if len(cams) > 1:
        return "rig", cams
    images = _images(root)
    if images:
        return "monocular", [Source(root.name, images=images)]
    if len(cams) == 1:
        return "monocular", cams
    raise PrepareError(f"{root}: no video ({', '.join(CAPTURE_VIDEO_SUFFIXES)}) or image "
                       f"({', '.join(STILL_SUFFIXES)}) found, neither in it nor in its sub-folders")


def _check_rig(sources: list[Source], trim: bool) -> int:
    """The frame count every rig camera is cut to; PrepareError when rates or counts differ
    (counts: unless `trim`)."""
    rates = {s.rate for s in sources if s.rate is not None}
    if len(rates) > 1:
        common = max(rates, key=lambda r: sum(s.rate == r for s in sources))
        odd = [f"{s.path.name} ({float(s.rate):.3g} fps)" for s in sources if s.rate != common]
        raise PrepareError(f"the videos' frame rates differ: {', '.join(odd)} against "
                           f"{float(common):.3g} fps for the others; re-encode them to one rate")
    counts = {s.frames for s in sources}
    shortest = min(counts)
    if len(counts) > 1 and not trim:
        common = max(counts, key=lambda n: sum(s.frames == n for s in sources))
        odd = [f"{s.path.name} ({s.frames})" for s in sources if s.frames != common]
        raise PrepareError(f"the cameras hold different numbers of frames: {', '.join(odd)} "
                           f"against {common} for the others; --trim cuts every camera to the "
                           f"shortest ({shortest})")
    return shortest


def find_sources(root, kind: str = "auto", trim: bool = False) -> tuple[str, list[Source], int]:
    """(kind, sources, frames per source) of INPUT `root` (module doc); PrepareError on an
    input that cannot be used, before anything is decoded."""
    root = Path(root)
    if kind not in KINDS:
        raise PrepareError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    if not root.exists():
        raise PrepareError(f"{root}: no such file or folder")
    found, sources = _layout(root)
    kind = found if kind == "auto" else kind
    if kind == "rig" and len(sources) < 2:
        raise PrepareError(f"{root}: a rig needs two or more cameras (videos or image "
                           f"sub-folders); found {len(sources)}")
    if kind == "monocular" and len(sources) != 1:
        raise PrepareError(f"{root}: a monocular capture is one video or one folder of "
                           f"images; found {len(sources)} cameras (--kind rig?)")
    for s in sources:
        if s.video is not None:
            s.frames, s.rate = _probe(s.video)
        else:
            s.frames = len(s.images)
    n = _check_rig(sources, trim) if kind == "rig" else sources[0].frames
    if n < 2:
        raise PrepareError(f"{sources[0].path}: a capture needs at least 2 frames, found {n}")
    return kind, sources, n


def _decode_video(video: Path, dest: Path, limit: int, fps: float | None,
                  progress) -> list[float]:
    """Write frames of `video` as dest/NNNNNN.png (the first `limit`, or one per 1/fps);
    returns the kept frames' times in seconds."""
    import av
    import cv2

    times, n = [], 0
    try:
        with av.open(str(video)) as container:
            stream = container.streams.video[0]
            next_t = None
            for k, frame in enumerate(container.decode(stream)):
                if k >= limit:
                    break
                t = float(frame.time) if frame.time is not None else k / float(stream.average_rate or 30)
                if progress is not None:
                    progress(1)
                if fps and next_t is not None and t < next_t - 1e-6:
                    continue
                next_t = (t if next_t is None else next_t) + (1.0 / fps if fps else 0.0)
                if not cv2.imwrite(str(dest / f"{n:06d}.png"), frame.to_ndarray(format="bgr24"),
                                   [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise OSError(f"{dest}: cannot write frame {n}")
                times.append(t)
                n += 1
    except (PrepareError, OSError):
        raise
    except Exception as exc:
        raise PrepareError(f"{video}: cannot decode the video ({type(exc).__name__}: {exc})") from None
    return times


def _copy_images(images: list[Path], dest: Path, progress) -> list[float]:
    import cv2

    for n, path in enumerate(images):
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise PrepareError(f"{path}: cannot read the image")
        if not cv2.imwrite(str(dest / f"{n:06d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"{dest}: cannot write frame {n}")
        if progress is not None:
            progress(1)
    return [float(n) for n in range(len(images))]


def decode(source: Source, dest: Path, limit: int, fps: float | None = None,
           progress=None) -> tuple[list[Path], list[float]]:
    """The frames of `source` as PNGs in folder `dest` and their times (seconds for a video,
    the index for images). A complete `dest` from an earlier run is reused (`done.json`)."""
    dest = Path(dest)
    marker = dest / "done.json"
    if marker.exists():
        times = json.loads(marker.read_text())["times"]
        if progress is not None:
            progress(limit)
        return [dest / f"{n:06d}.png" for n in range(len(times))], times
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        if source.video is not None:
            times = _decode_video(source.video, tmp, limit, fps, progress)
        else:
            times = _copy_images(source.images[:limit], tmp, progress)
        if not times:
            raise PrepareError(f"{source.path}: no frame decoded")
        (tmp / "done.json").write_text(json.dumps({"times": times}))
        if dest.exists():
            shutil.rmtree(dest)
        os.rename(tmp, dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return [dest / f"{n:06d}.png" for n in range(len(times))], times
