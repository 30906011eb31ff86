"""How the command line opens a SCENE argument: the runtime's one scene notion
(runtime/scene.py) with the training package's opener for run folders, and its warnings."""

from __future__ import annotations

import click

#: Scene openers the runtime cannot have itself (it never imports the training package): a
#: training run folder, drawn by its torch model (nehad/run_scene.py).
SCENE_OPENERS = ("nehad.run_scene:open_run",)


def open_cli_scene(path, lod: int | None = None, threads: int | None = None):
    """open_scene with the run opener; each problem found (a damaged layer chunk) is a warning
    on stderr."""
    from nehad.runtime.scene import open_scene

    scene = open_scene(path, lod=lod, threads=threads, openers=SCENE_OPENERS)
    for problem in scene.problems:
        click.echo(f"warning: {problem}", err=True)
    return scene


__all__ = ["open_cli_scene", "SCENE_OPENERS"]
