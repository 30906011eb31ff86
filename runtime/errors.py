"""Bad inputs of the runtime (docs/design.md, "Bad inputs and atomic writes").

Every error the runtime raises for a user's input is an :class:`InputProblem` (the camera, PLY,
image, model, path, video, batch, layer, memory and lock errors derive from it). It carries
which input was bad (`input`: "scene", "view", "time", "lod", "output", ...) and a message that
names inputs as placeholders, ``{time}`` or ``{extrapolate}``: each caller shows them in its own
words. The command line shows ``--time`` and ``--extrapolate``, a jobs.yaml shows its keys
``time`` and ``extrapolate: true``, and ``str(error)`` the plain key. The runtime itself never
writes an option name.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

#: The inputs a message may name as {placeholder}; anything else in braces is left alone.
INPUTS = frozenset({
    "scene", "view", "time", "lod", "output", "size", "background", "extrapolate", "path",
    "frames", "frames_dir", "frame_format", "fps", "crf", "encoder", "side_by_side", "threads",
    "workers", "scheduler", "depth", "alpha", "sh_degree", "format", "host", "port", "mode",
    "cameras",
})
_PLACEHOLDER = re.compile(r"\{(" + "|".join(sorted(INPUTS)) + r")\}")


class InputProblem(ValueError):
    """A bad input (module doc). `input` is the key of the input at fault, or None when the
    message names the file itself (a damaged model, a malformed camera file)."""

    def __init__(self, message: str, input: str | None = None):
        super().__init__(message)
        self.template = str(message)
        self.input = input

    def message(self, names: Mapping[str, str] | None = None) -> str:
        """The message with each {input} shown as `names` calls it (default: the key)."""
        names = names or {}
        return _PLACEHOLDER.sub(lambda m: names.get(m.group(1), m.group(1)), self.template)

    def __str__(self) -> str:
        return self.message()


class WriteError(InputProblem, OSError):
    """A file could not be written: the disk is full, the folder refuses writes, a file size
    limit, ... (issue 26). The message names the file the user asked for (never only the
    temporary file it was written through) and what the system said."""


def write_failure(path, exc: BaseException, verb: str = "cannot write it") -> WriteError:
    """The WriteError for `exc`, an OSError (or a library's error for one) met while writing
    `path`: ``PATH: cannot write it (No space left on device); nothing was written there``."""
    import errno as _errno
    import os as _os

    code = getattr(exc, "errno", None)
    reason = _os.strerror(code) if isinstance(code, int) and code > 0 else \
        (getattr(exc, "strerror", None) or " ".join(str(exc).split()) or type(exc).__name__)
    if code in (_errno.ENOSPC, getattr(_errno, "EDQUOT", -1)) and "space" not in reason.lower():
        reason += ": the disk is full"
    return WriteError(f"{path}: {verb} ({reason}); nothing was written there")


def name_inputs(message: str, names: Mapping[str, str]) -> str:
    """`message` with its {input} placeholders replaced by `names` (for text that is not an
    exception, e.g. a warning)."""
    return _PLACEHOLDER.sub(lambda m: names.get(m.group(1), m.group(1)), message)


__all__ = ["InputProblem", "INPUTS", "WriteError", "name_inputs", "write_failure"]
