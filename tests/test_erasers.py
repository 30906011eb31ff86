"""The prior against erasers (nehad.erasers): its value against a hand-computed sum, its pull
on the opacity alone, the chains left out, other backgrounds, and off at weight 0."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.erasers import WIDTH, EraserPrior  # noqa: E402
from nehad.gaussians import GaussianParameters  # noqa: E402


def _cloud(colours, opacities, mortal=()):
    n = len(colours)
    g = GaussianParameters.from_points(np.zeros((n, 3), np.float32),
                                       np.asarray(colours, np.float32), opacity=0.5)
    with torch.no_grad():
        p = torch.tensor(opacities, dtype=torch.float32)
        g.opacity_logits.copy_(torch.log(p / (1 - p)).reshape(g.opacity_logits.shape))
        for i in mortal:
            g.life_rate[i] = 3.0
    return g


def test_value_is_the_hand_computed_sum_and_pulls_only_on_opacity():
    colours = [[1.0, 1.0, 1.0], [0.95, 0.95, 0.95], [1.0, 0.9, 1.0], [0.5, 0.2, 0.1]]
    opacities = [0.8, 0.5, 0.3, 0.9]
    g = _cloud(colours, opacities)
    w = 2e-3
    loss = EraserPrior(w).loss(g)
    near = [1.0, math.exp(-3 * 0.05 ** 2 / (2 * WIDTH ** 2)), math.exp(-0.01 / (2 * WIDTH ** 2)),
            math.exp(-(0.25 + 0.64 + 0.81) / (2 * WIDTH ** 2))]
    want_loss = w * sum(a * o for a, o in zip(near, opacities))
    assert float(loss.detach()) == pytest.approx(want_loss, rel=1e-5)
    loss.backward()
    dlogit = g.opacity_logits.grad.reshape(-1).numpy()
    want = [w * a * o * (1 - o) for a, o in zip(near, opacities)]
    np.testing.assert_allclose(dlogit, want, rtol=1e-4, atol=1e-12)
    assert g.sh_dc.grad is None  # the colour's weight is held: erasers fade, not recolour
    assert dlogit[3] < 1e-12 < dlogit[2] < dlogit[1] < dlogit[0]


def test_chains_take_no_part_and_the_background_is_the_runs():
    g = _cloud([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], [0.5, 0.5, 0.5], mortal=(1,))
    assert float(EraserPrior(1.0).loss(g).detach()) == pytest.approx(0.5, rel=1e-5)  # row 0 only
    black = EraserPrior(1.0, background=(0.0, 0.0, 0.0))
    assert float(black.loss(g).detach()) == pytest.approx(0.5, rel=1e-5)  # row 2 only


def test_off_at_weight_zero():
    g = _cloud([[1.0, 1.0, 1.0]], [0.9])
    assert EraserPrior(0.0).loss(g) == 0.0


def test_the_cpu_presets_trainer_priors_hold_the_weight_and_the_runs_background():
    from nehad.config import build_config
    from nehad.motion_priors import MotionPriors

    cfg = build_config("cpu")
    assert cfg.loss.eraser_weight == 2e-6 and build_config("quick").loss.eraser_weight == 0.0
    priors = MotionPriors.of(cfg.loss, 0, np.linspace(0.0, 1.0, 5), None, 0.5, (0.0, 0.0, 0.0))
    assert priors.erasers.weight == 2e-6
    assert priors.erasers.background.tolist() == [0.0, 0.0, 0.0]
