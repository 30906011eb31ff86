"""How the CLI reports a bad input: one line on stderr, a non-zero exit, no traceback.

The runtime raises :class:`nehad.runtime.errors.InputProblem` (and its subclasses) for bad
inputs, with messages that name inputs as ``{time}``, ``{lod}``, ...: they are shown here as the
options (:data:`OPTION_NAMES`). The training package has its own (:class:`DatasetError`,
:class:`ConfigError`, ...). :func:`user_errors` turns exactly those into
:class:`click.ClickException` (``Error: ...``, exit code 1), and so is an :class:`OSError` that
names a file (permission denied, disk full).
An :class:`ImportError` of a package of the training extra (torch, onnx) is a runtime-only install
(docs/design.md section 2), not a bug: one line names the command, the missing package and the extra to
install. Any other exception is a bug and keeps its traceback.

Nothing here imports the library at import time (``nehad --help`` stays fast, and a module that
was never imported cannot have raised): the classes are looked up in ``sys.modules`` when an
exception arrives.
"""

from __future__ import annotations

import contextlib
import errno
import sys

import click

# (module, class) pairs whose exceptions are a user's bad input, not a bug. Other engineers add
# theirs here (ONNX model errors, training config errors, ...).
USER_ERROR_CLASSES = (
    ("nehad.runtime.errors", "InputProblem"),  # every runtime input error (runtime/errors.py)
    ("nehad.data.dnerf", "DatasetError"),
    ("nehad.data.capture_inputs", "PrepareError"),  # nehad prepare (a DatasetError too)
    ("nehad.cli.errors", "InputError"),
    ("nehad.configtools", "ConfigError"),
    ("nehad.checkpoint", "RunError"),
    ("nehad.metrics.lpips", "LpipsWeightsMissing"),
    ("nehad.export.onnx_export", "ExportError"),
    ("nehad.viz", "VizError"),
    ("nehad.checkpoint", "CheckpointError"),
)

#: How the command line calls the inputs a runtime message names as {input} (runtime/errors.py).
OPTION_NAMES = {
    "scene": "SCENE", "view": "--view", "time": "--time", "lod": "--lod", "output": "-o",
    "size": "--size", "background": "--background", "extrapolate": "--extrapolate",
    "path": "--path", "frames": "--frames", "frames_dir": "--frames-dir",
    "frame_format": "--frame-format", "fps": "--fps", "crf": "--crf", "encoder": "--encoder",
    "side_by_side": "--side-by-side", "threads": "--threads", "workers": "--workers",
    "scheduler": "--scheduler", "depth": "--depth", "alpha": "--alpha",
    "sh_degree": "--sh-degree", "format": "--format", "host": "--host", "port": "--port",
    "mode": "--mode", "cameras": "--cameras",
}

#: Top-level packages of the `train` extra (pyproject.toml) and how to install them.
TRAIN_EXTRA = ("torch", "onnx", "onnxscript")
TRAIN_INSTALL = "pip install -e '.[train]' torch==2.13.0"


#: errno values of a disk that refuses writes: full, over quota, file too large, read-only, I/O
_DISK_ERRNOS = frozenset(getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EIO")
                         if hasattr(errno, n))


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


def missing_extra(e: ImportError) -> str | None:
    """The package of the training extra whose import failed with `e`, or None.

    Either the import names it (``No module named 'torch'``), or the error was raised inside the
    package itself (an install that is broken, or blocked as in tests/torch_blocker.py)."""
    name = (getattr(e, "name", None) or "").split(".")[0]
    if name in TRAIN_EXTRA:
        return name
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is not None:
        parts = tb.tb_frame.f_code.co_filename.replace("\\", "/").split("/")
        for pkg in TRAIN_EXTRA:
            if pkg in parts[:-1]:
                return pkg
    return None


def _command() -> str:
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return "this command"
    return "nehad " + " ".join(ctx.command_path.split()[1:]) if " " in ctx.command_path else "nehad"


def interrupted(exc: BaseException) -> bool:
    """Whether `exc` is, or was caused by, a KeyboardInterrupt (its __cause__ / __context__
    chain)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


@contextlib.contextmanager
def user_errors():
    """Map the project's bad-input exceptions raised inside the block to ClickException."""
    try:
        yield
    except click.ClickException:
        raise
    except Exception as e:
        if interrupted(e):
            # Ctrl-C inside a Python callback of compiled code (numba's _numba_unpickle, a torch
            # hook) comes back wrapped, as a SystemError "returned a result with an exception
            # set": it is still the user's Ctrl-C, which the command answers (issue 26)
            raise KeyboardInterrupt from None
        if isinstance(e, _user_error_types()):
            text = e.message(OPTION_NAMES) if hasattr(e, "message") and callable(e.message) \
                else str(e)
            raise click.ClickException(_one_line(text)) from None
        if isinstance(e, ImportError) and (pkg := missing_extra(e)) is not None:
            raise click.ClickException(_one_line(
                f"{_command()} needs {pkg}, which cannot be imported here ({e}); install "
                f"the training extra: {TRAIN_INSTALL}")) from None
        if isinstance(e, OSError) and e.filename is not None:
            # the system refused a named file (permission denied, disk full, ...): not a bug
            raise click.ClickException(_one_line(f"{e.filename}: {e.strerror or e}")) from None
        if isinstance(e, OSError) and e.errno in _DISK_ERRNOS:
            # a writer that does not name its file (every writer of the project does: this
            # is the net under a library's own): still the disk, not a bug
            raise click.ClickException(_one_line(f"cannot write ({e.strerror or e})")) from None
        raise
