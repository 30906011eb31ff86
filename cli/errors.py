"""How the CLI reports a bad input: one line on stderr, a non-zero exit, no traceback.

The library raises its own error classes for bad inputs (:class:`CameraError`, :class:`PlyError`,
:class:`ImageError`, :class:`DatasetError`, ...), each with a message that names the file and the
field. :func:`user_errors` turns exactly those into :class:`click.ClickException` (``Error: ...``,
exit code 1), and so is an :class:`OSError` that names a file (permission denied, disk full).
Any other exception is a bug and keeps its traceback.

Nothing here imports the library at import time (``nehad --help`` stays fast, and a module that
was never imported cannot have raised): the classes are looked up in ``sys.modules`` when an
exception arrives.
"""

from __future__ import annotations

import contextlib
import sys

import click

# (module, class) pairs whose exceptions are a user's bad input, not a bug. Other engineers add
# theirs here (ONNX model errors, training config errors, ...).
USER_ERROR_CLASSES = (
    ("nehad.runtime.cameras", "CameraError"),
    ("nehad.runtime.ply", "PlyError"),
    ("nehad.runtime.images", "ImageError"),
    ("nehad.data.dnerf", "DatasetError"),
    ("nehad.cli.errors", "InputError"),
    ("nehad.configtools", "ConfigError"),
    ("nehad.trainer", "RunError"),
    ("nehad.metrics.lpips", "LpipsWeightsMissing"),
    ("nehad.runtime.onnx_model", "OnnxModelError"),
    ("nehad.export.onnx_export", "ExportError"),
    ("nehad.viz", "VizError"),
    ("nehad.runtime.splat", "SplatError"),
    ("nehad.runtime.paths", "PathError"),
    ("nehad.runtime.video", "VideoError"),
    ("nehad.runtime.batch", "BatchError"),
    ("nehad.runtime.distribute", "RenderError"),
    ("nehad.runtime.layers", "LayerError"),
)


class InputError(ValueError):
    """A bad command-line input found by the CLI itself (the message names it)."""


def _user_error_types() -> tuple[type, ...]:
    types = []
    for module, name in USER_ERROR_CLASSES:
        mod = sys.modules.get(module)
        cls = getattr(mod, name, None) if mod is not None else None
        if isinstance(cls, type):
            types.append(cls)
    return tuple(types)


def _one_line(message: str) -> str:
    return " ".join(str(message).split()) or "invalid input"


@contextlib.contextmanager
def user_errors():
    """Map the project's bad-input exceptions raised inside the block to ClickException."""
    try:
        yield
    except click.ClickException:
        raise
    except Exception as e:
        if isinstance(e, _user_error_types()):
            raise click.ClickException(_one_line(e)) from None
        if isinstance(e, OSError) and e.filename is not None:
            # the system refused a named file (permission denied, disk full, ...): not a bug
            raise click.ClickException(_one_line(f"{e.filename}: {e.strerror or e}")) from None
        raise
