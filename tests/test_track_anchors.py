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


def test_a_track_that_continues_an_anchored_one_extends_its_path():
    """Two pieces of the straight path (0.2-0.6 and 0.5-0.9) make one anchor whose rows cover
    0.2-0.9 once; a piece of another path overlapping in time makes a second anchor. With
    `cover` 0.9 an anchor waits for its Gaussians until its path covers 90% of the range."""
    anchors = TrackAnchors(weight=1.0, min_blobs=1, canonical_time=0.5)
    mu = anchors.add(_track(t0=0.2, t1=0.6, blobs=9), spacing=0.05, size=0.1)
    again = anchors.add(_track(t0=0.5, t1=0.9, blobs=9), spacing=0.05, size=0.1)
    np.testing.assert_array_equal(again, mu)
    taus, pts = anchors.path_of(mu)
    np.testing.assert_allclose(taus, np.arange(0.2, 0.9 + 1e-9, 0.05), atol=1e-12)
    np.testing.assert_allclose(pts, np.stack([taus, 2 * taus, -taus], 1), atol=1e-12)
    assert len(anchors.waiting) == 1 and anchors.covered(mu, 0.05) == pytest.approx(0.75)
    other = _track(t0=0.3, t1=0.7, blobs=9)
    other.points = other.points + np.array([0.0, 0.0, 0.5])  # 0.5 away, five radii
    assert not np.array_equal(anchors.add(other, 0.05, 0.1), mu)
    assert len(anchors.waiting) == 2
    assert len(anchors.ready((0.0, 1.0), 0.05, cover=0.9)) == 0  # 0.75 and 0.45 of 1.0
    anchors.add(_track(t0=0.0, t1=0.25, blobs=6), spacing=0.05, size=0.1)  # now 0.0-0.9
    got = anchors.ready((0.0, 1.0), 0.05, cover=0.9)
    assert len(got) == 1 and np.array_equal(got[0, :3], mu) and len(anchors.waiting) == 1


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


def _trained_field(volume: float = 0.0, size: float = 0.05, steps: int = 300):
    """The test preset's field trained by Adam on L_anchor alone for the straight track, and
    the anchors; with the field before training as a third item."""
    import copy

    from nehad.config import build_config
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    torch.manual_seed(0)
    cfg = build_config("test")
    field = DeformationField(cfg.field, aabb=np.array([[-1.5] * 3, [1.5] * 3]), extent=3.0)
    untrained = copy.deepcopy(field)
    gauss = GaussianParameters(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]),
                               torch.zeros(1, 1), torch.zeros(1, 1, 3), torch.zeros(1, 3, 3))
    model = NeHaDModel(gauss, field)
    anchors = TrackAnchors(weight=1.0, samples=64, min_blobs=1, canonical_time=0.5, volume=volume)
    anchors.add(_track(), spacing=0.05, size=size)
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    for step in range(steps):
        opt.zero_grad()
        anchors.loss(model, step).backward()
        opt.step()
    return field, anchors, untrained


def _miss(field, anchors, offset=(0.0, 0.0, 0.0)) -> float:
    """The largest distance, over the track's rows, between the point anchor + `offset` moved
    by the field and the track's point + `offset`."""
    with torch.no_grad():
        n = len(anchors.times)
        out = field(torch.tensor(anchors.points + np.asarray(offset), dtype=torch.float32),
                    torch.full((n, 3), float(np.log(0.05))),
                    torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                    torch.tensor(anchors.times, dtype=torch.float32)[:, None])
    want = torch.tensor(anchors.targets + np.asarray(offset), dtype=torch.float32)
    return float((out.means - want).norm(dim=1).max())


def test_a_field_trained_on_the_loss_alone_carries_the_anchor_along_the_track():
    """The field trained on L_anchor alone: its anchor's deformed place follows the track at the
    track's times (before training it stays near mu)."""
    field, anchors, untrained = _trained_field()
    before, after = _miss(untrained, anchors), _miss(field, anchors)
    assert before > 0.25  # the path spans 0.6 x (1, 2, -1) about mu
    assert after < 0.25 * before, (before, after)


def test_with_a_volume_the_points_about_the_anchor_follow_the_track_too():
    """`carve.anchor_volume`: trained on points spread over a ball of the object's radius (0.4
    here, more than one cell of the test preset's hex-plane), the field carries points 0.3 from
    the anchor along the track; trained on the anchor alone it does not (it moves them less
    well by more than twice)."""
    offsets = [(0.3, 0, 0), (0, -0.3, 0), (0, 0, 0.3), (-0.2, 0.2, -0.1)]
    point, anchors, _ = _trained_field(volume=0.0, size=0.4)
    ball, _, _ = _trained_field(volume=1.0, size=0.4)
    at_point = max(_miss(point, anchors, o) for o in offsets)
    in_ball = max(_miss(ball, anchors, o) for o in offsets)
    assert in_ball < 0.5 * at_point, (in_ball, at_point)
    assert in_ball < 0.1, in_ball


