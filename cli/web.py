"""`nehad web SOURCE -o DIR`: a static folder that plays the scene in any browser (docs/web.md);
parses, exports a run folder first when given one (torch), then calls runtime/web.py."""

from __future__ import annotations

import tempfile
from pathlib import Path

import click

from .errors import InputError, user_errors


@click.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="The folder to write (new or empty; written whole or not at all).")
@click.option("--cameras", "cameras_file", default=None, metavar="FILE",
              help="Cameras the page can jump to (a transforms file or a camera list); "
                   "default: a run's test cameras, else the model's own camera.")
@click.option("--lod", is_flag=True,
              help="For a run trained with --lod-levels: export its streaming layers; the page "
                   "offers each level of detail (a split-layer folder as SOURCE does the same).")
@click.option("--fp16-weights", is_flag=True,
              help="For a run folder: store the deformation field's weights as float16 (a "
                   "smaller download; the export checks parity against the rounded model).")
def web(source, output, cameras_file, lod, fp16_weights):
    """Write a folder that plays SOURCE in a web browser with no server behind it.

    SOURCE is an exported .onnx (`nehad export`), a split-layer folder (`nehad export
    --split-layers`) or a training run folder (exported here; needs torch). The folder holds
    index.html, a small player (WebGL2 splats; the deformation field evaluated by
    onnxruntime-web in wasm), the model and the libraries: serve it with any static file server
    (`python -m http.server -d DIR`, an object store, a static site host) and open index.html.
    The libraries come from runtime/web/node_modules (fetched once: npm ci --prefix
    runtime/web).
    """
    with user_errors():
        from nehad.runtime.web import build_player, check_libraries

        check_libraries()  # before any export: a missing library is said at once
        cameras = _cameras(cameras_file)
        if (source / "model.pt").is_file():
            with tempfile.TemporaryDirectory(prefix="nehad-web-") as tmp:
                model, run_cameras = _export_run(source, Path(tmp), lod, fp16_weights)
                report = build_player(model, output, cameras or run_cameras)
        else:
            if lod or fp16_weights:
                raise InputError(f"{source}: --lod and --fp16-weights apply to a run folder; "
                                 f"an exported model is played as it was exported")
            report = build_player(source, output, cameras)
    lib = sum(v for k, v in report.files.items() if k.startswith("ort/"))
    click.echo(f"{report.folder}: {report.gaussians} Gaussians, {report.cameras} camera(s)"
               f"{f', {report.layers} layers' if report.layers else ''}; "
               f"{report.total_bytes / 1e6:.1f} MB ({lib / 1e6:.1f} MB of libraries)")
    click.echo(f"serve it with: python -m http.server -d {report.folder}  "
               f"(then open http://127.0.0.1:8000/)")


def _cameras(cameras_file):
    if cameras_file is None:
        return []
    from nehad.runtime.cameras import load_view

    cams = load_view(cameras_file)
    return cams if isinstance(cams, list) else [cams]


def _export_run(run: Path, tmp: Path, lod: bool, fp16: bool):
    """(the exported model file or split folder, the run's test cameras)."""
    from nehad.model import load_run
    from nehad.run_scene import dataset_test_cameras

    if lod:
        from nehad.export.layers import export_split_layers

        model = tmp / "layers"
        export_split_layers(run, model, fp16_field=fp16)
    else:
        from nehad.export.onnx_export import export_run

        model = tmp / "model.onnx"
        export_run(run, model, fp16_weights=fp16)
    _, info = load_run(run)
    return model, dataset_test_cameras(info.data_dir)


__all__ = ["web"]
