"""One entry point for every dataset layout the trainer reads (docs/design.md section 5).

:func:`load_dataset` looks at the folder and hands it to the right reader:

=============  ==================================================  =============================
layout         recognised by                                       reader
=============  ==================================================  =============================
``dnerf``      ``transforms_{train,val,test}.json``                :mod:`nehad.data.dnerf`
``hypernerf``  ``dataset.json`` + ``metadata.json`` + ``scene.json``  :mod:`nehad.data.hypernerf`
``dynerf``     ``poses_bounds.npy``                                :mod:`nehad.data.dynerf`
=============  ==================================================  =============================

Every reader returns the same :class:`~nehad.data.dnerf.DNeRFScene` (frames per split with
:class:`~nehad.runtime.cameras.Camera` objects, times in [0, 1], background, initial points).
Split names: ``train`` and ``test`` everywhere; ``val`` is D-NeRF's own split, HyperNeRF's
``val_ids`` (as ``test``) and DyNeRF's cam00 (as ``test``).
"""

from __future__ import annotations

from pathlib import Path

from nehad.data.dnerf import SPLITS as DNERF_SPLITS
from nehad.data.dnerf import DatasetError, DNeRFScene, load_dnerf

__all__ = ["FORMATS", "detect_format", "load_dataset"]

FORMATS = ("dnerf", "hypernerf", "dynerf")


def detect_format(root) -> str:
    """"dnerf", "hypernerf" or "dynerf" for a scene folder; DatasetError when none fits."""
    from nehad.data.dynerf import is_dynerf
    from nehad.data.hypernerf import is_hypernerf

    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: scene folder not found")
    found = []
    if any((root / f"transforms_{s}.json").is_file() for s in DNERF_SPLITS):
        found.append("dnerf")
    if is_hypernerf(root):
        found.append("hypernerf")
    if is_dynerf(root):
        found.append("dynerf")
    if len(found) == 1:
        return found[0]
    if found:
        raise DatasetError(f"{root}: holds the files of several dataset layouts "
                           f"({', '.join(found)}); pass the format explicitly")
    hint = ""
    if (root / "dataset.json").is_file() or (root / "metadata.json").is_file():
        missing = [n for n in ("dataset.json", "metadata.json", "scene.json")
                   if not (root / n).is_file()]
        hint = f" (looks like HyperNeRF but {', '.join(missing)} missing)"
    elif any(p.suffix == ".mp4" for p in root.iterdir()):
        hint = " (has videos, but a DyNeRF scene also needs poses_bounds.npy)"
    raise DatasetError(f"{root}: not a dataset folder{hint}: expected transforms_*.json (D-NeRF), "
                       f"dataset.json + metadata.json + scene.json (HyperNeRF) or "
                       f"poses_bounds.npy (DyNeRF)")


def _stride(scene: DNeRFScene, stride: int) -> DNeRFScene:
    if stride > 1:
        scene.frames = {s: fs[::stride] for s, fs in scene.frames.items()}
        loaded = [f.time for fs in scene.frames.values() for f in fs]
        if loaded:
            scene.time_range = (min(loaded), max(loaded))
    return scene


def load_dataset(root, splits=("train",), background=(1.0, 1.0, 1.0), downscale: int = 1,
                 frame_stride: int = 1, format: str = "auto", **options) -> DNeRFScene:
    """Load any supported scene folder (layout detected unless `format` names it).

    `background`: what RGBA images are composited over (HyperNeRF and DyNeRF images are RGB, so
    it does not touch them). `downscale`: integer image downscale (HyperNeRF: the ``rgb/<S>x``
    folder when present). `frame_stride`: DyNeRF keeps video frames 0, s, 2s, ... (times stay
    those of the full video); D-NeRF and HyperNeRF keep every s-th image of each split.
    `options` go to the reader (``undistort`` for HyperNeRF, ``max_frames`` for DyNeRF).
    """
    from nehad.data.common import DatasetError, check_stride

    fmt = detect_format(root) if format == "auto" else format
    if fmt not in FORMATS:
        raise ValueError(f"format: expected auto or one of {', '.join(FORMATS)}, got {format!r}")
    frame_stride = check_stride(frame_stride)
    if isinstance(splits, str):
        splits = (splits,)
    scene = _load(root, fmt, splits, background, downscale, frame_stride, options)
    for split in splits:
        if not scene.frames.get(split):
            raise DatasetError(f"{root}: the {split} split has no frames")
    return scene


def _load(root, fmt, splits, background, downscale, frame_stride, options) -> DNeRFScene:
    """The reader of `fmt` on `root` (load_dataset's arguments, checked)."""
    if fmt == "dnerf":
        if options:
            raise TypeError(f"load_dataset: D-NeRF takes no options {sorted(options)}")
        scene = _stride(load_dnerf(root, splits=splits, background=background,
                                   downscale=downscale), frame_stride)
        scene.format = "dnerf"
        return scene
    if fmt == "hypernerf":
        from nehad.data.hypernerf import load_hypernerf

        return load_hypernerf(root, splits=splits, background=background, downscale=downscale,
                              frame_stride=frame_stride, **options)
    from nehad.data.dynerf import load_dynerf

    return load_dynerf(root, splits=splits, background=background, downscale=downscale,
                       frame_stride=frame_stride, **options)
