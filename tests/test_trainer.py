"""Trainer, config and run directories (issue: NeHaD training, docs/design.md section 5)."""

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
from nehad.model import RunError  # noqa: E402
from nehad.trainer import Trainer  # noqa: E402


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return synthesize_scene(tmp_path_factory.mktemp("data") / "scene", resolution=24, frames=8,
                            seed=2, points=300)


def test_presets_yaml_and_overrides(tmp_path):
    cfg = build_config("cpu")
    assert cfg.preset == "cpu" and cfg.data.downscale == 2
    assert cfg.field.hnn_depth == 1  # the cpu recipe's decoder (docs/results.md, 2026-11-28)
    assert build_config("paper").fine.iterations == 20000
    assert build_config("paper").field.hnn_depth == 2
    yml = tmp_path / "c.yaml"
    yml.write_text("fine:\n  iterations: 123\nfield:\n  decoder: mlp\n")
    cfg = build_config("test", yml, ["fine.iterations=77", "field.multires=[1,2]",
                                     "data.background=[1,1,1]", "field.verlet=false"])
    assert cfg.fine.iterations == 77 and cfg.field.decoder == "mlp"
    assert cfg.field.multires == (1, 2) and cfg.data.background == (1.0, 1.0, 1.0)
    assert cfg.field.verlet is False
    for bad, word in [("fine.iterations=abc", "fine.iterations"), ("nope=1", "nope"),
                      ("field.lam=1.5", "lam"), ("fine", "KEY=VALUE"),
                      ("carve.mode=ray", "carve.mode"), ("carve.seed_views=0", "seed_views"),
                      ("carve.track_members=3", "track_members"),
                      ("carve.max_tracks=0", "max_tracks"),
                      ("carve.check_pieces=member", "check_pieces"),
                      ("train.hold_mode=linear", "hold_mode"),
                      ("loss.scale_rate_times=random", "scale_rate_times"),
                      ("loss.acceleration_times=random", "acceleration_times")]:
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


def _train_cli(data, run, *extra, wait=True, env=None, timeout=300):
    cmd = [sys.executable, "-m", "nehad.cli.main", "train", str(data), "-o", str(run),
           "--preset", "test", "--quiet", *extra]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=env)


def _assert_same_models(run_a, run_b):
    """The two runs' model.pt hold bit-identical Gaussians and fields."""
    a = torch.load(run_a / "model.pt", weights_only=True)
    b = torch.load(run_b / "model.pt", weights_only=True)
    for part in ("gaussians", "field"):
        assert a[part].keys() == b[part].keys()
        for key in a[part]:
            assert torch.equal(a[part][key], b[part][key]), (part, key)


@pytest.mark.slow  # three CLI trainings
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
    _assert_same_models(tmp_path / "full", tmp_path / "killed")


@pytest.mark.slow  # two CLI trainings, the first compiling every kernel
def test_kernels_loaded_from_numbas_cache_train_what_compiled_ones_do(tmp_path, tiny_scene):
    """The first run after an install compiles the Numba kernels, every later one loads them
    from numba's cache: both must compute the same bits (with 'contract' or 'reassoc' in the
    rasterizer's backward they did not, and a run resumed with a warm cache differed from its
    uninterrupted twin; runtime/raster/kernels.py), nor the hex-plane lookup's passes (with 32
    channels, as the presets have, they did not either; nehad/field/hexplane_kernel.py)."""
    cache = tmp_path / "numba_cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "OMP_NUM_THREADS": "2",
           "NUMBA_NUM_THREADS": "2"}
    for name in ("compiled", "cached"):
        done = _train_cli(tiny_scene, tmp_path / name, "--set", "coarse.iterations=3", "--set",
                          "fine.iterations=4", "--set", "field.multires=[1,2]", "--set",
                          "field.out_dim=32", env=env, timeout=600)
        assert done.returncode == 0, done.stderr
        assert any(cache.rglob("*.nbi")), "numba wrote no cache"
    _assert_same_models(tmp_path / "compiled", tmp_path / "cached")


@pytest.mark.slow  # two CLI trainings
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
    from nehad.views import recomposite

    # the same RGBA frame loaded over white and over black: recompositing one gives the other
    white = load_dnerf(tiny_scene, splits=("train",), background=(1, 1, 1)).frames["train"][0]
    black = load_dnerf(tiny_scene, splits=("train",), background=(0, 0, 0)).frames["train"][0]
    assert white.alpha is not None and (white.alpha < 0.5).any()
    alpha = torch.from_numpy(white.alpha)[:, :, None]
    got = recomposite(torch.from_numpy(white.image), alpha, (1, 1, 1), (0, 0, 0))
    assert torch.allclose(got, torch.from_numpy(black.image), atol=1e-6)
    # the trainer draws a new colour each step (and the same one for the same step on resume)
    tr = _run(tmp_path, "rb", tiny_scene, **{"data.random_background": "true"})
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


