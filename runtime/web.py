"""`nehad web`: an exported scene as a static folder that plays in a browser with no server
behind it (docs/web.md).

The folder holds `index.html` and `player.js` (runtime/web/player: a WebGL2 splat shader that
follows the CPU rasterizer's semantics, and the controls), `scene.json` (cameras, time range,
background, the files to load), the model itself (one `model.onnx`, or a split-layer model's
`base.onnx` and `layer_K.bin` chunks), the onnxruntime-web files it needs (the ES module, its
wasm loader, and its wasm binary gzipped: the page inflates it with the browser's own
DecompressionStream) and `_headers`, the cross-origin isolation headers for the static hosts
that read such a file (with them the wasm runs multi-threaded). The libraries are copied from
`runtime/web/node_modules`, fetched once by `npm ci --prefix runtime/web` at the versions of
runtime/web/package-lock.json. The folder is written beside its destination and renamed into
place, so a failure writes nothing.
"""

from __future__ import annotations

import gzip
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputProblem, write_failure
from .tempfiles import temp_prefix

WEB_ROOT = Path(__file__).resolve().parent / "web"
PLAYER_FILES = ("index.html", "player.js")
ORT_DIST = WEB_ROOT / "node_modules" / "onnxruntime-web" / "dist"
#: what the page loads from onnxruntime-web: the ES module, its wasm loader, its wasm binary
ORT_FILES = ("ort.wasm.min.mjs", "ort-wasm-simd-threaded.mjs", "ort-wasm-simd-threaded.wasm")
FETCH_COMMAND = f"npm ci --prefix {WEB_ROOT}"
HEADERS = """/*
  Cross-Origin-Opener-Policy: same-origin
  Cross-Origin-Embedder-Policy: require-corp
"""
_URL = re.compile(rb"https?://[A-Za-z0-9._~:/?#\[\]@!$&'()*+,;=%-]+")


class WebError(InputProblem):
    """A web player folder cannot be written as asked (names the input)."""


@dataclass
class WebReport:
    folder: Path
    files: dict  # name -> bytes
    gaussians: int
    cameras: int
    layers: int

    @property
    def total_bytes(self) -> int:
        return sum(self.files.values())


def check_libraries() -> None:
    missing = [name for name in ORT_FILES if not (ORT_DIST / name).is_file()]
    if missing:
        raise WebError(f"the web player's libraries are missing ({', '.join(missing)} of "
                       f"onnxruntime-web); fetch them once with: {FETCH_COMMAND}")


