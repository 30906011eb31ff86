"""`nehad view SCENE`: look at a scene in the browser with a time slider (docs/view.md);
parses, opens the scene, starts runtime/viewer.py and waits."""

from __future__ import annotations

from pathlib import Path

import click

from .errors import user_errors
from .params import BACKGROUND
from .scenes import open_cli_scene


@click.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on (0.0.0.0: every interface; the page has no login).")
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="Port to listen on (0: any free port).")
@click.option("--mode", type=click.Choice(["server", "browser"]), default="server",
              show_default=True,
              help="Who draws: server (nehad's CPU rasterizer, what `nehad render` writes) or "
                   "browser (WebGL splats, base colour only); switchable in the page.")
@click.option("--cameras", "cameras_file", default=None, metavar="FILE",
              help="Cameras the page can jump to (a transforms file or a camera list); "
                   "default: a run's test cameras, else the model's own camera.")
@click.option("--lod", type=click.IntRange(min=0), default=None, metavar="K",
              help="Start with streaming layers 0..K (every layer count is offered in the page).")
@click.option("--background", type=BACKGROUND, default=None, metavar="R,G,B",
              help="Background colour (default: the scene's).")
@click.option("--threads", type=click.IntRange(min=1), default=None,
              help="onnxruntime threads for the deformation (default: its own).")
def view(scene, host, port, mode, cameras_file, lod, background, threads):
    """Look at SCENE in the browser: orbit, pan and zoom with the mouse, scrub or play time,
    jump to the dataset cameras, change layers and background.

    SCENE is anything `nehad render` takes (an exported .onnx, a split layers folder, a
    training run folder, a static 3DGS .ply). The page is served on --host:--port; open the
    address printed. Ctrl-C stops the server.
    """
    import time

    with user_errors():
        from nehad.runtime.viewer import Viewer, check_port

        check_port(host, port)  # before the scene loads: a port in use is said at once
        first = open_cli_scene(scene, lod=lod, threads=threads)
        scenes = {lod: first}
        if first.num_layers > 1:
            for k in range(first.num_layers):
                if k != lod:
                    scenes[k] = open_cli_scene(scene, lod=k, threads=threads)
            if lod is not None:
                scenes[None] = open_cli_scene(scene, threads=threads)
        cameras = _cameras(first, cameras_file)
        viewer = Viewer(scenes, cameras, mode, background, host, port)
        address = viewer.start()
    try:  # from here on Ctrl-C stops the server, also while the address is printed
        click.echo(f"nehad view: {first.describe()}; {len(cameras)} camera(s) to jump to")
        click.echo(f"open {address} in a browser (Ctrl-C stops the server)")
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        from nehad.runtime.interrupts import exit_interrupted

        viewer.stop()
        click.echo("stopped", err=True)
        exit_interrupted(0)  # the server's threads are stopped; no teardown wait


def _cameras(scene, cameras_file):
    """--cameras, else the cameras the scene comes with (runtime/scene.py, Scene.cameras)."""
    if cameras_file is None:
        return scene.cameras()
    from nehad.runtime.cameras import load_view

    cams = load_view(cameras_file)
    return cams if isinstance(cams, list) else [cams]


__all__ = ["view"]