def test_coarse_stage_alone_is_a_static_fit_reaching_25_db_on_held_out_views(tmp_path):
    """The backward pass trains: a coarse-only run (fine.iterations=0, static 3DGS) on a
    synthetic scene held at one time reaches >= 25 dB PSNR on held-out views."""
    from nehad.data.dnerf import load_dnerf
    from nehad.losses import psnr
    from nehad.splat.rasterize import render_torch
    from nehad.trainer import Trainer

    data = synthesize_scene(tmp_path / "scene", resolution=64, frames=40, fixed_time=0.5, seed=3)
    test = load_dnerf(data, splits=("test",), background=(1.0, 1.0, 1.0)).frames["test"]
    cfg = build_config("test", None, ["coarse.iterations=600", "fine.iterations=0",
                                      "train.sh_degree=0"])
    tr = Trainer(cfg, data, tmp_path / "run", progress=False, log=None)

    def held_out() -> float:
        with torch.no_grad():
            params = tr.model.gaussians_at(None, deform=False)
            return float(np.mean([float(psnr(render_torch(*params, f.camera,
                                                          background=tr.background).rgb,
                                              torch.from_numpy(f.image))) for f in test]))

    before = held_out()
    summary = tr.train()
    after = held_out()
    print(f"coarse-only run 64x64: {before:.2f} dB -> {after:.2f} dB on {len(test)} held-out "
          f"views in {summary['seconds']:.1f} s")
    assert summary["steps"] == 600 and summary["last"]["stage"] == "coarse"
    assert after >= 25.0
    assert after > before + 5.0


# -- the training recipe's schedules (docs/training.md) ---------------------------------------

def test_densify_schedule_scales_with_the_stage_and_never_resets_at_its_end():
    from nehad.config import fine_stage
    from nehad.densify import DensifySchedule

    s = DensifySchedule.for_stage(fine_stage(12000), 12000, 100)
    assert (s.start, s.stop, s.reset_every) == (1200, 9600, 1800)
    assert [it for it in range(1, 12001) if s.resets(it)] == [1800, 3600, 5400, 7200, 9000]
    # the same fractions keep their meaning in a 20x longer stage
    long = DensifySchedule.for_stage(fine_stage(240000), 240000, 100)
    assert (long.start, long.stop, long.reset_every) == (24000, 192000, 36000)
    # whatever the length, no reset on the last step or outside the densification window
    for length in (10, 99, 300, 2000, 3000, 6000, 20000, 30000):
        for stage in (fine_stage(length), fine_stage(length, densify_until=1.0)):
            s = DensifySchedule.for_stage(stage, length, 100)
            resets = [it for it in range(1, length + 1) if s.resets(it)]
            assert length not in resets and all(it < s.stop for it in resets)
            assert all(s.start <= it < s.stop for it in range(1, length + 1) if s.densifies(it))
    # the quarter period after each reset is "recovering" (no carving pass), and only it
    s = DensifySchedule.for_stage(fine_stage(12000), 12000, 100)
    rec = [it for it in range(1, 12001) if s.recovering(it)]
    assert rec == [it for r in (1800, 3600, 5400, 7200, 9000) for it in range(r, r + 450)]


def test_time_window_grows_from_the_canonical_time_to_the_whole_range():
    from nehad.config import coarse_stage, fine_stage
    from nehad.curriculum import eligible_frames, window_at

    fine = fine_stage(1000)
    w0 = window_at(fine, 0, 1000, 0.5, (0.0, 1.0))
    assert (w0.lo, w0.hi) == pytest.approx((0.44, 0.56))
    mid = window_at(fine, 250, 1000, 0.5, (0.0, 1.0))
    assert (mid.lo, mid.hi) == pytest.approx((0.22, 0.78))
    for it in (500, 700, 999):
        w = window_at(fine, it, 1000, 0.5, (0.0, 1.0))
        assert (w.lo, w.hi) == (0.0, 1.0)
    # the coarse stage's window stays put; an off-centre canonical time is clipped to the range
    c = window_at(coarse_stage(100), 99, 100, 0.02, (0.0, 1.0))
    assert (c.lo, c.hi) == pytest.approx((0.0, 0.08))
    times = np.linspace(0, 1, 11)
    assert list(eligible_frames(times, w0)) == [5]
    # a window between two frames still yields the nearest one
    from nehad.curriculum import TimeWindow, resolution_factor, widen_to_frames

    assert list(eligible_frames(times, TimeWindow(0.33, 0.34))) == [3]
    # a window holding too few frames widens to the nearest ones, a wide one stays
    w = widen_to_frames(w0, times, 3)
    assert (w.lo, w.hi) == pytest.approx((0.4, 0.6))
    assert widen_to_frames(TimeWindow(0.0, 1.0), times, 3) == TimeWindow(0.0, 1.0)
    assert widen_to_frames(w0, times, 0) == w0
    # the warm-up factor never takes the shorter side below the minimum size
    schedule = ((0.0, 4), (0.5, 2))
    assert [resolution_factor(schedule, s, 10) for s in (0, 5)] == [4, 2]
    assert [resolution_factor(schedule, s, 10, 400, 100) for s in (0, 5)] == [4, 2]
    assert [resolution_factor(schedule, s, 10, 200, 100) for s in (0, 5)] == [2, 2]
    assert [resolution_factor(schedule, s, 10, 100, 100) for s in (0, 5)] == [1, 1]


