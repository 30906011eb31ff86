"""The isometry prior (nehad.isometry) against hand-computed values and brute force."""

import math

import numpy as np
import torch
import torch.nn as nn

from nehad.gaussians import GaussianParameters
from nehad.isometry import REFRESH, IsometryPrior
from nehad.neighbours import nearest_neighbours


def _gaussians(points) -> GaussianParameters:
    return GaussianParameters.from_points(np.asarray(points, np.float32))


def _brute_force(pts, k):
    full = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(full, np.inf)
    return np.sort(full, axis=1)[:, :k]


def test_nearest_neighbours_match_brute_force():
    rng = np.random.default_rng(0)
    clouds = {"blob": rng.normal(size=(2000, 3)),
              "plane": np.c_[rng.uniform(-1, 1, (1500, 2)), np.zeros(1500)],
              "outliers": np.r_[0.05 * rng.normal(size=(1500, 3)),
                                rng.uniform(-50, 50, (20, 3))],
              "grid with ties": np.stack(np.meshgrid(*[np.arange(8.0)] * 3), -1).reshape(-1, 3)}
    for name, pts in clouds.items():
        j, d = nearest_neighbours(pts, 6)
        want = _brute_force(pts, 6)
        assert np.allclose(d, want, atol=1e-12), name
        assert np.allclose(np.linalg.norm(pts[j] - pts[:, None], axis=2), want), name
        assert not (j == np.arange(len(pts))[:, None]).any(), name
    j, d = nearest_neighbours(np.zeros((3, 3)), 8)  # k clipped to N - 1, coincident points
    assert j.shape == (3, 2) and not d.any()
    assert nearest_neighbours(np.zeros((1, 3)), 8)[0].shape == (1, 0)


def test_hand_computed_three_points():
    # a line of three points, spacing 1 and 2: each has the other 2 as neighbours
    g = _gaussians([[0, 0, 0], [1, 0, 0], [3, 0, 0]])
    prior = IsometryPrior(1.0, 2, local_scale=False)
    moved = torch.tensor([[0.0, 0, 0], [1.5, 0, 0], [3, 0, 0]])
    # pairs (i, j, d, |now - d|): (0,1,1,.5) (0,2,3,0) (1,0,1,.5) (1,2,2,.5) (2,1,2,.5) (2,0,3,0)
    d = np.array([1, 3, 1, 2, 2, 3.0])
    dev = np.array([0.5, 0, 0.5, 0.5, 0.5, 0])
    s = 2.0  # the lower median of the six distances
    a = np.exp(-0.5 * (d / s) ** 2)
    want = np.sum(a * dev) / (s * a.sum())
    assert math.isclose(float(prior.loss(g, moved, 0)), want, rel_tol=1e-5)


def test_rigid_and_scaled_motion_cost_nothing_tearing_does():
    rng = np.random.default_rng(1)
    pts = torch.from_numpy(rng.normal(size=(400, 3)).astype(np.float32))
    g = _gaussians(pts.numpy())
    c, s = math.cos(0.9), math.sin(0.9)
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local, fixed = IsometryPrior(1.0, 8, True), IsometryPrior(1.0, 8, False)
    assert float(local.loss(g, pts @ turn.T + 2.0, 0)) < 1e-5
    assert float(fixed.loss(g, pts @ turn.T + 2.0, 0)) < 1e-5
    assert float(local.loss(g, 3.0 * pts, 0)) < 1e-5  # a neighbourhood may grow whole
    assert float(fixed.loss(g, 3.0 * pts, 0)) > 1.0
    torn = pts + 0.3 * torch.from_numpy(rng.normal(size=(400, 3)).astype(np.float32))
    assert float(local.loss(g, torn, 0)) > 0.1


def _numpy_loss(canon, moved, k, local):
    """The module docstring's L_iso, written again with numpy and brute-force neighbours."""
    full = np.linalg.norm(canon[:, None] - canon[None], axis=2)
    np.fill_diagonal(full, np.inf)
    nbr = np.argsort(full, axis=1)[:, :k]
    d = np.take_along_axis(full, nbr, 1)
    now = np.linalg.norm(moved[:, None] - moved[nbr], axis=2)
    s = np.sort(d.ravel())[(d.size - 1) // 2]  # the lower median, as torch.median
    a = np.exp(-0.5 * (d / s) ** 2)
    m = (a * d * now).sum(1) / (a * d * d).sum(1) if local else np.ones(len(canon))
    return np.sum(a * np.abs(now - m[:, None] * d)) / (s * a.sum())


def test_loss_and_gradient_match_a_numpy_reference():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(60, 3))
    moved = pts @ rng.normal(size=(3, 3)) + 0.1 * rng.normal(size=pts.shape)
    g = _gaussians(pts)
    for local in (True, False):
        prior = IsometryPrior(1.0, 4, local)
        x = torch.from_numpy(moved).double().requires_grad_(True)
        prior.loss(g, x, 0)  # finds the pairs (float32 canonical distances)
        prior.pairs = tuple(p.double() if p.is_floating_point() else p for p in prior.pairs)
        value = prior.loss(g, x, 1)
        want = _numpy_loss(pts.astype(np.float32).astype(np.float64), moved, 4, local)
        assert math.isclose(float(value.detach()), want, rel_tol=1e-5), local
        value.backward()
        eps, num = 1e-6, np.zeros(pts.shape)
        for r in range(pts.shape[0]):
            for c in range(3):
                xp, xm = moved.copy(), moved.copy()
                xp[r, c] += eps
                xm[r, c] -= eps
                num[r, c] = (_numpy_loss(pts.astype(np.float32).astype(np.float64), xp, 4, local)
                             - _numpy_loss(pts.astype(np.float32).astype(np.float64), xm, 4,
                                           local)) / (2 * eps)
        assert np.allclose(x.grad.numpy(), num, atol=1e-6, rtol=1e-4), local


