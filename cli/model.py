"""`nehad export` and `nehad info`: a trained run to one self-contained ONNX file (or split
streaming layers), and what such a file holds (docs/design.md, "The exported file")."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .errors import InputError, user_errors


@click.command("export")
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="The .onnx file to write (atomically; only after the checks pass).")
@click.option("--opset", type=int, default=17, show_default=True,
              help="ONNX opset (17..20).")
@click.option("--fp16-weights", is_flag=True,
              help="Store the weights as float16 (a smaller file); the torch model is rounded "
                   "the same way for the parity check. With --split-layers: the field's weights "
                   "only (the Gaussians of every layer stay float32).")
@click.option("--split-layers", "split_dir", default=None,
              type=click.Path(file_okay=False, path_type=Path),
              help="For a run trained with --lod-levels: write DIR/base.onnx (field + layer 0), "
                   "DIR/layer_K.bin per enhancement layer and DIR/manifest.json (sizes, "
                   "sha256) for streaming (docs/streaming.md). With or instead of -o.")
@click.option("--parts", type=click.IntRange(1, 64), default=4, show_default=True,
              help="Cut the Gaussians into up to this many parts that the runtime deforms side "
                   "by side, one per core (fewer when a part would hold under 2048 moving "
                   "Gaussians); 1: one part. The file's main outputs are the same either way. "
                   "For -o only (a --split-layers base is one part).")
def export_(run, output, opset, fp16_weights, split_dir, parts):
    """Export the trained RUN to one self-contained ONNX file (format nehad-onnx/1).

    The graph maps an input `time` [1] to the activated Gaussians (means, scales, quats,
    opacities, sh; and `layer` for a run trained with streaming layers) and uses only standard
    ONNX operators. Before writing, it is checked with onnx.checker (full_check) and against the
    torch model at several times (1e-5). Needs torch.
    """
    if output is None and split_dir is None:
        raise click.UsageError("give -o MODEL.onnx, --split-layers DIR, or both")
    with user_errors():
        if split_dir is not None:
            _export_split(run, split_dir, opset, fp16_weights)
        if output is None:
            return
        if output.suffix.lower() != ".onnx":
            raise InputError(f"-o {output}: the model file must end in .onnx")
        if not output.parent.is_dir():
            raise InputError(f"-o {output}: output folder {output.parent} does not exist")
        if output.is_dir():
            raise InputError(f"-o {output}: is a folder")
        from nehad.runtime.outputs import check_outputs

        check_outputs([("-o", output)], [("RUN", run)])
        if not (run / "model.pt").is_file():
            raise InputError(f"{run}: not a finished training run (no model.pt)")
        from nehad.export.onnx_export import MAX_OPSET, export_run

        if not 17 <= opset <= MAX_OPSET:
            raise InputError(f"--opset {opset}: supported opsets are 17..{MAX_OPSET}")
        rep = export_run(run, output, opset=opset, fp16_weights=fp16_weights, parts=parts)
    worst = max(rep.parity.values()) if rep.parity else 0.0
    click.echo(f"{output}: {rep.num_gaussians} Gaussians, SH degree {rep.sh_degree}, opset "
               f"{rep.opset}, {rep.file_size / 1e6:.2f} MB, {sum(rep.operators.values())} nodes "
               f"({len(rep.operators)} operator types); parity vs torch {worst:.2g}; "
               f"exported in {rep.seconds:.1f} s")
    if rep.num_static:
        dev = rep.static_deviation
        click.echo(f"  {rep.num_static} of {rep.num_gaussians} Gaussians do not move (at most "
                   f"{dev.get('position', 0):.1e} of the extent over time): written "
                   f"pre-deformed, the field runs on the other {rep.num_gaussians - rep.num_static}")
    if "parts" in rep.metadata:
        k = len(json.loads(rep.metadata["parts"])) - 1
        click.echo(f"  {k} parts, deformed side by side by the runtime (--parts)")


def _export_split(run: Path, folder: Path, opset: int, fp16_field: bool = False) -> None:
    """`nehad export --split-layers`: base model, chunks and manifest (docs/design.md section 8)."""
    if not (run / "model.pt").is_file():
        raise InputError(f"{run}: not a finished training run (no model.pt)")
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--split-layers {folder}: exists and is not a folder")
    if not folder.parent.is_dir():
        raise InputError(f"--split-layers {folder}: parent folder {folder.parent} does not exist")
    from nehad.export.layers import export_split_layers

    rep = export_split_layers(run, folder, opset=opset, fp16_field=fp16_field)
    worst = max(rep.parity.values()) if rep.parity else 0.0
    click.echo(f"{folder}/: {len(rep.manifest['layers'])} layers, parity vs torch {worst:.2g} "
               f"(every prefix), field {rep.manifest['field_bytes'] / 1e6:.2f} MB"
               f"{' (float16)' if fp16_field else ''}, exported in {rep.seconds:.1f} s")
    for e in rep.manifest["layers"]:
        click.echo(f"  layer {e['layer']}: {e['file']:<12} {e['gaussians']:>8} Gaussians "
                   f"{e['bytes']:>11} bytes  (layers 0..{e['layer']}: "
                   f"{e['cumulative_bytes']} bytes)")


@click.command()
@click.argument("model", type=click.Path(dir_okay=False, path_type=Path))
def info(model):
    """Describe an exported MODEL (.onnx): Gaussians, SH degree, time range, bounds, opset,
    operators used and file size, after checking the file against the digest of its graph
    written at export (a damaged file is refused) and loading it in onnxruntime as `render`
    does (a file `render` refuses is refused here too). Needs neither torch nor onnx."""
    with user_errors():
        from nehad.runtime.onnx_model import OnnxModel

        i = OnnxModel(model, threads=1).info
        layers, static = i.layer_counts, i.static_gaussians  # the checks `render` makes
    md = i.metadata
    lo, hi = i.time_range
    click.echo(f"{model}: {md['format']}")
    click.echo(f"  Gaussians:    {i.num_gaussians}")
    click.echo(f"  SH degree:    {i.sh_degree}")
    click.echo(f"  time range:   [{lo:g}, {hi:g}]")
    click.echo(f"  bounds:       min {_fmt3(i.aabb[0])}  max {_fmt3(i.aabb[1])}")
    click.echo(f"  background:   {_fmt3(i.background)}")
    if i.default_camera is not None:
        c = i.default_camera
        click.echo(f"  camera:       {c.width}x{c.height}{f' ({c.name})' if c.name else ''}")
    if "lod_layers" in md:  # docs/design.md section 8 streaming layers (Gaussians per layer)
        split = (" (split: this file holds layer 0; chunks add the rest)"
                 if md.get("lod_split") == "1" else "")
        click.echo(f"  layers:       {layers}{split}")
    if "static_gaussians" in md:  # nehad.export.static_split
        click.echo(f"  static:       {static} of {i.num_gaussians} Gaussians "
                   f"written pre-deformed (the field runs on the others)")
    if "parts" in md:  # docs/design.md section 7: rows deformed side by side
        bounds = json.loads(md["parts"])
        click.echo(f"  parts:        {len(bounds) - 1} (rows {md['parts']}), deformed side by "
                   f"side, one per thread")
    for key, label in (("decoder", "decoder"), ("config_hash", "config hash"),
                       ("nehad_version", "exported by"), ("fp16_weights", "fp16 weights")):
        if key in md:
            click.echo(f"  {label + ':':<13} {md[key]}")
    click.echo(f"  opset:        {i.opset}")
    click.echo(f"  file size:    {i.file_size} bytes ({i.file_size / 1e6:.2f} MB)")
    if i.digest_checked:
        click.echo(f"  integrity:    graph sha256 {md['graph_sha256'][:16]}... matches the file")
    else:
        click.echo("  integrity:    no digest (exported before nehad wrote one); not checked")
    ops = sorted(i.operators.items(), key=lambda kv: (-kv[1], kv[0]))
    click.echo(f"  operators:    {sum(i.operators.values())} nodes, {len(ops)} types")
    for k in range(0, len(ops), 6):
        click.echo("    " + "  ".join(f"{op} {n}" for op, n in ops[k:k + 6]))


def _fmt3(v) -> str:
    return ",".join(f"{float(x):.4g}" for x in v)


__all__ = ["export_", "info"]
