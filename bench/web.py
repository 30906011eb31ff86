"""`nehad web`'s player in headless Chromium beside `nehad render` (docs/web.md).

    python bench/web.py MODEL.onnx --cameras CAMS [--camera K] [--frames 20] [--times 0.1,0.5,0.9]

Builds the player folder for MODEL (runtime/web.py) in a temporary folder, serves it on
127.0.0.1 with python's static file server, opens it in headless Chromium (SwiftShader WebGL2,
the CPU-only machine's GL; onnxruntime-web in wasm, one thread: python's server sends no
cross-origin isolation headers; with --isolated it sends them and the wasm runs threaded) and
prints:

* the page's load time (navigation to the first frame drawn: libraries, model, session, the
  first deformation and draw);
* per frame at a new time each (what playing does): the deformation in wasm, the drawing
  (sort, colours, WebGL), and whole frames per second;
* the same for `nehad render` in this process (onnxruntime + the Numba rasterizer, the
  machine's threads), the figure beside it;
* at each of --times, the page's picture of camera K against `nehad render`'s at that time and
  at the other times (PSNR, dB): the page must be closest to its own time.

Prints the load average before and after; time it alone.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def load_average() -> str:
    try:
        return "%.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "n/a"


def page_figures(browser, url, frames: int, times, camera: int) -> dict:
    from test_web import open_player, show

    start = time.perf_counter()
    open_player(browser, url)
    load_s = time.perf_counter() - start
    error = browser.evaluate("window.nehad.error")
    if error:
        sys.exit(f"the page failed: {error}")
    deform, draw, walls = [], [], []
    for i in range(frames):
        t = (i + 0.5) / frames
        t0 = time.perf_counter()
        res = browser.call("Runtime.evaluate", awaitPromise=True, returnByValue=True,
                           expression=f"window.nehad.show({t}, {camera}).then(s => "
                                      f"JSON.stringify([s, window.nehad.player.deformMs.at(-1), "
                                      f"window.nehad.player.drawMs.at(-1)]))")
        walls.append(time.perf_counter() - t0)
        _, d, g = json.loads(res["result"]["value"])
        deform.append(d)
        draw.append(g)
    pictures = [show(browser, t, camera) for t in times]
    return {"load_s": load_s, "deform_ms": float(np.median(deform)),
            "draw_ms": float(np.median(draw)), "fps": 1.0 / float(np.median(walls)),
            "pictures": pictures,
            "mode": browser.evaluate("window.nehad.stats.mode")}


def render_figures(model, cam, frames: int, times) -> dict:
    from nehad.runtime.onnx_model import OnnxModel
    from nehad.runtime.raster import render

    m = OnnxModel(model, cache_size=1)
    render(m.gaussians(0.0), cam, m.background)  # JIT, not timed
    deform, raster, walls = [], [], []
    for i in range(frames):
        t = (i + 0.5) / frames
        t0 = time.perf_counter()
        g = m.gaussians(t)
        t1 = time.perf_counter()
        render(g, cam, m.background)
        t2 = time.perf_counter()
        deform.append(t1 - t0)
        raster.append(t2 - t1)
        walls.append(t2 - t0)
    refs = [np.clip(render(m.gaussians(t), cam, m.background).rgb, 0, 1) for t in times]
    return {"deform_ms": 1e3 * float(np.median(deform)), "draw_ms": 1e3 * float(np.median(raster)),
            "fps": 1.0 / float(np.median(walls)), "pictures": refs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", type=Path, help="an exported .onnx")
    ap.add_argument("--cameras", required=True, help="the cameras to offer (a transforms file)")
    ap.add_argument("--camera", type=int, default=0, help="the camera to time and compare")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--times", default="0.1,0.5,0.9")
    ap.add_argument("--isolated", action="store_true",
                    help="serve with the cross-origin isolation headers (the wasm then runs on "
                         "several threads, as on a host that reads the folder's _headers)")
    args = ap.parse_args()

    from browser import Browser
    from test_web import psnr, serve

    from nehad.runtime.cameras import load_view
    from nehad.runtime.web import build_player

    times = [float(v) for v in args.times.split(",")]
    cams = load_view(args.cameras)
    cams = cams if isinstance(cams, list) else [cams]
    cam = cams[args.camera]
    print(f"load average before: {load_average()}")
    with tempfile.TemporaryDirectory() as tmp:
        rep = build_player(args.model, Path(tmp) / "site", cams)
        lib = sum(v for k, v in rep.files.items() if k.startswith("ort/"))
        print(f"folder: {rep.total_bytes / 1e6:.1f} MB ({lib / 1e6:.1f} MB of libraries, model "
              f"{rep.files.get('model.onnx', 0) / 1e6:.1f} MB), {rep.gaussians} Gaussians, "
              f"camera {args.camera}: {cam.width}x{cam.height}")
        browser = Browser(max(cam.width, 800), max(cam.height, 600) + 100)
        try:
            with serve(rep.folder, isolated=args.isolated) as url:
                page = page_figures(browser, url, args.frames, times, args.camera)
        finally:
            browser.close()
    ref = render_figures(args.model, cam, args.frames, times)
    print(f"page ({page['mode']}): load {page['load_s']:.2f} s")
    print("| | deformation ms | drawing ms | frames/s |\n|---|---|---|---|")
    print(f"| browser (onnxruntime-web wasm, SwiftShader WebGL2) | {page['deform_ms']:.1f} | "
          f"{page['draw_ms']:.1f} | {page['fps']:.1f} |")
    print(f"| nehad render (onnxruntime, Numba rasterizer) | {ref['deform_ms']:.1f} | "
          f"{ref['draw_ms']:.1f} | {ref['fps']:.1f} |")
    ok = True
    for i, (t, got) in enumerate(zip(times, page["pictures"])):
        scores = [psnr(got, r) for r in ref["pictures"]]
        own = scores[i] >= 30.0 and scores[i] == max(scores)
        ok &= own
        print(f"t = {t:g}: page vs nehad render at t = {times}: "
              f"{' / '.join(f'{s:.1f}' for s in scores)} dB {'ok' if own else 'FAILED'}")
    print(f"load average after: {load_average()}")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
