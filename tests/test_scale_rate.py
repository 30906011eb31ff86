"""The slow-size prior (nehad.scale_rate): its value against hand-computed sizes, a steady growth
against a blink, the same draw for the same step, and its gradient reaching the field."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.scale_rate import ScaleRatePrior  # noqa: E402


class _Sizes:
    """A stand-in model: Gaussian i has log-scales a_i + b_i t at time t (or what `law` says);
    its field is called with per-row times, as the prior calls it."""

    def __init__(self, n: int = 40, seed: int = 0, law=None):
        rng = np.random.default_rng(seed)
        self.a, self.b = (torch.tensor(rng.normal(size=(n, 3))) for _ in range(2))
        self.law = law or (lambda rows, t: self.a[rows] + self.b[rows] * t)
        z = torch.zeros((n, 3), dtype=torch.float64)
        self.gaussians = SimpleNamespace(means=torch.arange(n, dtype=torch.float64)[:, None] + z,
                                         log_scales=z, quats=torch.zeros((n, 4)),
                                         mu_eq=z, t_eq=torch.zeros((n, 1)))
        self.calls = []

    def field(self, means, log_scales, quats, t, mu_eq, t_eq):
        rows = means[:, 0].long()  # the stand-in's means carry each row's index
        self.calls.append(t.reshape(-1).clone())
        return SimpleNamespace(log_scales=self.law(rows, t.reshape(-1, 1)))


def _prior(weight=0.5, samples=16, times=np.linspace(0.0, 1.0, 11), pair="uniform"):
    prior = ScaleRatePrior(weight, samples, seed=5, times=pair)
    prior.set_times(times)
    return prior


def test_value_is_the_mean_squared_change_over_one_step():
    """log s(c + h) - log s(c) = b h for a steady change: the loss is w mean |b_i|^2 h^2 over
    the drawn rows, h the views' step (0.1 here), c in [t_min, t_max - h]."""
    model, prior = _Sizes(), _prior()
    assert prior.step_h == pytest.approx(0.1)
    loss = prior.loss(model, step=9)
    rows, c = prior.draw(40, 9)
    want = 0.5 * float((model.b[rows] ** 2).sum(dim=1).mean()) * 0.1 ** 2
    assert float(loss) == pytest.approx(want, rel=1e-9)
    times = model.calls[0]
    assert 0.0 <= c <= 0.9 and times.shape == (32,)
    assert torch.allclose(times[:16], torch.tensor(c, dtype=times.dtype))
    assert torch.allclose(times[16:], torch.tensor(c + 0.1, dtype=times.dtype))


def test_paired_with_the_view_one_step_before_or_after_it():
    """`times="view"`: the pair is the view's t and t +- h (h = 0.1 here), inside the training
    times at their ends; a steady change costs w mean |b_i|^2 h^2 as with uniform times, and the
    prior's own call deforms the drawn rows at t, then at the neighbour time."""
    model, prior = _Sizes(), _prior(pair="view")
    rows, _ = prior.draw(40, 9)
    want = 0.5 * float((model.b[rows] ** 2).sum(dim=1).mean()) * 0.1 ** 2
    assert float(prior.loss(model, step=9, t=0.4)) == pytest.approx(want, rel=1e-9)
    times = model.calls[-1]
    assert times.shape == (32,) and torch.all(times[:16] == 0.4)
    assert float(abs(times[16] - 0.4)) == pytest.approx(0.1) and torch.all(times[16:] == times[16])
    both = sorted({round(prior.neighbour_time(0.4, s), 9) for s in range(40)})
    assert both == [0.3, 0.5]
    assert {round(prior.neighbour_time(0.0, s), 9) for s in range(20)} == {0.1}
    assert {round(prior.neighbour_time(1.0, s), 9) for s in range(20)} == {0.9}
    picked_rows, picked_times = prior.rows_and_times(40, 9, t=0.4)
    assert torch.equal(picked_rows, rows) and picked_times.shape == (16,)  # one row per sample
    with pytest.raises(ValueError, match="give t"):
        prior.rows_and_times(40, 9)


def test_a_blink_costs_far_more_than_a_steady_growth():
    """A Gaussian that grows 4x over the whole time pays (ln 4 h)^2 per axis; one that shrinks
    10x between two frames (and grows back) pays (ln 10)^2 where the step meets the blink. With
    the MuJoCo scenes' step (1/120) that is 10^4 times the growth's cost."""
    h = 1.0 / 120
    steady = _Sizes(n=1, law=lambda rows, t: np.log(4.0) * t.expand(-1, 3))
    blink = _Sizes(n=1, law=lambda rows, t: -np.log(10.0) * ((t > 0.45) & (t < 0.55)).double()
                   .expand(-1, 3))
    prior = _prior(weight=1.0, samples=1, times=np.linspace(0.0, 1.0, 121))
    grow = float(prior.loss(steady, step=0))
    assert grow == pytest.approx(3 * (np.log(4.0) * h) ** 2, rel=1e-9)
    costs = [float(prior.loss(blink, step=s)) for s in range(400)]
    assert max(costs) == pytest.approx(3 * np.log(10.0) ** 2, rel=1e-9)
    assert max(costs) > 1e4 * grow


