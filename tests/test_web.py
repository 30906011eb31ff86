"""`nehad web` (runtime/web.py, docs/web.md): the folder plays the exported scene in a real
headless Chromium (SwiftShader WebGL2, onnxruntime-web in wasm) with nothing but a static file
server behind it; its pictures are what `nehad render` draws for the same camera and time; it
needs no other address; a model that cannot load says why on the page; bad inputs end in one
error and write nothing. The browser tests skip without Chromium or without the libraries
(`npm ci --prefix runtime/web`)."""

from __future__ import annotations

import base64
import contextlib
import functools
import http.server
import json
import re
import threading

import numpy as np
import pytest
from click.testing import CliRunner

from browser import Browser, find_chromium
from nehad.cli.main import main
from nehad.runtime import web
from nehad.runtime.cameras import load_view, save_view
from video_model import build_moving_export

needs_browser = pytest.mark.skipif(find_chromium() is None,
                                   reason="no Chromium (apt-get install chromium, or set "
                                          "NEHAD_CHROMIUM)")
needs_libraries = pytest.mark.skipif(not all((web.ORT_DIST / f).is_file() for f in web.ORT_FILES),
                                     reason=f"no onnxruntime-web ({web.FETCH_COMMAND})")
W, H = 192, 144
TIMES = (0.15, 0.5, 0.85)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """(model.onnx with moving Gaussians, a cam.json of two test cameras at W x H)."""
    onnx, scene = build_moving_export(tmp_path_factory)
    cams = [c.with_size(W, H) for c in load_view(scene / "transforms_test.json")[:2]]
    path = tmp_path_factory.mktemp("web") / "cams.json"
    save_view(path, cams)
    return onnx, path


@pytest.fixture
def fake_libraries(tmp_path, monkeypatch):
    """Stand-ins for the onnxruntime-web files (the bad-input tests never open a page)."""
    dist = tmp_path / "dist"
    dist.mkdir()
    for name in web.ORT_FILES:
        (dist / name).write_bytes(b"// stand-in\n")
    monkeypatch.setattr(web, "ORT_DIST", dist)


@contextlib.contextmanager
def serve(folder, isolated: bool = False):
    """A static file server on 127.0.0.1 for `folder` (python's own); yields its address.
    `isolated`: it sends the cross-origin isolation headers of the folder's `_headers` file."""
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def end_headers(self):
            if isolated:
                self.send_header("Cross-Origin-Opener-Policy", "same-origin")
                self.send_header("Cross-Origin-Embedder-Policy", "require-corp")
            super().end_headers()

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def open_player(browser: Browser, url: str) -> None:
    browser.open(url + "/index.html")
    browser.wait_for(lambda: browser.evaluate(
        "window.nehad && (window.nehad.ready || window.nehad.error)"), timeout=120)


@contextlib.contextmanager
def player(site, isolated: bool = False):
    """(browser, address) with the player of `site` open in it; the browser is closed after."""
    browser = Browser(800, 600)
    try:
        with serve(site, isolated) as url:
            open_player(browser, url)
            yield browser, url
    finally:
        browser.close()


def show(browser: Browser, t: float, camera: int) -> np.ndarray:
    """The page's picture of `camera` at time t, float32 (H, W, 3) in [0, 1]."""
    import cv2

    res = browser.call("Runtime.evaluate", awaitPromise=True, returnByValue=True,
                       expression=f"window.nehad.show({t}, {camera}).then(s => JSON.stringify(s))")
    assert "exceptionDetails" not in res, res
    png = base64.b64decode(browser.evaluate("window.nehad.png()").split(",", 1)[1])
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return img[:, :, ::-1].astype(np.float32) / 255.0


def psnr(a, b) -> float:
    return float(-10 * np.log10(max(np.mean((np.asarray(a, np.float64) - b) ** 2), 1e-12)))


def reference(onnx, camera, t: float) -> np.ndarray:
    from nehad.runtime.onnx_model import OnnxModel
    from nehad.runtime.raster import render

    m = OnnxModel(onnx)
    return np.clip(render(m.gaussians(t), camera, m.background).rgb, 0.0, 1.0)


def build(tmp_path, onnx, cams) -> str:
    out = tmp_path / "site"
    res = CliRunner().invoke(main, ["web", str(onnx), "-o", str(out), "--cameras", str(cams)])
    assert res.exit_code == 0, res.output
    return out


@needs_browser
@needs_libraries
@pytest.mark.slow  # a browser, onnxruntime-web's wasm, three times at two cameras
def test_the_page_draws_what_nehad_render_draws_at_each_time(model, tmp_path):
    onnx, cams = model
    site = build(tmp_path, onnx, cams)
    cameras = load_view(cams)
    with player(site) as (browser, _):
        assert browser.evaluate("window.nehad.error") is None
        for k, camera in enumerate(cameras):
            refs = [reference(onnx, camera, t) for t in TIMES]
            for i, t in enumerate(TIMES):
                got = show(browser, t, k)
                assert got.shape == (H, W, 3)
                scores = [psnr(got, r) for r in refs]
                print(f"camera {k} t {t}: {' / '.join(f'{s:.1f}' for s in scores)} dB "
                      f"against nehad render at t = {TIMES}")
                assert scores[i] >= 30.0
                assert scores[i] == max(scores), "closer to another time's render"
        text = browser.text()
        assert "deform" in text and "1 thread: the page is not cross-origin isolated" in text