def test_a_released_anchor_leaves_the_loss_when_its_gaussians_are_added():
    """`carve.anchor_release`: the loss samples only the rows of anchors without Gaussians."""
    d = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    model = SimpleNamespace(gaussians=SimpleNamespace(means=torch.zeros(1, 3, dtype=torch.float64)),
                            field=lambda mu, *rest: SimpleNamespace(means=mu + d))
    model.field.extent = 2.0
    anchors = TrackAnchors(weight=1.0, samples=1000, min_blobs=1, release=True)
    first = anchors.add(_track(), 0.05, 0.1)
    other = _track()
    other.points = other.points + np.array([0.0, 0.0, 1.0])
    anchors.add(other, 0.05, 0.1)
    both = float(anchors.loss(model, 0))
    anchors.ready()  # both get their Gaussians: both released
    assert both > 0.0 and anchors.loss(model, 1) == 0.0
    kept = TrackAnchors(weight=1.0, samples=1000, min_blobs=1)  # without release
    kept.add(_track(), 0.05, 0.1)
    kept.ready()
    assert float(kept.loss(model, 0)) > 0.0
    assert len(anchors.released) == 2 and np.array_equal(anchors.released[0], first)


def test_the_state_round_trips():
    anchors = TrackAnchors(weight=1.0, min_blobs=1, release=True)
    anchors.add(_track(), 0.05, 0.1)
    anchors.ready()
    again = TrackAnchors(weight=1.0, min_blobs=1)
    again.load_state_dict(anchors.state_dict())
    for name in ("points", "times", "targets", "sizes", "waiting", "released"):
        np.testing.assert_array_equal(getattr(again, name), getattr(anchors, name))
    again.load_state_dict(None)  # a checkpoint written without anchors keeps them
    assert len(again.times) == len(anchors.times)


def test_near_path_finds_the_points_on_the_anchored_path_at_their_own_times():
    """The path x(t) = (t, 2t, -t) over [0.2, 0.8]; radius 0.1, so the reach is 0.2."""
    anchors = TrackAnchors(weight=1.0, min_blobs=1, canonical_time=0.5)
    mu = anchors.add(_track(), spacing=0.05, size=0.1)
    times = np.array([0.3, 0.6, 0.6, 0.6, 0.86, 0.1])
    on = np.stack([times, 2 * times, -times], 1)
    means = on + np.array([[0, 0, 0], [0.15, 0, 0], [0.25, 0, 0], [0, 0, 0], [0, 0, 0],
                           [0, 0, 0]])
    means[3] = [0.3, 0.6, -0.3]  # the path's place at 0.3, not at its own time 0.6
    got = anchors.near_path(mu, 0.1, means, times, spacing=0.05)
    # in reach; 0.15 off; 0.25 off; elsewhere on the path; 0.06 past the span's end (more
    # than one spacing); before the span
    assert got.tolist() == [True, True, False, False, False, False]
    other = anchors.near_path(mu + 1.0, 0.1, means, times, 0.05)  # no such anchor
    assert not other.any()


def test_replacing_removes_only_the_chain_gaussians_on_an_anchored_path():
    """`carve.anchor_replace`: of four Gaussians on the path (two with a finite life) and one
    with a finite life off it, only the two mortal ones on it go, the densification
    statistics and the optimizer's rows with them."""
    from nehad.carve_pass import ResidualCarving
    from nehad.densify import DensifyState
    from nehad.gaussians import GaussianParameters

    anchors = TrackAnchors(weight=1.0, min_blobs=1, canonical_time=0.5)
    mu = anchors.add(_track(), spacing=0.05, size=0.1)
    t = np.array([0.3, 0.4, 0.5, 0.6, 0.6])
    means = np.stack([t, 2 * t, -t], 1)
    means[4] += 1.0  # off the path
    n = len(t)
    g = GaussianParameters(means, np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),
                           np.arange(n, dtype=np.float32)[:, None], np.zeros((n, 1, 3)),
                           np.zeros((n, 3, 3)), t_eq=t[:, None],
                           life_rate=np.array([[5.0], [0.0], [5.0], [0.0], [5.0]]))
    opt = torch.optim.Adam(g.parameters(), lr=1e-3)
    g.opacity_logits.sum().backward()
    opt.step()
    state = DensifyState(torch.arange(n, dtype=torch.float32), torch.ones(n), torch.zeros(n))
    ready = np.concatenate([mu, [0.9, 0.4, 0.1], [0.1]])[None]
    gone = ResidualCarving._unchain(g, opt, state, ready, anchors, spacing=0.05)
    assert gone == 2
    # rows 1, 3 and 4 stay (one Adam step of lr 1e-3 moved each logit down by 1e-3)
    np.testing.assert_allclose(g.opacity_logits.detach().reshape(-1), [1.0, 3.0, 4.0], atol=2e-3)
    assert state.grad_accum.tolist() == [1.0, 3.0, 4.0]
    assert opt.state[g.opacity_logits]["exp_avg"].shape[0] == 3
