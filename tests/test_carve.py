"""Residual carving (nehad.carve): points where several views agree something is missing, on
ray-cast scenes whose geometry is known."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.carve import carve_points, new_gaussians, seed_rays, unexplained_mask  # noqa: E402
from nehad.data.synth import Box, Sphere, render_view  # noqa: E402
from nehad.data.synth_stress import rig_camera  # noqa: E402

SIZE = 64
BOX = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])


def _cams(ids=range(12)):
    return [rig_camera(i, SIZE) for i in ids]


def _views(objects, cams):
    """Targets over white, and their alpha."""
    out = [render_view(objects, c, supersample=2) for c in cams]
    return [o[..., :3] + (1.0 - o[..., 3:]) for o in out], [o[..., 3] for o in out]


def test_missing_sphere_is_carved_where_it_is():
    sphere = Sphere("s", np.array([0.3, -0.2, 0.5]), 0.25, (0.9, 0.4, 0.1))
    cams = _cams()
    targets, alphas = _views([sphere], cams)
    blank = [np.ones_like(t) for t in targets]  # the model draws nothing yet
    pts, cols, widths, n_bad = carve_points(cams, targets, alphas, blank, BOX)
    assert n_bad > 0 and len(pts) >= 20
    d = np.linalg.norm(pts - sphere.centre, axis=1)
    # every carved point lies on the sphere, up to the 1-pixel match tolerance (7 cm at the
    # cameras' 5 m) and the 4 cm between depth samples; most lie on or in it
    assert np.all(d <= sphere.radius + 0.12), d.max()
    assert np.median(d) <= sphere.radius + 0.02
    assert np.all(widths > 0) and np.allclose(cols.mean(0), [0.9, 0.4, 0.1], atol=0.35)


def test_seeded_rays_pass_through_the_missing_object():
    """Ray seeding (carve.mode=rays): every seed lies on the ray of an unexplained pixel of the
    seeding view (it projects back onto the object's silhouette), the seeds of a ray span the
    box in depth, and the seed of each ray nearest the sphere is within one depth spacing of
    its surface (the optimisation then keeps that one)."""
    sphere = Sphere("s", np.array([0.3, -0.2, 0.5]), 0.25, (0.9, 0.4, 0.1))
    cams = _cams([0])
    targets, alphas = _views([sphere], cams)
    blank = [np.ones_like(t) for t in targets]
    depths = 32
    pts, cols, widths, n_bad = seed_rays(cams, targets, alphas, blank, BOX, stride=1,
                                         depth_samples=depths, max_rays=10_000)
    n_rays = len(pts) // depths
    assert n_bad == n_rays == int((alphas[0] >= 0.5).sum()) > 20
    uv, z = cams[0].project(pts)
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    assert np.all(z > 0) and np.all(alphas[0][v, u] >= 0.5)
    per_ray = np.linalg.norm(pts - sphere.centre, axis=1).reshape(n_rays, depths)
    spacing = float(np.linalg.norm(BOX[1] - BOX[0])) / depths  # the longest chord / samples
    assert np.all(per_ray.min(axis=1) <= sphere.radius + spacing), per_ray.min(axis=1).max()
    assert np.all(per_ray.max(axis=1) > 1.0)  # the other seeds of a ray are far from it
    assert np.allclose(cols.mean(0), [0.9, 0.4, 0.1], atol=0.35) and np.all(widths > 0)
    none = seed_rays(cams, targets, alphas, targets, BOX)  # nothing missing: nothing seeded
    assert none[3] == 0 and len(none[0]) == 0


def test_nothing_missing_nothing_carved():
    sphere = Sphere("s", np.array([0.3, -0.2, 0.5]), 0.25, (0.9, 0.4, 0.1))
    cams = _cams()
    targets, alphas = _views([sphere], cams)
    pts, _, _, n_bad = carve_points(cams, targets, alphas, targets, BOX)
    assert n_bad == 0 and len(pts) == 0


def test_views_that_see_a_drawn_occluder_do_not_veto():
    """A small sphere behind a wall from half the rig: with the renders' depth the views that
    see the (correctly drawn) wall in front of it are not counted, and it is still carved;
    without it they vote against and it is lost."""
    wall = Box("wall", np.array([0.0, 0.0, 0.75]), np.array([0.06, 1.1, 0.75]), np.eye(3),
               (0.2, 0.3, 0.9))
    sphere = Sphere("s", np.array([-0.6, 0.0, 0.4]), 0.15, (1.0, 0.55, 0.1))
    cams = _cams()
    targets, alphas = _views([wall, sphere], cams)
    drawn_wall = [render_view([wall], c, supersample=2) for c in cams]
    renders = [o[..., :3] + (1.0 - o[..., 3:]) for o in drawn_wall]
    # the render's depth where the wall is drawn: ray cast it
    depths = []
    for c, o in zip(cams, drawn_wall):
        v, u = np.mgrid[0:SIZE, 0:SIZE]
        dirs = np.stack([(u + 0.5 - c.cx) / c.fx, (v + 0.5 - c.cy) / c.fy, np.ones(u.shape)], -1)
        world = dirs @ c.camera_to_world[:3, :3].T
        # the wall's x = +-0.06 slab: depth along the camera z of the hit
        ox = c.centre[0]
        s_hit = (np.sign(ox) * 0.06 - ox) / np.where(np.abs(world[..., 0]) < 1e-9, 1e-9,
                                                     world[..., 0])
        depths.append(np.where(o[..., 3] > 0.5, s_hit, 0.0).astype(np.float32))
    alphas_drawn = [o[..., 3] for o in drawn_wall]
    hidden_somewhere = sum((a > 0.5)[tuple(np.clip(c.project(sphere.centre[None])[0][0, ::-1]
                                                   .astype(int), 0, SIZE - 1))]
                           for a, c in zip(alphas_drawn, cams))
    assert hidden_somewhere >= 3  # the scene does hide the sphere from several cameras
    kw = dict(agree=0.8)
    with_depth = carve_points(cams, targets, alphas, renders, BOX, render_alphas=alphas_drawn,
                              render_depths=depths, **kw)[0]
    without = carve_points(cams, targets, alphas, renders, BOX, **kw)[0]
    near = lambda p: int((np.linalg.norm(p - sphere.centre, axis=1) < sphere.radius + 0.08).sum())
    assert near(with_depth) >= 10
    assert near(without) < near(with_depth) // 2


def test_motion_allowance_follows_a_moving_object():
    """The sphere moves between views taken at different times: with the motion allowance it is
    carved near where the reference view saw it, with none it is not."""
    cams = _cams(range(6))
    times = np.arange(6) * 0.01
    objs = [[Sphere("s", np.array([0.6 * t * 10 - 0.3, 0.0, 0.4]), 0.12, (0.2, 0.8, 0.3))]
            for t in times]
    out = [_views(o, [c]) for o, c in zip(objs, cams)]
    targets, alphas = [o[0][0] for o in out], [o[1][0] for o in out]
    blank = [np.ones_like(t) for t in targets]
    moving = carve_points(cams, targets, alphas, blank, BOX, times, motion=3.0)[0]
    frozen = carve_points(cams, targets, alphas, blank, BOX, times, motion=0.0)[0]
    assert len(moving) > len(frozen)
    assert len(moving) >= 5


def test_unexplained_mask_and_new_gaussians_shapes():
    import torch

    from nehad.gaussians import GaussianParameters

    r = np.zeros((4, 4, 3))
    t = np.zeros((4, 4, 3))
    t[1, 1] = 0.5
    a = np.ones((4, 4))
    a[1, 1] = 0.2  # background in the target: never unexplained
    t[2, 2] = 0.6
    m = unexplained_mask(r, t, a, 0.25)
    assert m.sum() == 1 and m[2, 2]
    like = GaussianParameters.from_points(np.zeros((3, 3)), sh_degree=1)
    new = new_gaussians(np.ones((2, 3)), np.full((2, 3), 0.5), np.array([0.1, 0.2]), 0.3, like,
                        0.3)
    for name in like.NAMES:
        assert new[name].shape[1:] == getattr(like, name).shape[1:], name
    assert torch.allclose(torch.sigmoid(new["opacity_logits"]), torch.tensor(0.3))
    assert torch.allclose(new["t_eq"], torch.tensor(0.3)) and torch.equal(new["mu_eq"],
                                                                          new["means"])


@pytest.mark.parametrize("mode", ["vote", "rays", "tracks"])
def test_a_training_run_carves_and_stays_consistent(tmp_path, mode):
    """carve.every > 0 in a run (any carve.mode): passes are logged, Gaussians are added (the
    test scene's cloud is random and sparse; "tracks": blobs are found, Gaussians added when
    they make a track), the densification statistics keep the Gaussians' count, and the run
    finishes and reloads."""
    import json

    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.model import load_run
    from nehad.trainer import Trainer

    data = synthesize_scene(tmp_path / "scene", resolution=32, frames=12, points=0, seed=3)
    sets = [f"carve.mode={mode}", "carve.every=10", "carve.views=4", "train.init=random",
            "coarse.iterations=30",
            "fine.iterations=30", "train.log_interval=10", "densify.max_gaussians=900"]
    trainer = Trainer(build_config("test", None, sets), data, tmp_path / "run", progress=False)
    trainer.train()
    log = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    passes = [r for r in log if "carved" in r]
    if mode == "tracks":
        assert passes and sum(r["carve_blobs"] for r in passes) > 0
        assert all(r["carved"] == 0 or r["carve_tracks"] > 0 for r in passes)
    else:
        assert passes and sum(r["carved"] for r in passes) > 0
    assert all(r["gaussians"] <= 900 for r in log)
    assert len(trainer.densify_state.grad_accum) in (0, len(trainer.model.gaussians))
    model, _ = load_run(tmp_path / "run")
    assert len(model.gaussians) == len(trainer.model.gaussians)


def test_no_static_stage_passes_when_asked(tmp_path):
    """carve.static_stage=false: carving passes run in the deforming stage only."""
    import json

    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.trainer import Trainer

    data = synthesize_scene(tmp_path / "scene", resolution=32, frames=12, points=0, seed=3)
    log = {}
    for static in ("true", "false"):
        sets = ["carve.every=10", "carve.views=4", "train.init=random", "coarse.iterations=30",
                "fine.iterations=30", "train.log_interval=10", f"carve.static_stage={static}"]
        run = tmp_path / f"run_{static}"
        Trainer(build_config("test", None, sets), data, run, progress=False).train()
        records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        log[static] = {r["stage"] for r in records if "carved" in r}
    assert log["true"] == {"coarse", "fine"} and log["false"] == {"fine"}


def test_life_factor_and_immortal_gaussians_stay_immortal():
    """GaussianParameters.life_factor against the formula; a Gaussian with k = 0 has a zero
    gradient in k (it stays immortal under any loss), one with k > 0 does not."""
    from nehad.gaussians import GaussianParameters

    g = GaussianParameters.random_in_box(4, sh_degree=0)
    assert g.life_factor(0.3) is None  # every k = 0: no factor at all
    with torch.no_grad():
        g.life_rate[:2] = torch.tensor([[10.0], [40.0]])
        g.t_eq[:] = torch.tensor([[0.5], [0.2], [0.5], [0.9]])
    f = g.life_factor(0.3)
    expect = torch.exp(-0.5 * (torch.tensor([10.0, 40.0, 0.0, 0.0]) * (0.3 - g.t_eq.reshape(-1)))**2)
    assert torch.allclose(f, expect)
    assert float(f[0].detach()) == pytest.approx(float(np.exp(-0.5 * 4.0)), rel=1e-6)
    (f * torch.arange(1.0, 5.0)).sum().backward()
    grad = g.life_rate.grad.reshape(-1)
    assert float(grad[2]) == 0.0 and float(grad[3]) == 0.0
    assert float(grad[0]) < 0.0  # a longer life (smaller k) raises this loss's opacity sum


def test_drift_moves_only_mortal_gaussians():
    """GaussianParameters.drift = v (t - t_eq) for Gaussians with k > 0, 0 for the others (and
    their velocity's gradient is 0, so it stays 0); a model's means at t carry it."""
    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    g = GaussianParameters.random_in_box(3, sh_degree=0)
    with torch.no_grad():
        g.velocity[:] = torch.tensor([[1.0, -2.0, 0.5], [3.0, 0.0, 0.0], [4.0, 4.0, 4.0]])
    assert g.drift(0.8) is None  # no Gaussian has a life: none drifts
    with torch.no_grad():
        g.life_rate[:2] = 20.0
        g.t_eq[:] = torch.tensor([[0.5], [0.7], [0.1]])
    d = g.drift(0.8)
    expect = torch.tensor([[0.3, -0.6, 0.15], [0.3, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert torch.allclose(d, expect, atol=1e-6)
    (d * torch.randn(3, 3)).sum().backward()
    assert torch.all(g.velocity.grad[2] == 0) and torch.any(g.velocity.grad[0] != 0)
    field = DeformationField(FieldConfig(), np.array([[-2.0] * 3, [2.0] * 3]), 4.0)
    model = NeHaDModel(g, field)  # a fresh field is the identity: the means are mu + drift
    with torch.no_grad():
        means = model.gaussians_at(0.8)[0]
    assert torch.allclose(means, g.means + expect, atol=1e-5)


def test_drift_window_moves_every_gaussian_clamped():
    """With a drift window W (train.drift_window) every Gaussian drifts v clamp(t - t_eq, -W, W),
    whatever its life, and every velocity learns; the model's means carry it."""
    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    g = GaussianParameters.random_in_box(3, sh_degree=0)
    g.drift_window = 0.1
    with torch.no_grad():
        g.velocity[:] = torch.tensor([[1.0, -2.0, 0.5], [3.0, 0.0, 0.0], [4.0, 4.0, 4.0]])
        g.t_eq[:] = torch.tensor([[0.5], [0.75], [0.9]])
    d = g.drift(0.8)  # t - t_eq = 0.3 (clamped to 0.1), 0.05, -0.1
    expect = torch.tensor([[0.1, -0.2, 0.05], [0.15, 0.0, 0.0], [-0.4, -0.4, -0.4]])
    assert torch.allclose(d, expect, atol=1e-6)
    (d * torch.randn(3, 3)).sum().backward()
    assert all(torch.any(g.velocity.grad[i] != 0) for i in range(3))
    field = DeformationField(FieldConfig(), np.array([[-2.0] * 3, [2.0] * 3]), 4.0)
    model = NeHaDModel(g, field)
    with torch.no_grad():
        assert torch.allclose(model.gaussians_at(0.8)[0], g.means + expect, atol=1e-5)
        assert torch.allclose(model.gaussians_at(0.8, deform=False)[0], g.means + expect,
                              atol=1e-6)  # the static stage's render drifts too


def test_state_saved_before_life_rate_loads_immortal():
    """A checkpoint written before the life rate existed loads with k = 0 for every Gaussian."""
    from nehad.gaussians import GaussianParameters

    g = GaussianParameters.random_in_box(5, sh_degree=0)
    state = {k: v for k, v in g.state_dict().items() if k != "life_rate"}
    h = GaussianParameters.empty_like_state(state)
    h.load_state_dict(GaussianParameters.with_defaults(state))
    assert h.life_rate.shape == (5, 1) and not h.has_life()


def test_van_der_corput_passes_cover_the_window_evenly():
    """The fine stage's carving times: any first n passes leave no gap wider than 2 / n."""
    from nehad.carve_pass import van_der_corput

    for n in (4, 7, 16, 33):
        pts = np.sort([0.0, 1.0] + [van_der_corput(i) for i in range(1, n + 1)])
        assert np.diff(pts).max() <= 2.0 / n + 1e-12
    assert [van_der_corput(i) for i in (1, 2, 3, 4)] == [0.5, 0.25, 0.75, 0.125]


def test_opacity_reset_spares_gaussians_with_a_finite_life():
    """An opacity reset caps every opacity at 0.01 except those of Gaussians that live around
    one time (nehad.densify: a few views see them; a reset would have them pruned)."""
    from nehad.densify import DensifyStrategy
    from nehad.gaussians import GaussianParameters

    g = GaussianParameters(torch.zeros(4, 3), torch.zeros(4, 3), torch.tensor([[1.0, 0, 0, 0]] * 4),
                           torch.full((4, 1), 2.0), torch.zeros(4, 1, 3), torch.zeros(4, 0, 3))
    with torch.no_grad():
        g.life_rate[2] = 50.0
    opt = torch.optim.Adam(g.parameters())
    DensifyStrategy._reset_opacity(g, opt, frozen=1)
    alpha = torch.sigmoid(g.opacity_logits.detach()).reshape(-1)
    assert torch.allclose(alpha[[1, 3]], torch.tensor(0.01))
    assert torch.allclose(alpha[[0, 2]], torch.sigmoid(torch.tensor(2.0)))  # frozen; mortal


def test_pinned_gaussians_keep_place_motion_time_and_life():
    """carve.pin (nehad.carve_pass.pin_mortal): after backward, the Gaussians with a finite life
    get no gradient on their place, velocity, time and life, so Adam leaves them where the
    track put them, while their colour, opacity and shape still learn and the others move."""
    from nehad.carve_pass import pin_mortal
    from nehad.gaussians import GaussianParameters

    g = GaussianParameters(torch.randn(3, 3), torch.zeros(3, 3), torch.tensor([[1.0, 0, 0, 0]] * 3),
                           torch.zeros(3, 1), torch.zeros(3, 1, 3), torch.zeros(3, 0, 3))
    with torch.no_grad():
        g.life_rate[1] = 20.0
    before = {n: getattr(g, n).detach().clone() for n in g.NAMES}
    opt = torch.optim.Adam(g.parameters(), lr=0.1)
    for _ in range(3):
        opt.zero_grad()
        loss = sum((getattr(g, n) - 1.0).square().sum() for n in g.NAMES)
        loss.backward()
        pin_mortal(g)
        opt.step()
    for n in ("means", "velocity", "t_eq", "life_rate", "mu_eq"):
        assert torch.equal(getattr(g, n).detach()[1], before[n][1]), n
        assert not torch.equal(getattr(g, n).detach()[0], before[n][0]), n
    for n in ("sh_dc", "opacity_logits", "log_scales"):
        assert not torch.equal(getattr(g, n).detach()[1], before[n][1]), n


def _chain_scene():
    """A sphere moving along x, seen at training times 0.1 .. 0.5 and at held-out times midway;
    rows 0-4: a chain on it, one member per training time living sigma = 0.03 around it,
    moving with the sphere; row 5: a wrong copy 0.8 m beside it, living at every time."""
    from nehad.runtime.gaussians import GaussianCloud
    from nehad.views import Views

    path = lambda t: np.array([-0.5 + 2.0 * t, 0.0, 0.5])  # noqa: E731
    held = [0.15, 0.25, 0.35, 0.45]
    cams = _cams(range(len(held)))
    targets = [_views([Sphere("s", path(t), 0.2, (0.9, 0.4, 0.1))], [c])[0][0]
               for t, c in zip(held, cams)]
    views = Views(cams, [torch.from_numpy(np.ascontiguousarray(t, np.float32)) for t in targets],
                  held, [None] * len(held))
    t_eq = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.0])
    rates = np.array([1 / 0.03] * 5 + [0.0])
    sh = np.zeros((6, 1, 3), np.float32)
    sh[:, 0] = (np.array([0.9, 0.4, 0.1]) - 0.5) / 0.28209479177387814

    def cloud_of(t):  # the life windows left out, as chain_lives asks
        means = np.stack([path(t)] * 5 + [path(t) + [0.0, 0.8, 0.0]]).astype(np.float32)
        return GaussianCloud(means, np.full((6, 3), 0.15, np.float32),
                             np.tile(np.float32([1, 0, 0, 0]), (6, 1)),
                             np.full(6, 0.95, np.float32), sh.copy())
    return views, t_eq, rates, cloud_of