def _check_destination(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise WebError(f"-o {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise WebError(f"-o {out}: the folder exists and is not empty (choose a new one)")
    if not out.parent.is_dir():
        raise WebError(f"-o {out}: parent folder {out.parent} does not exist")


def camera_entry(cam, name: str = "") -> dict:
    """A camera as scene.json holds it: intrinsics and world_to_camera (OpenCV axes, row-major)."""
    w2c = np.asarray(cam.world_to_camera, np.float64)
    return {"name": name or cam.name or "", "width": int(cam.width), "height": int(cam.height),
            "fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
            "world_to_camera": [[float(v) for v in row] for row in w2c]}


def _model_source(source: Path):
    """(ModelInfo of the graph to load, its file, the split folder's manifest or None)."""
    from .onnx_model import OnnxModelError, read_model_info

    try:
        if source.is_dir():
            from .layers import LayerError, read_manifest

            try:
                manifest = read_manifest(source)
            except LayerError as e:
                raise WebError(f"{source}: not a split-layer model folder ({e})") from None
            base = source / manifest["layers"][0]["file"]
            return read_model_info(base), base, manifest
        return read_model_info(source), source, None
    except OnnxModelError as e:
        raise WebError(str(e)) from None


def _copy_libraries(ort_dir: Path) -> None:
    """The onnxruntime-web files, the wasm gzipped. The URLs in their messages (a guide on
    cross-origin isolation) are written as plain text, so no file of the folder names an
    outside address."""
    ort_dir.mkdir()
    for name in ORT_FILES:
        data = (ORT_DIST / name).read_bytes()
        if name.endswith(".wasm"):
            (ort_dir / f"{name}.gz").write_bytes(gzip.compress(data, 9, mtime=0))
            continue
        data = _URL.sub(lambda m: m.group(0).split(b"://", 1)[1].replace(b"/", b" "), data)
        (ort_dir / name).write_bytes(data)


def _web_base(path: Path) -> bytes:
    """A split-layer base model whose enhancement-layer slots (`extra_*`, overridable
    initializers in the export, runtime/layers.py) are plain graph inputs: onnxruntime-web feeds
    graph inputs only. The graph is otherwise byte for byte the export's."""
    from .layers import CHUNK_ARRAYS, EXTRA_LAYER, EXTRA_PREFIX
    from .onnx_proto import initializers_as_inputs

    names = [EXTRA_PREFIX + n for n in CHUNK_ARRAYS] + [EXTRA_LAYER]
    return initializers_as_inputs(path.read_bytes(), names)


def _scene_json(info, model_name: str, manifest, cameras: list) -> dict:
    aabb = np.asarray(info.aabb, np.float64).reshape(2, 3)
    entries = [camera_entry(c, getattr(c, "name", "") or f"camera {i}")
               for i, c in enumerate(cameras)]
    layers = None
    if manifest is not None:
        layers = [{"file": e["file"], "gaussians": int(e["gaussians"])}
                  for e in manifest["layers"][1:]]
    return {
        "format": "nehad-web/1", "model": model_name, "sh_degree": int(info.sh_degree),
        "num_gaussians": int(info.num_gaussians),
        "static_gaussians": info.static_gaussians,
        "time_range": [float(v) for v in info.time_range],
        "background": [float(v) for v in info.background],
        "cameras": entries, "default_camera": 0,
        "target": [float(v) for v in aabb.mean(0)], "layers": layers,
    }


def build_player(source, out, cameras=None) -> WebReport:
    """Write the player folder `out` for `source` (an exported .onnx file or a split-layer
    folder). `cameras`: the runtime Cameras to offer (default: the model's default camera)."""
    source, out = Path(source), Path(out)
    check_libraries()
    _check_destination(out)
    info, graph_file, manifest = _model_source(source)
    cams = list(cameras or [])
    if not cams:
        if info.default_camera is None:
            raise WebError(f"{source}: the model has no default camera; give --cameras FILE")
        cams = [info.default_camera]
    try:
        work = Path(tempfile.mkdtemp(prefix=temp_prefix(out), suffix=".tmp", dir=out.parent))
    except OSError as e:  # the folder is staged beside `out`: name `out`, not the stage
        raise write_failure(out, e, f"cannot create a folder in {out.parent}") from None
    try:
        umask = os.umask(0)
        os.umask(umask)
        work.chmod(0o777 & ~umask)  # mkdtemp's 0700 would hide the folder from a web server
        for name in PLAYER_FILES:
            shutil.copyfile(WEB_ROOT / "player" / name, work / name)
        _copy_libraries(work / "ort")
        if manifest is None:
            model_name = "model.onnx"
            shutil.copyfile(graph_file, work / model_name)
        else:
            model_name = manifest["layers"][0]["file"]
            for entry in manifest["layers"][1:]:
                shutil.copyfile(source / entry["file"], work / entry["file"])
            (work / model_name).write_bytes(_web_base(graph_file))
        scene = _scene_json(info, model_name, manifest, cams)
        (work / "scene.json").write_text(json.dumps(scene, indent=1) + "\n")
        (work / "_headers").write_text(HEADERS)
        if out.is_dir():
            out.rmdir()  # empty (checked above)
        work.rename(out)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    files = {str(p.relative_to(out)): p.stat().st_size for p in sorted(out.rglob("*"))
             if p.is_file()}
    return WebReport(out, files, int(info.num_gaussians), len(cams),
                     0 if manifest is None else len(manifest["layers"]))


__all__ = ["FETCH_COMMAND", "WebError", "WebReport", "build_player", "camera_entry",
           "check_libraries"]
