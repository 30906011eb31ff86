"""The smooth-motion prior (nehad.acceleration): its value against hand-computed paths, the
centre moved inside the training times, the same draw for the same step, and a short training
run with it on."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.acceleration import AccelerationPrior  # noqa: E402


class _Paths:
    """A stand-in model: Gaussian i at x_i(t) = p_i + v_i t + g_i t^2 / 2 (constant
    acceleration g_i), with field.extent 2."""

    def __init__(self, n: int = 50, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.p, self.v, self.g = (torch.tensor(rng.normal(size=(n, 3))) for _ in range(3))
        self.field = SimpleNamespace(extent=torch.tensor(2.0))
        self.calls = []

    def at(self, t: float) -> torch.Tensor:
        return self.p + self.v * t + 0.5 * self.g * t * t

    def means_at(self, t: float, rows):
        self.calls.append(float(t))
        return self.at(t)[rows]


def _prior(weight=0.5, samples=20, times=np.linspace(0.0, 1.0, 11)):
    prior = AccelerationPrior(weight, samples, seed=3)
    prior.set_times(times)
    return prior


def test_value_is_the_mean_second_difference():
    """x(c + h) - 2 x(c) + x(c - h) = g h^2 exactly for a constant acceleration: the loss is
    w mean |g_i| h^2 / extent over the drawn rows, with h the views' step (0.1 here)."""
    model, prior = _Paths(), _prior()
    assert prior.step_h == pytest.approx(0.1)
    loss = prior.loss(model, model.at(0.4), 0.4, step=7)
    rows = torch.randperm(50, generator=torch.Generator().manual_seed(3 * 1_000_003 + 7))[:20]
    want = 0.5 * float(model.g[rows].norm(dim=1).mean()) * 0.1 ** 2 / 2.0
    assert float(loss) == pytest.approx(want, rel=1e-9)
    assert model.calls == [pytest.approx(0.5), pytest.approx(0.3)]  # x(c) is the step's row


def test_straight_paths_cost_nothing_and_a_bounce_costs_its_turn():
    model = _Paths()
    model.g.zero_()
    assert float(_prior().loss(model, model.at(0.5), 0.5, step=1)) < 1e-9

    class Bounce(_Paths):  # one Gaussian falls at speed 1 and comes back up at t = 0.5
        def at(self, t):
            return torch.tensor([[0.0, 0.0, abs(t - 0.5)]], dtype=torch.float64)

    b = Bounce(n=1)
    # h = 0.1: (0.1 - 0 + 0.1) at the turn -> 0.2; w 1, extent 2 -> 0.1 (not squared)
    assert float(_prior(weight=1.0).loss(b, b.at(0.5), 0.5, step=0)) == pytest.approx(0.1)


def test_centre_moved_inside_the_training_times():
    """At the first and last view the three times move inside [t_min + h, t_max - h]: x(c) is
    then evaluated, not taken from the step's deformed means."""
    model, prior = _Paths(), _prior(times=[0.2, 0.3, 0.4, 0.6, 0.7])  # h = 0.1
    wrong = torch.full((50, 3), 1e6, dtype=torch.float64)  # never read at the ends
    loss = prior.loss(model, wrong, 0.2, step=0)
    assert sorted(model.calls) == pytest.approx([0.2, 0.3, 0.4])
    assert float(loss) < 10
    model.calls.clear()
    prior.loss(model, wrong, 0.7, step=0)
    assert sorted(model.calls) == pytest.approx([0.5, 0.6, 0.7])


def test_uniform_times_reach_the_gaps():
    """`times="uniform"`: the centre is drawn in [t_min + h, t_max - h] whatever the view's time,
    and x(c) is evaluated; the value is still w mean |g_i| h^2 / extent."""
    model = _Paths()
    prior = AccelerationPrior(0.5, 20, seed=3, times="uniform")
    prior.set_times(np.linspace(0.0, 1.0, 11))
    centres = set()
    for step in range(20):
        model.calls.clear()
        loss = prior.loss(model, model.at(0.0), 0.0, step=step)
        lo, mid, hi = sorted(model.calls)
        assert 0.1 - 1e-12 <= mid <= 0.9 + 1e-12
        assert (lo, hi) == (pytest.approx(mid - 0.1), pytest.approx(mid + 0.1))
        centres.add(round(mid, 6))
        rows = torch.randperm(50, generator=torch.Generator().manual_seed(3 * 1_000_003
                                                                           + step))[:20]
        want = 0.5 * float(model.g[rows].norm(dim=1).mean()) * 0.01 / 2.0
        assert float(loss) == pytest.approx(want, rel=1e-9)
    assert len(centres) == 20  # a fresh time each step


def test_same_step_same_draw_and_off_or_too_short_is_zero():
    model, prior = _Paths(n=500), _prior(samples=10)
    a = prior.loss(model, model.at(0.5), 0.5, step=11)
    b = prior.loss(model, model.at(0.5), 0.5, step=11)
    c = prior.loss(model, model.at(0.5), 0.5, step=12)
    assert float(a) == float(b) and float(a) != float(c)
    assert _prior(weight=0.0).loss(model, model.at(0.5), 0.5, 1) == 0.0
    assert _prior(times=[0.3]).loss(model, model.at(0.3), 0.3, 1) == 0.0  # no step
    assert _prior(times=[0.3, 0.4]).loss(model, model.at(0.3), 0.3, 1) == 0.0  # span < 2h


def test_a_real_model_matches_its_own_deformed_means():
    """With a real model the prior's x(t) rows are the rows `gaussians_at` renders."""
    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    torch.manual_seed(0)
    n = 64
    g = GaussianParameters(torch.randn(n, 3) * 0.3, torch.full((n, 3), -3.0),
                           torch.nn.functional.normalize(torch.randn(n, 4), dim=1),
                           torch.zeros(n, 1), torch.rand(n, 1, 3), torch.zeros(n, 15, 3))
    cfg = FieldConfig(resolution=(8, 8, 8, 4), out_dim=8, multires=(1,), width=16,
                      hnn_hidden=16)
    model = NeHaDModel(g, DeformationField(cfg, torch.tensor([[-1.0] * 3, [1.0] * 3])))
    with torch.no_grad():  # move the field off the identity, and make it depend on t (the
        for p in model.field.adapters.parameters():  # time planes start at 1)
            p.normal_(0, 0.3)
        for p in model.field.hexplane.parameters():
            p.add_(torch.randn(p.shape) * 0.3)
    rows = torch.tensor([3, 17, 40])
    full = model.gaussians_at(0.37)[0]
    assert torch.allclose(model.means_at(0.37, rows), full[rows], atol=1e-6)
    prior = _prior(weight=1.0, samples=n)
    loss = prior.loss(model, full, 0.37, step=0)
    loss.backward()
    assert float(loss.detach()) > 0
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0
               for p in model.field.parameters())


def test_training_runs_with_it(tmp_path):
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.trainer import Trainer

    data = synthesize_scene(tmp_path / "scene", resolution=24, frames=8, seed=0)
    cfg = build_config("test", None, ["loss.acceleration_weight=1.0",
                                      "loss.acceleration_samples=64"])
    tr = Trainer(cfg, data, tmp_path / "run", progress=False, log=None)
    assert tr.priors.acceleration.step_h == pytest.approx(1 / 7)
    out = tr.train()
    assert out["steps"] == 70 and np.isfinite(out["last"]["loss"])