def test_time_planes_outside_the_window_are_held_at_its_edges(tmp_path, tiny_scene):
    from nehad.curriculum import TimeWindow, hold_time_planes, time_plane_rows
    from nehad.field.hexplane import TIME_PLANES

    tr = _run(tmp_path, "hold", tiny_scene, **{"field.resolution": "[8,8,8,11]"})
    hp = tr.model.field.hexplane
    with torch.no_grad():
        for p in hp.parameters():
            p.normal_()
    before = [p.detach().clone() for p in hp.parameters()]
    window = TimeWindow(0.35, 0.62)
    first, last = time_plane_rows(window, 11)
    assert (first, last) == (3, 7)  # nodes at k / 10: 0.3 .. 0.7 bracket the window
    hold_time_planes(hp, window)
    for scale, old_scale in zip(hp.planes, _chunks(before, len(hp.planes))):
        for k, (plane, old) in enumerate(zip(scale, old_scale)):
            if k not in TIME_PLANES:
                assert torch.equal(plane, old)
                continue
            assert torch.equal(plane[:, :, first:last + 1], old[:, :, first:last + 1])
            assert torch.equal(plane[:, :, :first], old[:, :, first:first + 1].expand_as(
                plane[:, :, :first]))
            assert torch.equal(plane[:, :, last + 1:], old[:, :, last:last + 1].expand_as(
                plane[:, :, last + 1:]))


def test_slope_hold_carries_a_linear_motion_on_past_the_window(tmp_path, tiny_scene):
    """`train.hold_mode=slope`: rows that change linearly inside the window go on changing at
    the same rate outside it, whatever they held before; the default holds the edge values."""
    from nehad.curriculum import TimeWindow, hold_time_planes
    from nehad.field.hexplane import TIME_PLANES

    tr = _run(tmp_path, "slope", tiny_scene, **{"field.resolution": "[8,8,8,11]"})
    hp = tr.model.field.hexplane
    rows = torch.arange(11, dtype=torch.float32).reshape(1, 1, 11, 1)
    lines = {}
    with torch.no_grad():
        for s, scale in enumerate(hp.planes):
            for k in TIME_PLANES:
                plane = scale[k]
                a = torch.randn(1, plane.shape[1], 1, plane.shape[3])
                b = torch.randn(1, plane.shape[1], 1, plane.shape[3])
                lines[s, k] = a + b * rows
                plane.copy_(lines[s, k] + 5.0 * torch.randn_like(plane))
                plane[:, :, 3:8] = lines[s, k][:, :, 3:8]  # rows 3..7 hold the window
    hold_time_planes(hp, TimeWindow(0.35, 0.62), mode="slope")
    for (s, k), line in lines.items():
        torch.testing.assert_close(hp.planes[s][k].detach(), line, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="hold mode"):
        hold_time_planes(hp, TimeWindow(0.35, 0.62), mode="linear")


def _chunks(items, n):
    size = len(items) // n
    return [items[i * size:(i + 1) * size] for i in range(n)]


def test_trunk_standardisation_gives_every_gaussian_its_own_h(tmp_path, tiny_scene):
    tr = _run(tmp_path, "std", tiny_scene)
    for s in range(tr.cfg.coarse.iterations + 1):  # through the first fine step
        tr.train_step(s)
    g = tr.model.gaussians
    field = tr.model.field
    fresh = type(field)(field.cfg, field.aabb, float(field.extent))
    with torch.no_grad():
        fresh.hexplane.load_state_dict(field.hexplane.state_dict())
        t_col = torch.full((len(g), 1), tr.cfg.train.canonical_time)
        from nehad.field.hexplane import normalize_aabb

        f = fresh.hexplane(normalize_aabb(g.means, fresh.aabb), 2 * t_col - 1)
        h_default = fresh.trunk(f)
        fresh.standardize_trunk(g.means, tr.cfg.train.canonical_time)
        h = fresh.trunk(f)
    # default initialisation: h is mostly the trunk's bias, nearly the same for every Gaussian
    assert float((h_default.std(0) / h_default.abs().mean(0)).median()) < 0.5
    assert torch.allclose(h.mean(0), torch.zeros(h.shape[1]), atol=1e-4)
    assert torch.allclose(h.std(0), torch.ones(h.shape[1]), atol=1e-3)