def _held_out_error(views, t_eq, rates, cloud_of, life) -> float:
    """The summed squared error of `views` with the rows' lives multiplied by `life` (0: off)."""
    from nehad.runtime.raster import render

    total = 0.0
    for k, t in enumerate(views.times):
        cloud = cloud_of(t)
        sigma = np.where(rates > 0, life / np.maximum(rates, 1e-12), np.inf)
        cloud.opacities[:] = np.where(life > 0, 0.95 * np.exp(-0.5 * ((t - t_eq) / sigma) ** 2),
                                      0.0)
        total += float(np.square(render(cloud, views.cameras[k], (1.0, 1.0, 1.0)).rgb
                                 - views.images[k].numpy()).sum())
    return total


def test_the_check_drops_a_wrong_chain_and_lengthens_the_trained_members_lives():
    """chain_lives against brute force: the wrong copy is dropped (the held-out views are
    closer without it), and the chain's life factor is the one of the candidates that gives
    the held-out views, midway between its members, the lowest error, here longer than 1
    (at 1 each member is at 0.25 of its opacity there)."""
    from nehad.chain_check import DROPPED, chain_lives

    views, t_eq, rates, cloud_of = _chain_scene()
    chains = [np.arange(5), np.array([5])]
    factors = (1.0, 1.5, 2.0, 3.0)
    life = chain_lives(chains, t_eq, rates, cloud_of, views, (1.0, 1.0, 1.0), factors)
    assert life[5] == DROPPED
    assert (_held_out_error(views, t_eq, rates, cloud_of, np.array([1.0] * 5 + [0.0]))
            < _held_out_error(views, t_eq, rates, cloud_of, np.ones(6)))
    errors = [_held_out_error(views, t_eq, rates, cloud_of, np.array([f] * 5 + [0.0]))
              for f in factors]
    assert np.all(life[:5] == factors[int(np.argmin(errors))]) and life[0] > 1.0
    assert min(errors) < errors[0] - 1.0  # the longer life is worth it, not a tie
    keep_or_drop = chain_lives(chains, t_eq, rates, cloud_of, views, (1.0, 1.0, 1.0))
    np.testing.assert_array_equal(keep_or_drop, [1.0] * 5 + [DROPPED])
    untrained = chain_lives(chains, t_eq, rates, cloud_of, views, (1.0, 1.0, 1.0), factors,
                            trained=np.array([True, False, True, False, True, True]))
    assert np.all(untrained[[1, 3]] == 1.0)  # only the trained rows are lengthened


