"""The spin prior (nehad.spin_prior): zero on a body that turns as its spin says, the square of
the miss otherwise, the selection by place, and a checkpoint round trip."""

import numpy as np
import torch

from nehad.spin import rotations
from nehad.spin_prior import SPIN_STEPS, SpinPrior


def _rotation(axis_angle):
    """Rodrigues' rotation matrix of a rotation vector, written out: the reference."""
    angle = float(np.linalg.norm(axis_angle))
    if angle < 1e-12:
        return np.eye(3)
    k = np.asarray(axis_angle, np.float64) / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


class _Gaussians:
    def __init__(self, n, mortal=None):
        self._mortal = torch.zeros(n, dtype=torch.bool) if mortal is None else mortal

    def mortal(self):
        return self._mortal


class _TurningModel:
    """Points that turn about `centre` at `omega` (rad per unit of time) times `factor`, from
    their places at t = 0."""

    def __init__(self, points, centre, omega, factor=1.0, mortal=None):
        self.points, self.centre = torch.as_tensor(points), torch.as_tensor(centre)
        self.omega, self.factor = np.asarray(omega, np.float64), factor
        self.gaussians = _Gaussians(len(points), mortal)

    def means_at(self, t, rows=None):
        turn = torch.as_tensor(_rotation(self.omega * self.factor * t))
        out = (self.points - self.centre) @ turn.T + self.centre
        return out if rows is None else out[rows]


def _prior(centre, omega, radius=1.0, spacing=0.01):
    prior = SpinPrior(weight=2.0, samples=64, seed=3)
    prior.spacing = spacing
    times = np.linspace(0.2, 0.8, 61)
    prior.bodies = [{"times": times, "points": np.tile(centre, (len(times), 1)),
                     "omega": np.asarray(omega, np.float64), "radius": radius}]
    return prior


def test_rotation_matches_the_spin_modules():
    w = np.array([0.3, -1.2, 2.0])
    assert np.allclose(_rotation(w), rotations(w[None])[0], atol=1e-12)


def test_zero_for_the_true_turn_and_the_miss_squared_otherwise():
    rng = np.random.default_rng(0)
    centre = np.array([0.5, -0.2, 0.3])
    pts = centre + rng.uniform(-0.5, 0.5, (200, 3)) * [1.0, 0.2, 0.2]
    omega = np.array([0.0, 0.0, 12.0])
    t = 0.5
    good = _TurningModel(pts, centre, omega)
    prior = _prior(centre, omega)
    assert float(prior.loss(good, good.means_at(t), t, step=0)) < 1e-10
    slow = _TurningModel(pts, centre, omega, factor=0.25)
    x0 = slow.means_at(t)
    got = float(prior.loss(slow, x0, t, step=0))
    # by hand: the rows within the radius, their spread about their mean at t and t + h
    h = SPIN_STEPS * prior.spacing
    rows = prior._pick(prior.bodies[0], x0, np.zeros(200, bool), t, 0, 0)[0]
    a, b = x0.numpy()[rows], slow.means_at(t + h).numpy()[rows]
    d0, d1 = a - a.mean(0), b - b.mean(0)
    want = 2.0 * np.mean(np.sum((d1 - d0 @ _rotation(omega * h).T) ** 2, 1))
    assert abs(got - want) <= 1e-9 * max(want, 1e-12) + 1e-12
    assert want > 1e-4  # a quarter of the turn misses by a measurable amount


def test_only_field_gaussians_near_the_path_inside_the_span():
    centre = np.array([0.0, 0.0, 0.0])
    pts = np.array([[0.05 * k, 0.05, 0.0] for k in range(20)] + [[3.0, 0.0, 0.0]] * 5)
    mortal = torch.zeros(25, dtype=torch.bool)
    mortal[0] = True
    model = _TurningModel(pts, centre, [0, 0, 5.0], mortal=mortal)
    prior = _prior(centre, [0, 0, 5.0], radius=0.55)
    x = model.means_at(0.5)
    rows, t2 = prior._pick(prior.bodies[0], x, mortal.numpy(), 0.5, 0, 0)
    assert list(rows) == list(range(1, 11))  # the mortal row and the far ones left out
    assert t2 == 0.5 + SPIN_STEPS * prior.spacing
    assert prior._pick(prior.bodies[0], x, mortal.numpy(), 0.79, 0, 0)[1] < 0.79  # back at the end
    assert prior._pick(prior.bodies[0], x, mortal.numpy(), 0.1, 0, 0)[0] is None  # outside
    assert prior.loss(model, x, 0.1, 0) == 0.0


def test_state_round_trip():
    prior = _prior(np.array([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0], radius=0.4)
    again = SpinPrior(weight=2.0)
    again.load_state_dict(prior.state_dict())
    assert again.spacing == prior.spacing and len(again.bodies) == 1
    for key in ("times", "points", "omega"):
        assert np.array_equal(again.bodies[0][key], prior.bodies[0][key])
    assert again.bodies[0]["radius"] == 0.4
    empty = SpinPrior(weight=1.0)
    empty.load_state_dict(None)
    assert empty.bodies == []
