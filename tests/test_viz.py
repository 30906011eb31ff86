"""Trajectories, BED masks and their score, plots (issue 8: `nehad viz`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime.cameras import Camera, load_view
from nehad.runtime.gaussians import SH_C0, GaussianCloud
from nehad.viz import VizError
from nehad.viz.masks import (auc_from_histograms, frame_counts, render_weights, summarize,
                             weight_image)
from nehad.viz.plots import encode_png, line_plot, nice_ticks
from nehad.viz.trajectories import (Tracks, compute_tracks, draw_tracks, select_gaussians,
                                    track_times, write_video)
MUJOCO = Path(__file__).resolve().parents[2] / "shared" / "data" / "mujoco"


def _camera(size=64, dist=4.0) -> Camera:
    """Looks down -z at the origin from (0, 0, dist), OpenCV axes."""
    w2c = np.eye(4)
    w2c[:3, :3] = np.diag([1.0, -1.0, -1.0])
    w2c[2, 3] = dist
    f = size / (2 * np.tan(np.radians(25)))
    return Camera(size, size, f, f, size / 2, size / 2, w2c, time=0.5)


def _cloud(means, scale=0.03, opacity=0.9, rgb=(0.5, 0.5, 0.5)) -> GaussianCloud:
    n = len(means)
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    sh = np.tile(((np.asarray(rgb) - 0.5) / SH_C0)[None, None, :], (n, 1, 1))
    return GaussianCloud(np.asarray(means, np.float32), np.full((n, 3), scale), quats,
                         np.full(n, opacity), sh)


# ---------------------------------------------------------------------------------------------
# trajectories


def test_tracks_equal_the_deformed_means_projected(tiny_run, tiny_run_model):
    import torch

    from nehad.model import cloud_at

    data, _ = tiny_run
    model, meta = tiny_run_model
    cam = load_view(f"{data}/transforms_test.json:0").with_size(80, 60)
    times = track_times((0.0, 1.0), 6)
    tracks = compute_tracks(lambda t: cloud_at(model, t, meta.sh_degree), cam, times,
                            count=40, seed=3)
    assert len(tracks) == 40 and tracks.world.shape == (6, 40, 3)
    assert np.all(np.diff(tracks.ids) > 0)
    for k, t in enumerate(times):
        with torch.no_grad():
            means = model.gaussians_at(torch.tensor([t]))[0].numpy()
        np.testing.assert_allclose(tracks.world[k], means[tracks.ids], rtol=0, atol=1e-6)
        # independent projection: OpenCV camera frame, u = fx X/Z + cx, v = fy Y/Z + cy
        pc = means[tracks.ids] @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
        uv = np.stack([cam.fx * pc[:, 0] / pc[:, 2] + cam.cx,
                       cam.fy * pc[:, 1] / pc[:, 2] + cam.cy], 1)
        np.testing.assert_allclose(tracks.pixels[k], uv, rtol=0, atol=1e-3)
        np.testing.assert_allclose(tracks.depth[k], pc[:, 2], rtol=0, atol=1e-5)
    steps = np.linalg.norm(np.diff(tracks.world.astype(np.float64), axis=0), axis=2).sum(0)
    np.testing.assert_allclose(tracks.path_length, steps, rtol=1e-9)
    assert tracks.path_length.min() > 0  # the fine stage moved them
    # the same seed gives the same sample; another seed another one
    again = compute_tracks(lambda t: cloud_at(model, t, meta.sh_degree), cam, times,
                           count=40, seed=3)
    np.testing.assert_array_equal(again.ids, tracks.ids)


def test_onnx_tracks_match_the_torch_run(tiny_run, tiny_run_model, tiny_onnx):
    from nehad.runtime.onnx_model import OnnxModel
    from nehad.model import cloud_at

    data, _ = tiny_run
    model, meta = tiny_run_model
    cam = load_view(f"{data}/transforms_test.json:0")
    times = track_times((0.0, 1.0), 5)
    a = compute_tracks(OnnxModel(tiny_onnx).gaussians, cam, times, count=50)
    b = compute_tracks(lambda t: cloud_at(model, t, meta.sh_degree), cam, times, ids=a.ids)
    np.testing.assert_allclose(a.world, b.world, rtol=0, atol=1e-5)


def test_select_prefers_movers_and_filters():
    cam = _camera()
    t, n = 4, 100
    rng = np.random.default_rng(0)
    base = rng.uniform(-0.5, 0.5, (n, 3))
    world = np.repeat(base[None], t, 0)
    movers = np.arange(10)
    world[:, movers, 0] += np.linspace(0, 0.3, t)[:, None]  # 10 Gaussians travel 0.3
    world[:, 50] = [0, 0, 10]  # behind the camera (z = 4 - 10 < 0): never a candidate
    opac = np.full(n, 0.9)
    opac[60] = 0.01
    ids = select_gaussians(world.astype(np.float32), opac, cam, 10, "moving", seed=1)
    np.testing.assert_array_equal(ids, movers)
    ids = select_gaussians(world.astype(np.float32), opac, cam, 15, "moving", seed=1)
    assert set(movers) <= set(ids) and len(ids) == 15
    ids = select_gaussians(world.astype(np.float32), opac, cam, 200, "random")
    assert 50 not in ids and 60 not in ids and len(ids) == n - 2
    with pytest.raises(VizError, match="mode"):
        select_gaussians(world, opac, cam, 5, "fastest")
    with pytest.raises(VizError, match="in view"):
        select_gaussians(world, np.zeros(n), cam, 5)


def test_draw_tracks_draws_the_path_and_nothing_else():
    t = np.array([0.0, 1.0])
    pixels = np.array([[[5.5, 10.5]], [[45.5, 10.5]]])
    tracks = Tracks(t, np.array([0]), np.zeros((2, 1, 3)), pixels, np.full((2, 1), 3.0),
                    np.array([1.0]))
    img = draw_tracks(np.ones((32, 64, 3), np.float32), tracks, heads=False, thickness=1)
    assert img.dtype == np.uint8 and img.shape == (32, 64, 3)
    changed = (img != 255).any(-1)
    assert changed[10, 8:43].all()  # the segment's row
    assert not changed[:7].any() and not changed[14:].any() and not changed[:, 50:].any()
    # behind the camera: nothing drawn
    behind = Tracks(t, np.array([0]), np.zeros((2, 1, 3)), pixels, np.full((2, 1), -1.0),
                    np.array([1.0]))
    assert (draw_tracks(np.ones((32, 64, 3)), behind) == 255).all()


def test_write_video_h264_yuv420p_odd_size(tmp_path):
    import av

    frames = [np.full((33, 47, 3), k * 20, np.uint8) for k in range(7)]
    out = tmp_path / "v.mp4"
    assert write_video(out, iter(frames), fps=12) == 7
    with av.open(str(out)) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == "h264" and s.codec_context.pix_fmt == "yuv420p"
        assert (s.width, s.height) == (48, 34)
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(decoded) == 7
    assert abs(float(decoded[5][:33, :47].mean()) - 100) < 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]
    with pytest.raises(VizError, match="no frames"):
        write_video(tmp_path / "e.mp4", iter([]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


# ---------------------------------------------------------------------------------------------
# BED masks


def test_bed_weights_equal_one_minus_m_pos_of_the_field(tiny_run_model):
    import torch

    from nehad.viz.masks import bed_weights

    model, _ = tiny_run_model
    g = model.gaussians
    sh = torch.cat([g.sh_dc, g.sh_rest], 1)
    for t in (0.0, 0.3, 0.5, 1.0):
        with torch.no_grad():
            out = model.field(g.means, g.log_scales, g.quats, t, g.mu_eq, g.t_eq,
                              opacity_logits=g.opacity_logits, sh=sh)
        want = 1.0 - out.aux["m_pos"].reshape(-1).numpy()
        np.testing.assert_allclose(bed_weights(model, t), want, rtol=0, atol=1e-6)


def test_bed_weights_match_the_formula_and_fraction(tiny_run_model):
    """An independent float64 evaluation of docs/design.md section 4.7 from the stored parameters."""
    from nehad.viz.masks import bed_weights, dynamic_fraction

    model, _ = tiny_run_model
    c = model.field.cfg
    g = model.gaussians
    mu, mu_eq = g.means.detach().double().numpy(), g.mu_eq.detach().double().numpy()
    t_eq = g.t_eq.detach().double().numpy().reshape(-1)
    sigma_s = c.sigma_s_fraction * float(model.field.extent)
    times = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    fracs = []
    for t in times:
        dd = np.sqrt(((mu - mu_eq) ** 2).sum(1) + c.norm_eps) / sigma_s
        dtau = (t - t_eq) / c.sigma_t
        e = 0.5 * (dd * dd + dtau * dtau) + c.lam * dd * dtau
        w = 1.0 - ((1 - c.gamma) * np.exp(-c.beta * e) + c.gamma)
        np.testing.assert_allclose(bed_weights(model, t), w, rtol=0, atol=1e-5)
        fracs.append((w > 0.5).mean())
    np.testing.assert_allclose(dynamic_fraction(model, times), fracs, atol=1e-9)
    # weights lie in [0, 1 - gamma]
    w = bed_weights(model, 0.0)
    assert w.min() >= -1e-6 and w.max() <= 1 - c.gamma + 1e-6


def test_runs_without_bed_are_refused(tiny_run_model):
    import dataclasses
    from types import SimpleNamespace

    from nehad.viz.masks import bed_status, bed_weights

    model, _ = tiny_run_model
    assert bed_status(model) is None
    for change, word in (({"bed_position": False}, "bed_position=false"),
                         ({"decoder": "mlp"}, "4DGS baseline")):
        cfg = dataclasses.replace(model.field.cfg, **change)
        other = SimpleNamespace(gaussians=model.gaussians,
                                field=SimpleNamespace(cfg=cfg, extent=model.field.extent))
        assert word in bed_status(other)
        with pytest.raises(VizError, match="no BED position mask"):
            bed_weights(other, 0.5)


def test_render_weights_recovers_the_weights():
    cam = _camera(64)
    rng = np.random.default_rng(1)
    left = rng.normal([-0.5, 0, 0], 0.08, (300, 3))
    right = rng.normal([0.5, 0, 0], 0.08, (300, 3))
    cloud = _cloud(np.concatenate([left, right]), scale=0.04)
    wmap, alpha = render_weights(cloud, np.full(600, 0.3), cam)
    seen = alpha > 0.05
    assert seen.sum() > 200
    np.testing.assert_allclose(wmap[seen], 0.3, atol=1e-5)
    assert np.isnan(wmap[alpha <= 1e-6]).all()
    # left static (0), right dynamic (0.95): the split shows on the two halves of the image
    w = np.r_[np.zeros(300), np.full(300, 0.95)]
    wmap, alpha = render_weights(cloud, w, cam)
    core = alpha > 0.5
    left_px = core & (np.arange(64)[None, :] < 28)
    right_px = core & (np.arange(64)[None, :] > 36)
    assert left_px.sum() > 50 and right_px.sum() > 50
    assert wmap[left_px].max() < 0.05 and wmap[right_px].min() > 0.9
    # scored against "the right cluster moves": near perfect
    uv, _ = cam.project(np.array([[0.5, 0, 0]]))
    yy, xx = np.mgrid[0:64, 0:64] + 0.5
    moving = (xx - uv[0, 0]) ** 2 + (yy - uv[0, 1]) ** 2 < 5.0 ** 2
    static_fg = ((xx - (64 - uv[0, 0])) ** 2 + (yy - uv[0, 1]) ** 2 < 5.0 ** 2)
    s = summarize([frame_counts(wmap, alpha, moving, static_fg)])
    assert s["precision"] > 0.95 and s["recall"] > 0.6 and s["iou"] > 0.6
    assert s["auc"] > 0.99 and s["mean_weight_moving"] > 0.9 and s["mean_weight_static"] < 0.05
    img = weight_image(wmap, alpha)
    assert img.shape[0] > 64 and img.shape[1] == 64  # the colour bar below
    assert img[32, 5].tolist() == [1.0, 1.0, 1.0]  # background stays white


def test_scores_from_known_masks():
    wmap = np.zeros((4, 5), np.float32)
    wmap[:, :2] = 0.9  # predicted dynamic: columns 0, 1 (8 px)
    alpha = np.ones((4, 5), np.float32)
    alpha[0, 0] = 0.2  # not covered: not predicted
    moving = np.zeros((4, 5), bool)
    moving[:, 1:3] = True  # truth: columns 1, 2 (8 px)
    static = ~moving
    c = frame_counts(wmap, alpha, moving, static)
    assert (c["tp"], c["fp"], c["fn"]) == (4, 3, 4)
    s = summarize([c, c])
    assert s["tp"] == 8 and s["iou"] == pytest.approx(8 / 22)
    assert s["precision"] == pytest.approx(8 / 14) and s["recall"] == pytest.approx(0.5)
    # AUC: moving weights {0.9 x4, 0 x4} vs static {0.9 x3 (one uncovered), 0 x8}
    assert s["auc"] == pytest.approx(((4 * 8 + 0.5 * 4 * 3) + 0.5 * 4 * 8) / (8 * 11))
    assert auc_from_histograms([0, 5], [5, 0]) == 1.0
    assert auc_from_histograms([1, 1], [1, 1]) == 0.5
    assert auc_from_histograms([0, 0], [1, 1]) is None
    with pytest.raises(VizError, match="ground truth"):
        frame_counts(wmap, alpha, moving[:3], static[:3])


def test_synth_ground_truth_and_scene_recognition(tiny_run):
    from nehad.data.dnerf import load_dnerf
    from nehad.viz.masks import (score_run, synth_ground_truth, synth_moving_objects,
                                 synth_scene_name)

    data, run = tiny_run
    frame = load_dnerf(data, splits=("test",)).frames["test"][0]
    assert synth_scene_name(frame) == "spheres"
    assert synth_moving_objects("spheres") == [False, True, True, True]  # "still" never moves
    moving, static = synth_ground_truth("spheres", frame.camera)
    assert moving.any() and static.any() and not (moving & static).any()
    assert not ((moving | static) & (frame.alpha < 0.05)).any()
    res = score_run(run, "test")
    assert res["ground_truth"].startswith("nehad synth") and res["frames"] == 1
    assert res["moving"] == ["mover", "spinner", "bouncer"] and res["static_objects"] == ["still"]
    s, f = res["summary"], res["per_frame"][0]
    assert s["moving_pixels"] == int(moving.sum())
    assert s["iou"] == pytest.approx(f["iou"]) and 0 <= s["auc"] <= 1


@pytest.mark.skipif(not (MUJOCO / "scene7_deformation").is_dir(), reason="no MuJoCo data")
def test_moving_objects_and_label_truth_on_mujoco():
    from nehad.data.dnerf import Frame
    from nehad.viz.masks import label_ground_truth, moving_object_ids, read_label_mask

    scene = MUJOCO / "scene7_deformation"
    found = moving_object_ids(scene)
    assert found["moving"] == [1, 2] and found["names"][2] == "cube"
    # the cube rests most of the time but is pushed: some pair of same-camera masks differs
    assert 0.05 < found["min_iou"][2] < 0.95 and found["min_iou"][1] < 0.05
    img = scene / "test" / "r_0000.png"
    labels = read_label_mask(scene / "test" / "masks" / "r_0000.png")
    cam = load_view(f"{scene}/transforms_test.json:0")
    alpha = np.ones(labels.shape, np.float32)
    moving, static = label_ground_truth(Frame(cam, None, alpha, img), [1], 800, 800)
    np.testing.assert_array_equal(moving, labels == 1)
    np.testing.assert_array_equal(static, labels != 1)
    half, _ = label_ground_truth(Frame(cam, None, alpha, img), [1], 400, 400)
    assert half.shape == (400, 400)
    assert abs(int(half.sum()) * 4 - int(moving.sum())) < 0.05 * moving.sum() + 50


# ---------------------------------------------------------------------------------------------
# plots


def test_line_plot_draws_series_where_they_are():
    img = line_plot([{"x": [0, 10], "y": [0, 0], "label": "flat", "color": (255, 0, 0)}],
                    size=(300, 200), ylim=(-1, 1), legend=False)
    assert img.shape == (200, 300, 3) and img.dtype == np.uint8
    red = (img[:, :, 0] > 200) & (img[:, :, 1] < 80) & (img[:, :, 2] < 80)
    rows = np.flatnonzero(red.any(1))
    assert len(rows) and rows.max() - rows.min() <= 3  # one horizontal line
    mid = (14 + (200 - 30)) / 2  # the middle of the plot area (y = 0 of [-1, 1])
    assert abs(rows.mean() - mid) < 2
    assert nice_ticks(0, 1, 5) == pytest.approx([0, 0.2, 0.4, 0.6, 0.8, 1.0])
    log = line_plot([{"x": [1, 2, 3], "y": [1e-3, 1e-2, 0.0]}], logy=True)  # 0 is skipped
    assert encode_png(log)[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------
# command line


def _ok(res):
    assert res.exit_code == 0, res.output
    return res.output


def _fails(res, *words):
    assert res.exit_code != 0
    assert "Traceback" not in res.output
    for w in words:
        assert w in res.output, res.output
    return res.output


def test_cli_trajectories_image_and_video(tiny_run, tiny_onnx, tmp_path):
    import av

    from nehad.runtime.images import read_image

    data, run = tiny_run
    runner = CliRunner()
    out = _ok(runner.invoke(main, ["viz", "trajectories", str(run), "-o", str(tmp_path / "t.png"),
                                   "--count", "50", "--size", "96x96"]))
    assert "50 Gaussians tracked over 32 times" in out
    img = read_image(tmp_path / "t.png")
    assert img.shape == (96, 96, 3) and img.std() > 0.01
    # the .onnx model, its default camera, a video
    out = _ok(runner.invoke(main, ["viz", "trajectories", str(tiny_onnx), "--video", "--times",
                                   "5", "-o", str(tmp_path / "t.mp4"), "--count", "20"]))
    assert "5 frames" in out
    with av.open(str(tmp_path / "t.mp4")) as c:
        assert sum(1 for _ in c.decode(video=0)) == 5
    _fails(runner.invoke(main, ["viz", "trajectories", str(run), "-o", str(tmp_path / "x.mp4")]),
           "-o", ".png")
    _fails(runner.invoke(main, ["viz", "trajectories", str(run), "--video", "-o",
                                str(tmp_path / "x.png")]), ".mp4")
    _fails(runner.invoke(main, ["viz", "trajectories", str(data / "points3d.ply"), "-o",
                                str(tmp_path / "x.png")]), "static")
    _fails(runner.invoke(main, ["viz", "trajectories", str(tmp_path / "nope"), "-o",
                                str(tmp_path / "x.png")]), "nope")
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "x.mp4").exists()


def test_cli_masks_render_plot_score(tiny_run, tiny_onnx, tmp_path):
    from nehad.runtime.images import read_image

    data, run = tiny_run
    runner = CliRunner()
    out = _ok(runner.invoke(main, ["viz", "masks", str(run), "--time", "0.1", "-o",
                                   str(tmp_path / "m.png"), "--plot", str(tmp_path / "f.png"),
                                   "--score", "--json", str(tmp_path / "s.json"),
                                   "--size", "64x64"]))
    assert "BED weights at t = 0.1" in out and "IoU" in out and "AUC" in out
    img = read_image(tmp_path / "m.png")
    assert img.shape[1] == 64 and img.shape[0] > 64
    assert read_image(tmp_path / "f.png").shape == (300, 640, 3)
    doc = json.loads((tmp_path / "s.json").read_text())
    assert set(doc["summary"]) >= {"iou", "precision", "recall", "auc", "mean_weight_moving"}
    assert doc["frames"] == 1 and len(doc["per_frame"]) == 1
    _fails(runner.invoke(main, ["viz", "masks", str(tiny_onnx), "--score"]),
           str(tiny_onnx), "training run", "no mask output")
    _fails(runner.invoke(main, ["viz", "masks", str(run)]), "nothing to do")
    _fails(runner.invoke(main, ["viz", "masks", str(run), "--score", "--moving-ids", "0"]),
           "--moving-ids")
    _fails(runner.invoke(main, ["viz", "masks", str(run), "--score", "--moving-ids", "1,99"]),
           "--moving-ids", "no object 99", "its objects: 1")  # (it scored 99 as never seen)
    _fails(runner.invoke(main, ["viz", "masks", str(run), "--score", "--data",
                                str(tmp_path / "gone")]), "gone")
    _fails(runner.invoke(main, ["viz", "masks", str(run), "-o", str(tmp_path / "m.gif")]),
           ".png")


def test_onnx_trajectories_without_torch(tiny_run, tiny_onnx, tmp_path):
    """An exported model needs no torch for trajectories (and .splat); a run says in one line
    that it does."""
    import subprocess
    import sys

    from torch_blocker import blocked_torch_env

    env = blocked_torch_env(tmp_path)
    cmd = [sys.executable, "-m", "nehad.cli.main"]
    res = subprocess.run(cmd + ["viz", "trajectories", str(tiny_onnx), "-o",
                                str(tmp_path / "t.png"), "--count", "20", "--times", "4"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "t.png").is_file()
    res = subprocess.run(cmd + ["viz", "masks", str(tiny_run[1]), "--score"], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == [
        f"Error: {tiny_run[1]}: the BED split needs torch to read a training run (pip install "
        f"-e '.[train]' torch==2.13.0)"]
