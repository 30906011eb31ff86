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

import sys

import click

from nehad import __version__

from .batch import batch
from .model import export_, info
from .render import ply, render
from .synth import synth
from .threads import apply_thread_defaults
from .train import demo, eval_, train
from .video import video
from .view import view
from .viz import report, viz


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "-V", "--version", prog_name="nehad")
def main():
    """NeHaD: dynamic 3D Gaussian splatting, trained and rendered on the CPU.

    \b
    Quickstart:
      nehad synth demo_scene
      nehad render demo_scene/gaussians.ply --view demo_scene/transforms_test.json:0 \\
          -o render.png --background 1,1,1
    """


for _command in (synth, train, eval_, demo, export_, info, render, ply, video, batch, view, viz,
                 report):
    main.add_command(_command)


def entry(prog_name: str | None = None) -> None:
    """The `nehad` executable: thread counts for the load the machine has now (they must be in
    the environment before torch or numba load; see nehad/cli/threads.py), then the commands.
    Tests call :func:`main` directly and keep their own environment."""
    args = sys.argv[1:]
    if args and not set(args) & {"-h", "--help", "-V", "--version"}:
        # silent: a bad input must still end in exactly one `Error:` line
        apply_thread_defaults()
    main(prog_name=prog_name)


if __name__ == "__main__":  # python -m nehad.cli.main
    entry(prog_name="nehad")