def test_same_draw_for_the_same_step_and_off_cases():
    model, prior = _Sizes(), _prior()
    assert float(prior.loss(model, step=4)) == float(prior.loss(model, step=4))
    assert float(prior.loss(model, step=4)) != float(prior.loss(model, step=5))
    assert _prior(weight=0.0).loss(model, step=1) == 0.0
    assert _prior(times=[0.3]).loss(model, step=1) == 0.0  # one time: no step


def _moving_model(n: int = 64, dtype=torch.float32, hnn_grad: str | None = None,
                  overrides=()):
    """A real model whose field moves (its adapters start at zero, and its time planes at 1: no
    change in time)."""
    from nehad.config import build_config
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    cfg = build_config("test", None,
                       [*([f"field.hnn_grad={hnn_grad}"] if hnn_grad else []), *overrides])
    torch.manual_seed(0)
    field = DeformationField(cfg.field, aabb=np.array([[-1.0] * 3, [1.0] * 3]), extent=2.0)
    with torch.no_grad():
        for p in field.adapters.parameters():
            p.normal_(0.0, 0.1)
        for p in field.hexplane.parameters():
            p.uniform_(0.1, 1.0)
    gauss = GaussianParameters(torch.rand(n, 3) * 2 - 1, torch.rand(n, 3) - 3.0,
                               torch.nn.functional.normalize(torch.randn(n, 4), dim=1),
                               torch.randn(n, 1), torch.randn(n, 1, 3), torch.randn(n, 15, 3))
    gauss.mu_eq.data = gauss.means.data + 0.05 * torch.randn(n, 3)
    gauss.t_eq.data = torch.rand(n, 1)
    return NeHaDModel(gauss, field).to(dtype)


@pytest.mark.parametrize("appearance", [False, True])
@pytest.mark.parametrize("pair", ["uniform", "view"])
def test_samples_in_the_views_evaluation_equal_a_call_of_their_own(pair, appearance):
    """`gaussians_and_samples_at` (one field evaluation of N + M rows) gives the view's
    Gaussians as `gaussians_at` does and the samples as the prior's own call does, and the
    loss's gradient on every parameter is the same (float64); paired with the view, its own
    rows are the pairs' first half. With the field deforming opacities and SH too, and
    without (they then do not go through the field)."""
    model = _moving_model(dtype=torch.float64, hnn_grad="closed_form",
                          overrides=[f"field.deform_opacity_sh={str(appearance).lower()}"])
    prior = _prior(weight=1.0, samples=24, pair=pair)
    rows, times = prior.rows_and_times(64, step=3, t=0.37)
    assert len(times) == (24 if pair == "view" else 48)
    view, sampled = model.gaussians_and_samples_at(0.37, rows, times,
                                                   with_view_rows=pair == "view")
    for a, b in zip(view, model.gaussians_at(0.37)):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    folded = prior.loss(model, 3, sampled, t=0.37)
    grads = torch.autograd.grad(folded, list(model.parameters()), allow_unused=True)
    own = prior.loss(model, 3, t=0.37)
    assert float(own.detach()) > 0
    assert float(folded.detach()) == pytest.approx(float(own.detach()), rel=1e-12)
    for g, w in zip(grads, torch.autograd.grad(own, list(model.parameters()), allow_unused=True)):
        assert (g is None) == (w is None)
        if g is not None:
            assert torch.allclose(g, w, rtol=1e-9, atol=1e-12)
    assert sum(g is not None and float(g.abs().sum()) > 0 for g in grads) >= 3


def test_gradient_reaches_the_field():
    """On a real field, the prior's gradient reaches the hex-plane and the decoder."""
    model = _moving_model()
    field = model.field
    prior = _prior(weight=1.0, samples=32)
    loss = prior.loss(model, step=2)
    loss.backward()
    assert float(loss.detach()) > 0
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0
               for p in field.hexplane.parameters())
    assert float(field.adapters.scale.weight.grad.abs().sum()) > 0


@pytest.mark.parametrize("pair", ["uniform", "view"])
def test_training_runs_with_it_and_the_term_is_in_the_loss(tmp_path, monkeypatch, pair):
    """A short run with the prior on: the trainer calls it at every deforming step only, and the
    run ends with a finite loss."""
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.trainer import Trainer

    data = synthesize_scene(tmp_path / "scene", resolution=24, frames=8, seed=0)
    cfg = build_config("test", None, ["loss.scale_rate_weight=1.0",
                                      "loss.scale_rate_samples=64",
                                      f"loss.scale_rate_times={pair}"])
    tr = Trainer(cfg, data, tmp_path / "run", progress=False, log=None)
    assert tr.priors.scale_rate.step_h == pytest.approx(1 / 7)
    steps = []
    inner = tr.priors.scale_rate.loss
    monkeypatch.setattr(tr.priors.scale_rate, "loss", lambda model, step, deformed, t:
                        steps.append((step, deformed is not None))
                        or inner(model, step, deformed, t))
    out = tr.train()
    assert out["steps"] == 70 and np.isfinite(out["last"]["loss"])
    deforming = out["steps"] - cfg.coarse.iterations
    assert len(steps) == deforming > 0
    assert all(folded for _, folded in steps)  # the samples rode on the view's evaluation
