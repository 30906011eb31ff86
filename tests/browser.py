"""A headless Chromium driven over the DevTools protocol, for the tests that look at a page
(`nehad view`). Needs Debian's `chromium` (or $NEHAD_CHROMIUM) and the `websockets` package
(a dependency of viser); `find_chromium()` is None when there is no browser.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np


def find_chromium() -> str | None:
    for name in (os.environ.get("NEHAD_CHROMIUM"), "chromium", "chromium-browser",
                 "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


class Browser:
    """One headless Chromium with one page of `width` x `height` CSS pixels (scale 1)."""

    def __init__(self, width: int, height: int, timeout: float = 60.0):
        from websockets.sync.client import connect

        self.profile = tempfile.mkdtemp(prefix="nehad-chromium-")
        self.proc = subprocess.Popen(
            [find_chromium(), "--headless=new", "--no-sandbox", "--no-first-run",
             "--disable-background-networking", "--disable-extensions", "--mute-audio",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             f"--window-size={width},{height}", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while not (port_file.is_file() and port_file.read_text().strip()):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        pages = []
        while not pages:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
                pages = [p for p in json.load(r) if p.get("type") == "page"]
            if not pages:
                time.sleep(0.1)
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None)
        self.ids = itertools.count(1)
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                  deviceScaleFactor=1, mobile=False)

    def call(self, method: str, **params):
        """One DevTools command; its result (events in between are skipped)."""
        k = next(self.ids)
        self.ws.send(json.dumps({"id": k, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == k:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        res = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return res.get("result", {}).get("value")

    def text(self) -> str:
        """The page's text, hidden elements included."""
        return self.evaluate("document.body ? document.body.textContent : ''") or ""

    def hide_overlays(self) -> int:
        """Hide every element that neither is nor holds a canvas (panels, notifications), so a
        screenshot shows the 3D view alone; returns how many were hidden."""
        return self.evaluate("""(() => {
            const keep = new Set();
            document.querySelectorAll('canvas').forEach(c => {
                for (let e = c; e; e = e.parentElement) keep.add(e); });
            let n = 0;
            document.querySelectorAll('body *').forEach(e => {
                if (!keep.has(e) && !e.querySelector('canvas')) {
                    e.style.visibility = 'hidden'; n++; } });
            return n; })()""")

    def screenshot(self) -> np.ndarray:
        """The page as float32 (H, W, 3) in [0, 1]."""
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return img[:, :, ::-1].astype(np.float32) / 255.0

    def settled_screenshot(self, timeout: float = 30.0, every: float = 0.5) -> np.ndarray:
        """A screenshot once two taken `every` seconds apart are the same (the canvas has
        finished drawing; on a loaded machine that can take seconds), or the last at the
        timeout."""
        deadline = time.monotonic() + timeout
        last = self.screenshot()
        while time.monotonic() < deadline:
            time.sleep(every)
            shot = self.screenshot()
            if np.array_equal(shot, last):
                return shot
            last = shot
        return last

    def wait_for(self, predicate, timeout: float = 30.0, every: float = 0.05):
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"the page did not get there in {timeout:g} s; it shows: "
                                   f"{self.text()[:400]!r}")
            time.sleep(every)

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.profile, ignore_errors=True)
