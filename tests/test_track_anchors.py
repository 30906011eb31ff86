"""Track anchors (nehad.track_anchors, `carve.anchor_weight`): the rows an anchored track gives,
the loss against a hand-computed miss, a field trained on the loss alone carrying the anchor
along the track, and the state a checkpoint keeps."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.track_anchors import TrackAnchors  # noqa: E402
from nehad.tracks import Track  # noqa: E402


def _track(blobs: int = 20, t0: float = 0.2, t1: float = 0.8) -> Track:
    """A straight path x(t) = (t, 2t, -t) sampled at `blobs` times in [t0, t1]."""
    times = np.linspace(t0, t1, blobs)
    points = np.stack([times, 2 * times, -times], 1)
    blob = SimpleNamespace(colour=np.array([0.9, 0.4, 0.1]), area=10)
    return Track(blobs=[blob] * blobs, times=times, points=points,
                 velocities=np.tile([1.0, 2.0, -1.0], (blobs, 1)))


def test_a_long_track_gives_one_row_per_frame_step_at_its_canonical_place():
    anchors = TrackAnchors(weight=1.0, min_blobs=12, canonical_time=0.5)
    mu = anchors.add(_track(), spacing=0.05, size=0.1)
    np.testing.assert_allclose(mu, [0.5, 1.0, -0.5])
    assert len(anchors.times) == 13  # 0.2, 0.25, ..., 0.8
    np.testing.assert_allclose(anchors.targets, np.stack(
        [anchors.times, 2 * anchors.times, -anchors.times], 1), atol=1e-12)
    np.testing.assert_allclose(anchors.points, np.tile(mu, (13, 1)))
    # the canonical time outside the span: the nearest end's place
    late = TrackAnchors(weight=1.0, min_blobs=12, canonical_time=0.95)
    np.testing.assert_allclose(late.add(_track(), 0.05, 0.1), [0.8, 1.6, -0.8])


def test_an_anchor_is_ready_for_its_gaussians_at_the_next_pass():
    anchors = TrackAnchors(weight=1.0, min_blobs=1)
    assert len(anchors.ready()) == 0
    mu = anchors.add(_track(), 0.05, 0.1)
    ready = anchors.ready()
    assert ready.shape == (1, 7)
    np.testing.assert_allclose(ready[0, :3], mu)
    np.testing.assert_allclose(ready[0, 3:6], [0.9, 0.4, 0.1])
    assert ready[0, 6] == 0.1 and len(anchors.ready()) == 0  # handed out once


def test_short_tracks_and_weight_zero_are_not_anchored():
    assert TrackAnchors(weight=1.0, min_blobs=12).add(_track(blobs=11), 0.05, 0.1) is None
    off = TrackAnchors(weight=0.0)
    assert off.add(_track(), 0.05, 0.1) is None and off.loss(None, 0) == 0.0


def test_the_loss_is_the_mean_squared_miss_over_the_extent():
    """A stand-in field that moves every point by a fixed d: the loss is w |mu + d - x(t)|^2
    averaged over the sampled rows, over the extent squared, computed by hand."""
    anchors = TrackAnchors(weight=0.5, samples=1000, min_blobs=1, canonical_time=0.5)
    anchors.add(_track(), spacing=0.05, size=0.1)
    d = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    model = SimpleNamespace(gaussians=SimpleNamespace(means=torch.zeros(1, 3, dtype=torch.float64)),
                            field=lambda mu, *rest: SimpleNamespace(means=mu + d))
    model.field.extent = 2.0
    expected = np.mean(np.sum((anchors.points + d.numpy() - anchors.targets) ** 2, 1)) / 4.0
    assert float(anchors.loss(model, step=3)) == pytest.approx(0.5 * expected, rel=1e-12)


def test_a_field_trained_on_the_loss_alone_carries_the_anchor_along_the_track():
    """The test preset's field, trained by Adam on L_anchor only: its anchor's deformed place
    follows the track at the track's times (before training it stays near mu)."""
    from nehad.config import build_config
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    torch.manual_seed(0)
    cfg = build_config("test")
    field = DeformationField(cfg.field, aabb=np.array([[-1.5] * 3, [1.5] * 3]), extent=3.0)
    gauss = GaussianParameters(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]),
                               torch.zeros(1, 1), torch.zeros(1, 1, 3), torch.zeros(1, 3, 3))
    model = NeHaDModel(gauss, field)
    anchors = TrackAnchors(weight=1.0, samples=64, min_blobs=1, canonical_time=0.5)
    anchors.add(_track(), spacing=0.05, size=0.05)

    def miss() -> float:
        with torch.no_grad():
            n = len(anchors.times)
            out = field(torch.tensor(anchors.points, dtype=torch.float32),
                        torch.full((n, 3), float(np.log(0.05))),
                        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                        torch.tensor(anchors.times, dtype=torch.float32)[:, None])
        return float((out.means - torch.tensor(anchors.targets, dtype=torch.float32))
                     .norm(dim=1).max())

    before = miss()
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    for step in range(300):
        opt.zero_grad()
        anchors.loss(model, step).backward()
        opt.step()
    after = miss()
    assert before > 0.25  # the path spans 0.6 x (1, 2, -1) about mu
    assert after < 0.25 * before, (before, after)


def test_the_state_round_trips():
    anchors = TrackAnchors(weight=1.0, min_blobs=1)
    anchors.add(_track(), 0.05, 0.1)
    again = TrackAnchors(weight=1.0, min_blobs=1)
    again.load_state_dict(anchors.state_dict())
    for name in ("points", "times", "targets", "sizes", "waiting"):
        np.testing.assert_array_equal(getattr(again, name), getattr(anchors, name))
    again.load_state_dict(None)  # a checkpoint written without anchors keeps them
    assert len(again.times) == len(anchors.times)
