"""Trainer, config and run directories (issue: NeHaD training, SPEC section 5)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.config import build_config  # noqa: E402
from nehad.configtools import ConfigError  # noqa: E402
from nehad.data.synth import synthesize_scene  # noqa: E402
from nehad.trainer import RunError, Trainer  # noqa: E402


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return synthesize_scene(tmp_path_factory.mktemp("data") / "scene", resolution=24, frames=8,
                            seed=2, points=300)


def test_presets_yaml_and_overrides(tmp_path):
    cfg = build_config("cpu")
    assert cfg.preset == "cpu" and cfg.data.downscale == 2
    assert build_config("paper").fine.iterations == 20000
    yml = tmp_path / "c.yaml"
    yml.write_text("fine:\n  iterations: 123\nfield:\n  decoder: mlp\n")
    cfg = build_config("test", yml, ["fine.iterations=77", "field.multires=[1,2]",
                                     "data.background=[1,1,1]", "field.verlet=false"])
    assert cfg.fine.iterations == 77 and cfg.field.decoder == "mlp"
    assert cfg.field.multires == (1, 2) and cfg.data.background == (1.0, 1.0, 1.0)
    assert cfg.field.verlet is False
    for bad, word in [("fine.iterations=abc", "fine.iterations"), ("nope=1", "nope"),
                      ("field.lam=1.5", "lam"), ("fine", "KEY=VALUE")]:
        with pytest.raises(ConfigError, match=word):
            build_config("test", None, [bad])
    with pytest.raises(ConfigError, match="preset"):
        build_config("fast")


def _run(tmp_path, name, data, **over):
    sets = [f"{k}={v}" for k, v in over.items()]
    cfg = build_config("test", None, sets)
    return Trainer(cfg, data, tmp_path / name, progress=False)


def test_fresh_field_first_fine_render_equals_last_coarse_render(tmp_path, tiny_scene):
    tr = _run(tmp_path, "ident", tiny_scene)
    for s in range(tr.cfg.coarse.iterations):
        tr.train_step(s)
    tr.model.gaussians.reset_equilibrium()
    with torch.no_grad():
        canon = tr.model.gaussians_at(None, deform=False)
        for t in (0.0, 0.37, 1.0):
            deformed = tr.model.gaussians_at(t, deform=True)
            for a, b in zip(canon, deformed):
                assert torch.allclose(a, b, atol=1e-6), t


def test_training_lowers_the_loss_and_writes_the_run(tmp_path, tiny_scene):
    tr = _run(tmp_path, "run", tiny_scene)
    summary = tr.train()
    run = tmp_path / "run"
    assert (run / "model.pt").exists() and (run / "config.yaml").exists()
    lines = (run / "metrics.jsonl").read_text().splitlines()
    assert len(lines) >= 5
    import json
    first, last = json.loads(lines[0]), json.loads(lines[-1])
    assert last["step"] == summary["steps"] == 70
    assert last["loss"] < first["loss"]
    state = torch.load(run / "model.pt", weights_only=True)
    assert state["format"] == "nehad-run/1"


def _train_cli(data, run, *extra, wait=True):
    cmd = [sys.executable, "-m", "nehad.cli.main", "train", str(data), "-o", str(run),
           "--preset", "test", "--quiet", *extra]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_resume_after_sigkill_reproduces_the_uninterrupted_run(tmp_path, tiny_scene):
    full = _train_cli(tiny_scene, tmp_path / "full")
    assert full.returncode == 0, full.stderr
    proc = _train_cli(tiny_scene, tmp_path / "killed", wait=False)
    ckpts = tmp_path / "killed" / "checkpoints"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if ckpts.is_dir() and any(p.name.startswith("step_") for p in ckpts.iterdir()):
            break
        time.sleep(0.05)
    assert proc.poll() is None, "training ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (tmp_path / "killed" / "model.pt").exists()
    resumed = _train_cli(tiny_scene, tmp_path / "killed", "--resume")
    assert resumed.returncode == 0, resumed.stderr
    a = torch.load(tmp_path / "full" / "model.pt", weights_only=True)
    b = torch.load(tmp_path / "killed" / "model.pt", weights_only=True)
    for part in ("gaussians", "field"):
        assert a[part].keys() == b[part].keys()
        for key in a[part]:
            assert torch.equal(a[part][key], b[part][key]), (part, key)


def test_resume_with_another_config_is_refused(tmp_path, tiny_scene):
    first = _train_cli(tiny_scene, tmp_path / "r", "--set", "fine.iterations=5")
    assert first.returncode == 0, first.stderr
    again = _train_cli(tiny_scene, tmp_path / "r", "--resume", "--set", "fine.iterations=6")
    assert again.returncode != 0
    assert "fine.iterations" in again.stderr and "Traceback" not in again.stderr
    fresh = _train_cli(tiny_scene, tmp_path / "r")
    assert fresh.returncode != 0 and "--resume" in fresh.stderr


def test_random_background_recomposites_the_target_exactly(tmp_path, tiny_scene, monkeypatch):
    from nehad.data.dnerf import load_dnerf
    from nehad.trainer import recomposite

    # the same RGBA frame loaded over white and over black: recompositing one gives the other
    white = load_dnerf(tiny_scene, splits=("train",), background=(1, 1, 1)).frames["train"][0]
    black = load_dnerf(tiny_scene, splits=("train",), background=(0, 0, 0)).frames["train"][0]
    assert white.alpha is not None and (white.alpha < 0.5).any()
    alpha = torch.from_numpy(white.alpha)[:, :, None]
    got = recomposite(torch.from_numpy(white.image), alpha, (1, 1, 1), (0, 0, 0))
    assert torch.allclose(got, torch.from_numpy(black.image), atol=1e-6)
    # the trainer draws a new colour each step (and the same one for the same step on resume)
    tr = _run(tmp_path, "rb", tiny_scene)
    seen = []
    import nehad.trainer as trainer_module
    real = trainer_module.render_torch

    def spy(*args, background, **kw):
        seen.append(tuple(background))
        return real(*args, background=background, **kw)

    monkeypatch.setattr(trainer_module, "render_torch", spy)
    for s in (0, 1, 1):
        tr.train_step(s)
    assert seen[0] != seen[1] and seen[1] == seen[2]
    assert all(0.0 <= v <= 1.0 for c in seen for v in c)
