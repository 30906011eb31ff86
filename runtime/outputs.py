"""An output that is also an input is refused before anything is written (issue 26).

``nehad batch j.png`` with a job writing ``j.png``, ``nehad ply gaussians.ply --time 0 -o
gaussians.ply``, ``nehad export run -o run/model.pt``: the command would overwrite (or, through
its atomic rename, replace) a file it is still reading, or that the next run needs. Every
command lists what it reads and what it will write and calls :func:`check_outputs` after its
arguments are parsed and before any work.

What a command reads: a file given as an input (``--view cam.json:3`` reads ``cam.json``), and,
for a folder given as an input (a training run, a split layers folder), the files its readers
open there (:data:`FOLDER_INPUTS`). Two names are the same file when the file system says so
(hard links, symbolic links, ``..``) or, for files that do not exist yet, when their absolute
normalised paths are equal.
"""

from __future__ import annotations

import fnmatch
import os
import re
from pathlib import Path

from .errors import InputProblem

__all__ = ["OutputIsInputError", "FOLDER_INPUTS", "check_outputs", "input_files", "same_file",
           "strip_index"]

#: Files the readers of a run folder or a split layers folder open (glob patterns, relative).
FOLDER_INPUTS = ("model.pt", "config.yaml", "metrics.jsonl", "checkpoints/step_*.pt",
                 "manifest.json", "base.onnx", "layer_*.bin", "eval_*/metrics.json")

_INDEX = re.compile(r"^(?P<file>.+?)(?:[:#]-?[^:#/]*)$")


class OutputIsInputError(InputProblem):
    """An output names a file the command reads."""


def strip_index(spec) -> str:
    """``cams.json:3`` / ``cams.json#3`` -> ``cams.json`` (a camera file with its frame index);
    anything that exists as given is kept as it is."""
    text = str(spec)
    if os.path.exists(text):
        return text
    m = _INDEX.match(text)
    return m.group("file") if m else text


def _key(path) -> str:
    return os.path.normcase(os.path.abspath(os.path.realpath(os.fspath(path))))


def same_file(a, b) -> bool:
    """Whether the paths `a` and `b` name the same file (module doc)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return _key(a) == _key(b)


def input_files(path) -> list[Path]:
    """The files a command reads from the input `path`: the file itself, or a folder's
    :data:`FOLDER_INPUTS`."""
    p = Path(strip_index(path))
    if not p.is_dir():
        return [p]
    found = []
    for pattern in FOLDER_INPUTS:
        found += sorted(p.glob(pattern))
    return found


def check_outputs(outputs, inputs, error=OutputIsInputError) -> None:
    """Refuse (``error``) when an output is one of the inputs.

    `outputs`: (label, path) pairs of files to write, or (label, folder, pattern) triples of a
    folder the command writes files matching the glob `pattern` into; `inputs`: (label, path)
    pairs as given on the command line (files, folders, ``FILE:K`` camera specs; None skipped).
    Labels are how the message names the value (``-o``, ``--view``, ``jobs[2].output``)."""
    files = []
    for label, value in inputs:
        if value is None:
            continue
        for f in input_files(value):
            files.append((label, value, f))
    for out in outputs:
        label, target = out[0], out[1]
        if target is None:
            continue
        for in_label, value, f in files:
            if len(out) == 3:
                clash = same_file(Path(f).parent, target) and fnmatch.fnmatch(Path(f).name, out[2])
            else:
                clash = same_file(f, target) or (Path(target).exists() and Path(target).is_dir()
                                                 and same_file(target, value))
            if clash:
                what = f"{in_label} {value}" if str(f) == str(strip_index(value)) else \
                    f"{in_label} {value} (it reads {f})"
                raise error(f"{label} {target}: is also an input ({what}); writing it would "
                            f"destroy what the command reads: choose another output")