def test_trained_rows_are_those_a_training_view_sees_within_a_life_sigma():
    from nehad.chain_check import trained_rows

    train_times = np.array([0.0, 0.1, 0.2, 0.6])
    t_eq = np.array([0.1, 0.2 + 0.1, 0.4, 0.6 - 0.1, 0.35])
    rates = np.array([10.0, 10.0, 10.0, 10.0, 0.0])  # sigma 0.1; the last lives at every time
    np.testing.assert_array_equal(trained_rows(t_eq, rates, train_times),
                                  [True, True, False, True, True])


def test_untrained_members_take_their_trained_neighbours_appearance():
    """fill_untrained against a hand-computed case: a member between two trained ones gets
    their time-weighted mean, members beyond the last trained one its values, trained members
    keep theirs; with no trained member nothing changes."""
    from nehad.chain_check import fill_untrained

    times = np.array([0.0, 0.1, 0.4, 0.2, 0.5, 0.6])
    trained = np.array([True, False, True, False, False, True])
    values = np.array([[0.0, 10.0], [9.0, 9.0], [3.0, 4.0], [9.0, 9.0], [9.0, 9.0],
                       [5.0, 0.0]])
    out = fill_untrained(times, trained, values)
    expect = values.copy()
    expect[1] = 0.75 * values[0] + 0.25 * values[2]  # t 0.1 between 0.0 and 0.4
    expect[3] = 0.5 * values[0] + 0.5 * values[2]  # t 0.2
    expect[4] = 0.5 * values[2] + 0.5 * values[5]  # t 0.5 between 0.4 and 0.6
    np.testing.assert_allclose(out, expect)
    tail = fill_untrained(np.array([0.0, 0.1, 0.2]), np.array([True, False, False]), values[:3])
    np.testing.assert_allclose(tail, values[[0, 0, 0]])
    none = fill_untrained(times, np.zeros(6, bool), values)
    np.testing.assert_array_equal(none, values)


