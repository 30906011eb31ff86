"""The `nehad` command line: thin commands that parse, validate and call the library
(docs/design.md, "Layout"). This file only registers them; each family lives in its own file:
synth.py, train.py (train, eval, demo), model.py (export, info), render.py (render, ply),
video.py, batch.py, view.py and viz.py (viz, report).

Import cost matters: ``nehad --help`` must not load numpy/numba, and nothing here may import
torch (the runtime works without it). Library modules are imported inside the commands.

Bad inputs end with a one-line ``Error: ...`` naming the input and a non-zero exit, never a
traceback, and leave no output file behind (see :mod:`nehad.cli.errors`).
"""

from __future__ import annotations

import os
import sys

import click

from nehad import __version__

from .batch import batch
from .model import export_, info
from .prepare import prepare
from .render import ply, render
from .synth import synth
from .threads import apply_thread_defaults
from .train import demo, eval_, train
from .video import video
from .view import view
from .viz import report, viz
from .web import web


class _OneLineUsageError(click.UsageError):
    """A usage error (a bad option value, a missing argument) shown as the one `Error:` line
    every bad input ends in, where to read more in the same line (click's own shows the usage
    and a hint on two lines before it)."""

    def show(self, file=None) -> None:
        where = f" (see '{self.ctx.command_path} --help')" if self.ctx is not None else ""
        click.echo(f"Error: {self.message}{where}", err=True)


#: click's "no arguments: here is the help" (a UsageError since click 8.2): shown as click shows it
_HELP_ERRORS = tuple(getattr(click.exceptions, name) for name in ("NoArgsIsHelpError",)
                     if hasattr(click.exceptions, name))


def _one_line(e: click.UsageError) -> click.UsageError:
    if isinstance(e, (_OneLineUsageError,) + _HELP_ERRORS):
        return e
    return _OneLineUsageError(e.format_message(), e.ctx)


class _Commands(click.Group):
    """The command group; it refuses an argument that is not valid UTF-8 before any command
    runs (issue 26), and shows usage errors on one line (`_OneLineUsageError`)."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.UsageError as e:
            raise _one_line(e) from None

    def parse_args(self, ctx, args):
        for arg in args:
            if isinstance(arg, str) and _not_utf8(arg):
                # Python keeps such bytes as lone surrogates (PEP 383); OpenImageIO, PyAV and
                # onnxruntime take UTF-8 strings only, and would fail deep inside a write
                raise click.ClickException(
                    f"{os.fsencode(arg)!r}: not valid UTF-8 (a file name in another encoding?); "
                    f"nehad takes UTF-8 arguments only: rename the file or folder")
        return super().parse_args(ctx, args)

    def invoke(self, ctx):
        """Ctrl-C in a command without its own message (train, video, batch and view have
        theirs): one line, exit status 130, no traceback and no "Aborted!"."""
        from .errors import interrupted

        try:
            return super().invoke(ctx)
        except click.UsageError as e:  # a subcommand's options, or one it raised itself
            raise _one_line(e) from None
        except Exception as e:
            if not interrupted(e):  # e.g. SystemError wrapping a KeyboardInterrupt
                raise
            _interrupted(ctx)
        except KeyboardInterrupt:
            _interrupted(ctx)


def _interrupted(ctx) -> None:
    from nehad.runtime.interrupts import exit_interrupted

    command = " ".join(["nehad", ctx.invoked_subcommand or ""]).strip()
    click.echo(f"interrupted: {command} stopped before it finished; every file is written whole "
               f"or not at all, so nothing partial is left", err=True)
    exit_interrupted(130)


def _not_utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "-V", "--version", prog_name="nehad")
def main():
    """NeHaD: dynamic 3D Gaussian splatting, trained and rendered on the CPU.

    \b
    Quickstart:
      nehad synth demo_scene
      nehad render demo_scene/gaussians.ply --view demo_scene/transforms_test.json:0 \\
          -o render.png --background 1,1,1
    """


for _command in (synth, prepare, train, eval_, demo, export_, info, render, ply, video, batch, view, web,
                 viz, report):
    main.add_command(_command)


def _stack_dumps_on_sigusr1() -> None:
    """``kill -USR1 PID`` prints every thread's Python stack to stderr (faulthandler) and the
    process goes on: a command that seems hung says where it is (the tests send it before they
    kill a process that did not end)."""
    import faulthandler
    import signal

    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)


def entry(prog_name: str | None = None) -> None:
    """The `nehad` executable: thread counts for the load the machine has now (they must be in
    the environment before torch or numba load; see nehad/cli/threads.py), then the commands.
    Tests call :func:`main` directly and keep their own environment."""
    from nehad.runtime import interrupts

    _stack_dumps_on_sigusr1()
    interrupts.install()  # Ctrl-C: safe points, a second one ends at once, a bounded exit
    args = sys.argv[1:]
    if args and not set(args) & {"-h", "--help", "-V", "--version"}:
        # silent: a bad input must still end in exactly one `Error:` line
        apply_thread_defaults()
    main(prog_name=prog_name)


if __name__ == "__main__":  # python -m nehad.cli.main
    entry(prog_name="nehad")
