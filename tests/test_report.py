"""`nehad report RUN -o report.html` (issue 8): one self-contained page, checked structurally
(html.parser, every image decodes) and, where Chromium is installed, in a real headless browser."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main


SECTIONS = ["summary", "curves", "metrics", "renders", "trajectories", "masks", "config"]


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags, self.imgs, self.ids, self.links, self.text = [], [], [], [], []
        self.stack = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(a)
        if "id" in a:
            self.ids.append(a["id"])
        for k in ("href", "src"):
            if k in a:
                self.links.append(a[k])

    def handle_data(self, data):
        self.text.append(data)


def _parse(path: Path) -> _Page:
    p = _Page()
    p.feed(path.read_text(encoding="utf-8"))
    p.close()
    return p


def _decode(src: str) -> np.ndarray:
    import cv2

    head, data = src.split(",", 1)
    assert head == "data:image/png;base64"
    raw = base64.b64decode(data, validate=True)
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.size
    return img


@pytest.fixture(scope="module")
def report(tiny_run, tmp_path_factory):
    from nehad.evaluate import evaluate_run

    data, run = tiny_run
    result = evaluate_run(run, "test", data, lpips=False, progress=False)
    out = tmp_path_factory.mktemp("report") / "report.html"
    res = CliRunner().invoke(main, ["report", str(run), "-o", str(out), "--max-side", "160"])
    assert res.exit_code == 0, res.output
    return out, result, res.output


def test_report_is_self_contained_and_every_image_decodes(report, tiny_run):
    out, result, output = report
    page = _parse(out)
    assert page.ids == SECTIONS
    assert "report.html" in output and "sections: " + ", ".join(SECTIONS) in output
    # nothing outside the file: images inline, links to anchors of the page only
    assert all(s.startswith("data:image/png;base64,") for s in page.links if not s.startswith("#"))
    assert all(s[1:] in page.ids for s in page.links if s.startswith("#"))
    assert "link" not in page.tags and "iframe" not in page.tags
    # curves (3), test render, trajectories, 3 weight renders, fraction plot, 1 truth/weight pair
    assert len(page.imgs) == 10, [i.get("alt") for i in page.imgs]
    for img in page.imgs:
        a = _decode(img["src"])
        assert (a.shape[1], a.shape[0]) == (int(img["width"]), int(img["height"]))
        assert img.get("alt")
        assert a.std() > 0  # not a blank picture
    text = " ".join(page.text)
    # the metrics table holds the numbers of metrics.json
    assert f"{result['mean']['psnr']:.2f}" in text and f"{result['mean']['ssim']:.4f}" in text
    assert "preset: test" in text  # the config
    assert "IoU" in text and "AUC" in text and "nehad synth scene 'spheres'" in text
    log = [json.loads(x) for x in (tiny_run[1] / "metrics.jsonl").read_text().splitlines()]
    assert f"{log[-1]['psnr']:.2f} dB (step {log[-1]['step']})" in text
    assert not [p for p in out.parent.iterdir() if p.name != "report.html"]  # atomic, no temp


def test_report_without_eval_or_dataset(tiny_run, tmp_path):
    """A section whose inputs are missing says so; the report is still written."""
    _, run = tiny_run
    copy = tmp_path / "run"
    copy.mkdir()
    for name in ("model.pt", "config.yaml", "metrics.jsonl"):
        shutil.copy(run / name, copy / name)
    from nehad.checkpoint import atomic_torch_save, load_state

    state = load_state(copy / "model.pt")  # the dataset the run recorded has moved
    state["data_dir"] = str(tmp_path / "moved")
    atomic_torch_save(state, copy / "model.pt")
    out = tmp_path / "r.html"
    res = CliRunner().invoke(main, ["report", str(copy), "-o", str(out), "--max-side", "64"])
    assert res.exit_code == 0, res.output
    page = _parse(out)
    text = " ".join(page.text)
    assert page.ids == SECTIONS
    assert "No evaluation yet" in text and "No test renders" in text and "moved" in text
    for img in page.imgs:
        _decode(img["src"])


def test_report_bad_inputs(tiny_run, tiny_onnx, tmp_path):
    _, run = tiny_run
    runner = CliRunner()
    for args, word in [([str(tiny_onnx), "-o", str(tmp_path / "a.html")], "not an exported"),
                       ([str(tmp_path), "-o", str(tmp_path / "a.html")], "no model.pt"),
                       ([str(run), "-o", str(tmp_path / "a.pdf")], ".html"),
                       ([str(run), "-o", str(tmp_path / "no" / "a.html")], "does not exist"),
                       ([str(run), "-o", str(tmp_path / "a.html"), "--data",
                         str(tmp_path / "moved")], "scene folder not found"),
                       ([str(run), "-o", str(tmp_path / "a.html"), "--data", str(tmp_path)],
                        "not a dataset folder")]:
        res = runner.invoke(main, ["report"] + args)
        assert res.exit_code != 0 and word in res.output, res.output
        assert "Traceback" not in res.output
    assert not list(tmp_path.glob("*.html"))


def _chromium() -> str | None:
    for name in (os.environ.get("NEHAD_CHROMIUM"), "chromium", "chromium-browser",
                 "google-chrome", "chrome-headless-shell"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@pytest.mark.skipif(_chromium() is None,
                    reason="no Chromium (apt-get install chromium, or set NEHAD_CHROMIUM)")
def test_report_in_headless_chromium(report, tmp_path):
    """Chromium loads the page offline and decodes every image (the page's own load handler
    counts them into <html data-images-ok>); a screenshot is not blank."""
    out, _, _ = report
    flags = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run(flags + ["--virtual-time-budget=5000", "--dump-dom", out.as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    import re

    total = re.search(r'data-images-total="(\d+)"', dom.stdout)
    ok = re.search(r'data-images-ok="(\d+)"', dom.stdout)
    assert total and ok, dom.stdout[:500]
    assert int(total.group(1)) == int(ok.group(1)) == 10
    shot = tmp_path / "shot.png"
    res = subprocess.run(flags + ["--hide-scrollbars", "--window-size=1100,2400",
                                  f"--screenshot={shot}", out.as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and shot.is_file(), res.stderr[-2000:]
    import cv2

    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (2400, 1100)
    assert (img < 200).any(-1).mean() > 0.01  # text and pictures were painted