def test_a_chain_splits_into_its_trained_core_and_its_two_ends():
    """core_and_ends against a hand-made chain: the core spans the first to the last trained
    member (untrained ones between included) and is judged only between their times; the
    members before and after are the two ends; a chain with no trained member is one piece."""
    from nehad.chain_check import core_and_ends

    t_eq = np.array([0.50, 0.10, 0.20, 0.30, 0.40, 0.00, 0.90])
    trained = np.array([False, True, False, True, False, False, True])
    pieces = core_and_ends(np.array([0, 1, 2, 3, 4, 5]), t_eq, trained)
    (core, span), (head, head_span), (tail, tail_span) = pieces
    np.testing.assert_array_equal(core, [1, 2, 3])
    assert span == (0.10, 0.30) and head_span is None and tail_span is None
    np.testing.assert_array_equal(head, [5])
    np.testing.assert_array_equal(tail, [0, 4])
    alone = core_and_ends(np.array([0, 2, 4]), t_eq, trained)
    assert len(alone) == 1 and alone[0][1] is None
    np.testing.assert_array_equal(alone[0][0], [0, 2, 4])


def test_a_chain_its_training_views_made_transparent_is_trained_away():
    """`trained_away` against hand-made chains: one whose trained members are all under
    AWAY_OPACITY (its untrained member opaque) is; one with a trained member at the bound, one
    with no trained member and one fully transparent but untrained are not; with every row
    trained, the fully transparent one is, and the first is not (its member at 0.98)."""
    from nehad.chain_check import AWAY_OPACITY, trained_away

    assert AWAY_OPACITY == 0.05
    chains = [np.array([0, 1, 2]), np.array([3, 4]), np.array([5, 6]), np.array([7])]
    trained = np.array([True, True, False, True, False, False, False, False])
    opacity = np.array([0.01, 0.049, 0.98, 0.05, 0.9, 0.9, 0.9, 0.0])
    assert trained_away(chains, trained, opacity) == [0]
    assert trained_away(chains, np.ones(8, bool), opacity) == [3]
