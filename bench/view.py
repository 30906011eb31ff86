"""`nehad view` in a headless Chromium: frame time in each drawing mode, and the time from a
slider move to the new picture (docs/view.md). Needs Chromium and the `view` extra.

    python bench/view.py model.onnx --cameras DATA/transforms_test.json --size 800x600 \\
        --screenshots docs/

For each mode (server: nehad's rasterizer sends the picture; browser: the page draws the
splats) it opens the page at the first camera, moves the time slider to --times one after the
other and measures, per move, the time until the page shows the new time (the panel's text is
updated right after the picture is sent, so this bounds the picture's arrival from above), and
the viewer's own frame time (deformation + drawing + PNG encoding in server mode; deformation +
splat upload in browser mode). Then it times camera moves in server mode (the deformation is
cached: drawing only). Prints the load average it ran under.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--cameras", required=True, help="camera file (e.g. transforms_test.json)")
    ap.add_argument("--camera", type=int, default=0, help="which camera of the file")
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--times", default="0.1,0.3,0.5,0.7,0.9")
    ap.add_argument("--screenshots", default=None, help="folder for view_server.png and "
                                                        "view_browser.png")
    a = ap.parse_args()
    from browser import Browser, find_chromium

    from nehad.runtime.cameras import load_view
    from nehad.runtime.images import write_image
    from nehad.runtime.scene import open_scene
    from nehad.runtime.viewer import Viewer

    if find_chromium() is None:
        sys.exit("no Chromium: apt-get install chromium")
    w, h = (int(v) for v in a.size.lower().split("x"))
    cams = load_view(a.cameras)
    cams = cams if isinstance(cams, list) else [cams]
    cams = [cams[a.camera]] + [c for k, c in enumerate(cams) if k != a.camera]
    times = [float(t) for t in a.times.split(",")]
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores)")
    for mode in ("server", "browser"):
        scene = open_scene(a.model)
        viewer = Viewer({None: scene}, cams, mode, None, "127.0.0.1", 0)
        browser = Browser(w, h)
        try:
            browser.open(viewer.start())
            browser.wait_for(lambda: "t = " in browser.text(), 120)
            time.sleep(2.0)
            latencies, frames = [], []
            for t in times:
                start = time.perf_counter()
                viewer.set_time(t)
                browser.wait_for(lambda: f"t = {t:.3f}" in browser.text(), 30, every=0.002)
                latencies.append(time.perf_counter() - start)
                frames.append(viewer.stats.seconds)
                time.sleep(0.3)
            print(f"{mode}: {scene.num_gaussians} Gaussians, {w}x{h}: slider -> new time shown "
                  f"{1000 * statistics.median(latencies):.0f} ms median "
                  f"({', '.join(f'{1000 * x:.0f}' for x in latencies)}); viewer frame "
                  f"{1000 * statistics.median(frames):.0f} ms median")
            if mode == "server":
                client = next(iter(viewer.server.get_clients().values()))
                cam = viewer.view_camera(client)
                draws = []
                for _ in range(5):
                    s = time.perf_counter()
                    viewer.draw(cam)
                    draws.append(time.perf_counter() - s)
                print(f"server: a camera move redraws in {1000 * statistics.median(draws):.0f} ms "
                      f"median (deformation cached, {viewer.caches[None].evaluations} "
                      f"evaluations for {len(times) + 1} times)")
            if a.screenshots:
                out = Path(a.screenshots) / f"view_{mode}.png"
                write_image(out, browser.screenshot())
                print(f"wrote {out}")
        finally:
            browser.close()
            viewer.stop()
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