def test_mortal_gaussians_take_no_part_and_pairs_follow_the_set():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(50, 3)).astype(np.float32)
    g = _gaussians(pts)
    with torch.no_grad():
        g.life_rate[:10] = 5.0  # a chain's members
    prior = IsometryPrior(1.0, 4)
    prior.loss(g, g.means.detach(), 0)
    i, j = prior.pairs[0], prior.pairs[1]
    assert int(torch.minimum(i, j).min()) >= 10
    far = g.means.detach().clone()
    far[:10] += 100.0  # moving the mortal rows costs nothing
    assert float(prior.loss(g, far, 1)) < 1e-5
    # densification replaces the means' parameter: the pairs are searched again at once
    g.means = nn.Parameter(torch.from_numpy(pts[:30].copy()))
    g.life_rate = nn.Parameter(torch.zeros(30, 1))
    prior.loss(g, g.means.detach(), 3)
    assert int(prior.pairs[0].max()) < 30 and prior._found_at == 3
    prior.loss(g, g.means.detach(), REFRESH - 1)
    assert prior._found_at == 3
    prior.loss(g, g.means.detach(), REFRESH)  # and at every multiple of the refresh
    assert prior._found_at == REFRESH


def test_off_costs_nothing():
    g = _gaussians(np.zeros((5, 3)))
    assert IsometryPrior(0.0, 8).loss(g, g.means, 0) == 0.0


def test_coincident_gaussians_give_finite_values_and_gradients():
    # densification's clones sit exactly on their parent: d = 0 and, unmoved, |x| = 0
    rng = np.random.default_rng(4)
    pts = np.repeat(rng.normal(size=(20, 3)), 2, axis=0)
    pts[::7] = 0.0  # a row whose every neighbour is coincident too
    g = _gaussians(pts)
    for local in (True, False):
        x = torch.from_numpy(pts.astype(np.float32)).requires_grad_(True)
        value = IsometryPrior(1.0, 3, local).loss(g, x, 0)
        value.backward()
        assert torch.isfinite(value) and torch.isfinite(x.grad).all()


def test_reference_time_keeps_the_distances_of_the_step_that_found_the_pairs():
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(200, 3)).astype(np.float32)
    g = _gaussians(pts)  # canonical = pts
    at_t = torch.from_numpy(pts * np.array([1.0, 2.0, 0.5], np.float32))  # not a similarity
    prior = IsometryPrior(1.0, 6, local_scale=True, reference="time", refresh=50)
    assert float(prior.loss(g, at_t, 1)) < 1e-5  # the pairs and distances of at_t itself
    c, s = math.cos(1.1), math.sin(1.1)
    turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    assert float(prior.loss(g, at_t @ turn.T - 1.0, 49)) < 1e-5  # the same shape, turned
    assert float(prior.loss(g, torch.from_numpy(pts), 49)) > 0.05  # the canonical shape
    prior.loss(g, torch.from_numpy(pts), 50)  # a multiple of the refresh: the pairs anew
    assert float(prior.loss(g, torch.from_numpy(pts), 51)) < 1e-5
    canonical = IsometryPrior(1.0, 6, local_scale=True)
    assert float(canonical.loss(g, torch.from_numpy(pts), 0)) < 1e-5


def test_the_refresh_must_divide_the_checkpoint_interval():
    from nehad.config import build_config
    from nehad.configtools import ConfigError

    build_config("cpu", None, ["loss.isometry_weight=0.1", "loss.isometry_refresh=250"])
    try:
        build_config("cpu", None, ["loss.isometry_weight=0.1", "loss.isometry_refresh=300"])
    except ConfigError as e:
        assert "loss.isometry_refresh: 300 must divide train.checkpoint_interval (1000)" in str(e)
    else:
        raise AssertionError("a refresh that does not divide the checkpoint interval passed")
    build_config("cpu", None, ["loss.isometry_refresh=300"])  # off: nothing to resume