@needs_browser
@needs_libraries
@pytest.mark.slow
def test_the_folder_plays_with_the_network_cut_off_and_names_no_outside_address(model, tmp_path):
    onnx, cams = model
    site = build(tmp_path, onnx, cams)
    for path in site.rglob("*"):
        if path.is_file():
            text = path.read_bytes()
            assert not re.search(rb"https?://", text), f"{path.name} names an outside address"
    browser = Browser(800, 600)
    try:
        with serve(site) as url:
            open_player(browser, url)
            assert browser.evaluate("window.nehad.error") is None
            loaded = browser.evaluate(
                "performance.getEntriesByType('resource').map(e => e.name)")
            assert loaded and all(u.startswith(url + "/") for u in loaded), loaded
        # the server is gone: every later frame comes from what the page holds
        browser.call("Network.enable")
        browser.call("Network.emulateNetworkConditions", offline=True, latency=0,
                     downloadThroughput=-1, uploadThroughput=-1)
        before = show(browser, 0.2, 1)
        after = show(browser, 0.8, 1)
        assert psnr(after, reference(onnx, load_view(cams)[1], 0.8)) >= 30.0
        assert psnr(before, after) < 60.0  # it moved
    finally:
        browser.close()


@needs_browser
@needs_libraries
@pytest.mark.slow
def test_a_model_that_cannot_load_says_why_on_the_page(model, tmp_path):
    onnx, cams = model
    site = build(tmp_path, onnx, cams)
    (site / "model.onnx").write_bytes(b"not an onnx model")
    with player(site) as (browser, _):
        error = browser.evaluate("window.nehad.error")
        assert error and error.startswith("model.onnx: onnxruntime-web cannot load it")
        assert "Error: model.onnx" in browser.text()


def test_bad_inputs_end_in_one_error_and_write_nothing(model, tmp_path, fake_libraries):
    onnx, cams = model
    runner = CliRunner()

    def refused(args, words):
        res = runner.invoke(main, ["web", *args])
        assert res.exit_code == 1, res.output
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("Error:"), res.output
        assert words in lines[0], lines[0]
        assert "Traceback" not in res.output

    foreign = tmp_path / "foreign.onnx"
    foreign.write_bytes(b"\x08\x07" + b"\x00" * 40)
    refused([str(foreign), "-o", str(tmp_path / "a")], "foreign.onnx")
    assert not (tmp_path / "a").exists()
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    refused([str(onnx), "-o", str(full)], "not empty")
    assert sorted(p.name for p in full.iterdir()) == ["keep.txt"]
    refused([str(onnx), "-o", str(tmp_path / "b"), "--lod"], "--lod")
    assert not (tmp_path / "b").exists()
    refused([str(onnx), "-o", str(tmp_path / "c"), "--cameras", str(tmp_path / "none.json")],
            "none.json")
    assert not (tmp_path / "c").exists()
    with pytest.MonkeyPatch.context() as mp:  # a parent folder that refuses a new folder
        def no_folder(*args, **kwargs):
            raise PermissionError(13, "Permission denied")
        mp.setattr(web.tempfile, "mkdtemp", no_folder)
        refused([str(onnx), "-o", str(tmp_path / "e")],
                f"{tmp_path / 'e'}: cannot create a folder in {tmp_path} (Permission denied)")
    web.ORT_DIST = tmp_path / "empty"  # fake_libraries' monkeypatch restores it
    refused([str(onnx), "-o", str(tmp_path / "d")], "npm ci --prefix")
    assert not (tmp_path / "d").exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_the_folder_holds_the_player_the_model_and_the_scene(model, tmp_path, fake_libraries):
    onnx, cams = model
    site = build(tmp_path, onnx, cams)
    names = sorted(str(p.relative_to(site)) for p in site.rglob("*") if p.is_file())
    assert names == ["_headers", "index.html", "model.onnx", "ort/ort-wasm-simd-threaded.mjs",
                     "ort/ort-wasm-simd-threaded.wasm.gz", "ort/ort.wasm.min.mjs", "player.js",
                     "scene.json"]
    assert (site / "model.onnx").read_bytes() == onnx.read_bytes()
    scene = json.loads((site / "scene.json").read_text())
    cameras = load_view(cams)
    assert scene["format"] == "nehad-web/1" and len(scene["cameras"]) == len(cameras)
    got = np.array(scene["cameras"][1]["world_to_camera"])
    assert np.allclose(got, cameras[1].world_to_camera)
    assert "Cross-Origin-Embedder-Policy: require-corp" in (site / "_headers").read_text()


@needs_browser
@needs_libraries
@pytest.mark.slow
def test_served_with_the_isolation_headers_the_wasm_runs_threaded(model, tmp_path):
    onnx, cams = model
    site = build(tmp_path, onnx, cams)
    with player(site, isolated=True) as (browser, _):
        assert browser.evaluate("window.nehad.error") is None
        assert browser.evaluate("self.crossOriginIsolated") is True
        assert "threads, cross-origin isolated" in browser.evaluate("window.nehad.stats.mode")
        got = show(browser, 0.5, 0)
        assert psnr(got, reference(onnx, load_view(cams)[0], 0.5)) >= 30.0