def test_resolution_schedule_and_logged_psnr(tmp_path, tiny_scene):
    import json

    tr = _run(tmp_path, "res", tiny_scene,
              **{"data.resolution_schedule": "[[0,4],[0.5,2]]", "coarse.iterations": 10,
                 "fine.iterations": 10, "data.random_background": "true",
                 "data.warmup_min_size": 0})
    seen = []  # the image sizes carving is given: the layer's own, never the warm-up's

    class Spy:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def step_post_update(self, *args, **kw):
            seen.append(tuple(kw["views"].images[0].shape[:2]))
            return self.inner.step_post_update(*args, **kw)

    tr.carving = Spy(tr.carving)
    tr.train()
    lines = [json.loads(x) for x in (tmp_path / "res" / "metrics.jsonl").read_text().splitlines()]
    sizes = {r["step"]: r["resolution"] for r in lines}
    assert sizes[10] == [6, 6] and sizes[20] == [12, 12]  # 24 px images / 4, then / 2
    assert len(seen) == 20 and set(seen) == {(24, 24)}
    assert all(np.isfinite(r["psnr"]) for r in lines)


def test_resume_of_a_missing_run_and_a_broken_dataset_write_nothing(tmp_path, tiny_scene):
    with pytest.raises(RunError, match="no run to resume"):
        _run_resume(tmp_path / "nothing", tiny_scene)
    assert not (tmp_path / "nothing").exists()
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    (broken / "transforms_train.json").write_text("{not json")
    from nehad.data.dnerf import DatasetError

    with pytest.raises(DatasetError):
        _run(tmp_path, "from_broken", broken)
    assert not (tmp_path / "from_broken").exists()


def _run_resume(run, data):
    return Trainer(build_config("test"), data, run, resume=True, progress=False)


def test_static_stage_keeps_transparent_gaussians_and_the_boundary_revives_them(tmp_path,
                                                                                tiny_scene):
    """coarse.prune_transparent=false (the default): no Gaussian of the static stage is pruned
    for its opacity (true prunes them on this scene); train.revive_opacity=0.05: at the first
    deforming step every opacity is at least 0.05 (docs/results.md, 2026-11-26)."""
    counts = {}
    for name, over in (("prune", {"coarse.prune_transparent": "true"}), ("keep", {})):
        tr = _run(tmp_path, name, tiny_scene, **{"coarse.densify_from": 0.0, **over})
        with torch.no_grad():  # half the Gaussians transparent: the default prunes them
            tr.model.gaussians.opacity_logits[::2] = -9.0
        for s in range(tr.cfg.coarse.iterations):
            tr.train_step(s)
        opacity = torch.sigmoid(tr.model.gaussians.opacity_logits.detach())
        counts[name] = int((opacity < 0.002).sum())  # the 150 set transparent, still there
    assert counts["prune"] <= 10 and counts["keep"] >= 140, counts
    tr = _run(tmp_path, "revive", tiny_scene, **{"train.revive_opacity": 0.05})
    with torch.no_grad():
        tr.model.gaussians.opacity_logits[::2] = -9.0
    for s in range(tr.cfg.coarse.iterations):
        tr.train_step(s)
    assert float(torch.sigmoid(tr.model.gaussians.opacity_logits.detach()).min()) < 0.01
    tr.train_step(tr.cfg.coarse.iterations)  # the boundary, then one deforming step
    opacity = torch.sigmoid(tr.model.gaussians.opacity_logits.detach())
    assert float(opacity.min()) > 0.04, float(opacity.min())


def test_resume_of_a_run_older_than_a_config_key(tmp_path):
    """A run whose config.yaml predates a key (here train.drift_window) resumes when the new
    config holds that key at its default, the value the run trained with; a changed value is
    still refused, naming the key."""
    import yaml

    from nehad.checkpoint import prepare_run_dir
    from nehad.config import build_config
    from nehad.configtools import to_dict

    cfg = build_config("test")
    run = tmp_path / "old"
    run.mkdir()
    saved = to_dict(cfg)
    del saved["train"]["drift_window"]
    (run / "config.yaml").write_text(yaml.safe_dump(saved, sort_keys=False))
    prepare_run_dir(run, cfg, resume=True)
    changed = build_config("test", overrides=["train.drift_window=0.1"])
    with pytest.raises(RunError, match="train.drift_window"):
        prepare_run_dir(run, changed, resume=True)
