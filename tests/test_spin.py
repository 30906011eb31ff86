"""A tracked object's spin from its blobs' shapes (nehad.spin), the places the deformation field
takes written-in Gaussians to (nehad.placement), and a spinning body's path smoothed over its
wandering blob centroids (nehad.spin_tracks.smooth_path), on ray-cast views and stand-in fields
whose answers are known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nehad.data.synth import Box, Sphere, _axis_angle, render_view
from nehad.data.synth_stress import rig_camera
from nehad.spin import estimate_spin, projection_jacobians
from nehad.tracks import find_blobs

SIZE = 96
FRAMES = 60
CENTRE = np.array([0.0, 0.0, 0.6])
AXIS = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
RATE = 4.0 * math.pi  # two turns over t in [0, 1]


def _blobs(shape_at):
    """One blob per frame: the ray-cast object over white, nothing drawn; (blobs, cameras)."""
    times = np.linspace(0.0, 1.0, FRAMES)
    cams, targets, alphas = [], [], []
    for i, t in enumerate(times):
        cam = rig_camera(i, SIZE)
        full = render_view([shape_at(t)], cam, supersample=2)
        cams.append(cam)
        targets.append(full[..., :3] + (1.0 - full[..., 3:]))
        alphas.append(full[..., 3])
    blobs = find_blobs(cams, times, targets, alphas, [np.ones_like(x) for x in targets],
                       min_area=1)
    assert sorted(b.view for b in blobs) == list(range(FRAMES))  # one blob a view
    return blobs, cams


def test_projection_jacobians_match_finite_differences():
    cam = rig_camera(3, SIZE)
    x = np.array([0.2, -0.1, 0.5])
    (jac,) = projection_jacobians([cam], x[None])
    h = 1e-6
    numeric = np.stack([(cam.project(x + h * e)[0][0] - cam.project(x - h * e)[0][0]) / (2 * h)
                        for e in np.eye(3)], 1)
    assert np.allclose(jac, numeric, rtol=1e-5, atol=1e-3)


@pytest.fixture(scope="module")
def rod():
    return _blobs(lambda t: Box("rod", CENTRE, np.array([0.5, 0.025, 0.025]),
                                _axis_angle(AXIS, RATE * t), (0.9, 0.25, 0.2)))


def test_a_spinning_rods_blobs_give_its_spin(rod):
    """A rod 20 times longer than thick turning two turns about a tilted axis, one rig camera
    per time (12 degrees a frame): its rate within 1% and its axis within 2 degrees, and its
    body's longest spread that of a uniform rod of its length (L^2 / 12)."""
    blobs, cams = rod
    spin = estimate_spin(blobs, cams, np.repeat(CENTRE[None], len(blobs), 0), 1.0 / (FRAMES - 1))
    rate = float(np.linalg.norm(spin.omega))
    assert abs(rate - RATE) < 0.01 * RATE, spin.omega
    angle = math.degrees(math.acos(min(1.0, float(spin.omega @ AXIS) / rate)))
    assert angle < 2.0, angle
    assert spin.spins and spin.fit < 0.2 * spin.fit_still, (spin.fit, spin.fit_still)
    longest = float(np.linalg.eigvalsh(spin.spread)[-1])
    assert abs(longest - 1.0 / 12.0) < 0.15 / 12.0, longest


def test_the_misfit_matches_its_matrix_form_and_candidates_refine_as_if_alone(rod):
    """`_misfit`'s design, written element by element, against J R E_ab R^T J^T formed as
    matrix products (E_ab the symmetric unit matrix of each of the spread's six numbers),
    solved by numpy's least squares; and `_refine` of four candidates at once against each
    refined on its own, on the spinning rod's blobs (each its own Gauss-Newton steps: the
    same omegas to 1e-9)."""
    from nehad.spin import _PAIRS, _misfit, _refine, rotations

    blobs, cams = rod
    points = np.repeat(CENTRE[None], len(blobs), 0)
    times = np.array([b.time for b in blobs])
    jac = projection_jacobians([cams[b.view] for b in blobs], points)
    observed = np.array([[b.shape[0, 0], b.shape[1, 1], b.shape[0, 1]] for b in blobs])
    weights = 1.0 / np.array([np.trace(b.shape) for b in blobs])
    dts = times - times.mean()
    omegas = np.random.default_rng(0).normal(0.0, 6.0, (5, 3))
    err, six = _misfit(omegas, jac, dts, observed, weights)
    for k, omega in enumerate(omegas):
        m = jac @ rotations(omega[None] * dts[:, None])
        cols = []
        for a, b in _PAIRS:
            unit = np.zeros((3, 3))
            unit[a, b] = unit[b, a] = 1.0
            c = m @ unit @ np.swapaxes(m, 1, 2)
            cols.append(np.stack([c[:, 0, 0], c[:, 1, 1], c[:, 0, 1]], 1).reshape(-1))
        design = np.stack(cols, 1) * np.repeat(weights, 3)[:, None]
        rhs = (observed * weights[:, None]).reshape(-1)
        want = np.linalg.lstsq(design, rhs, rcond=None)[0]
        assert np.allclose(six[k], want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
        assert err[k] == pytest.approx(np.sqrt(np.mean((design @ want - rhs) ** 2)), rel=1e-6)
    starts = np.array([[0.3, 0.2, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.5]]) * 11.0
    together, errs = _refine(starts, jac, dts, observed, weights)
    for start, omega, e in zip(starts, together, errs):
        alone, e_alone = _refine(start[None], jac, dts, observed, weights)
        assert np.allclose(omega, alone[0], rtol=0, atol=1e-9) and e == pytest.approx(e_alone[0])


def test_a_round_object_reports_no_spin():
    """A sphere on a path: every turn fits its round blobs alike, so no spin is reported."""
    def ball(t):
        return Sphere("s", CENTRE + np.array([0.6 * t - 0.3, 0.0, 0.0]), 0.2, (0.2, 0.4, 0.9))

    blobs, cams = _blobs(ball)
    points = np.stack([ball(b.time).centre for b in blobs])
    assert not estimate_spin(blobs, cams, points, 1.0 / (FRAMES - 1)).spins


def _stand_in_field(shift):
    """A stand-in deformation field: means -> shift(means, t), scales and rotations kept."""
    def field(means, log_scales, quats, t, mu_eq=None, t_eq=None):
        return SimpleNamespace(means=shift(means, t), log_scales=log_scales, quats=quats)
    return field


def test_newton_steps_place_where_the_fixed_point_stops_short():
    """A field that folds space (x -> c - x / 2 + t u: its derivative -1/2, where the fixed
    point's half steps grow the error by 1.25 a step): the fixed point ends far off, the Newton
    steps land on the wanted places; the field's own motion of them is u."""
    from nehad.placement import field_velocity, solve_places

    c, u = torch.tensor([0.3, -0.2, 0.1]), torch.tensor([1.0, 2.0, -0.5])
    field = _stand_in_field(lambda x, t: c - 0.5 * x + torch.as_tensor(t) * u)
    rng = np.random.default_rng(0)
    want = torch.as_tensor(rng.uniform(-1, 1, (20, 3)), dtype=torch.float32)
    ls, q = torch.zeros(20, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(20, 1)
    t_eq = torch.full((20, 1), 0.4)
    *_, stuck = solve_places(field, want, ls, q, t_eq)
    assert float(stuck.min()) > 1.0
    mu, _, _, left = solve_places(field, want, ls, q, t_eq, reach=torch.full((20,), 10.0))
    assert float(left.max()) < 1e-4
    assert torch.allclose(c - 0.5 * mu + 0.4 * u, want, atol=1e-4)
    assert torch.allclose(field_velocity(field, mu, ls, q, t_eq, 0.01), u.expand(20, 3),
                          atol=1e-3)


def test_a_place_found_at_one_knot_carries_to_the_next():
    """The folding field again, its solutions 4 or more away from the wanted places, Newton
    steps capped at 0.1 (20 of them reach 2): only the first knot's copies get a good seed.
    With `neighbours` the three knots after it start from their neighbours' places and land
    (within a quarter of a step's reach, where a copy is no longer retried); without, they stay
    off."""
    from nehad.placement import solve_places

    c = torch.tensor([3.0, 0.0, 0.0])
    field = _stand_in_field(lambda x, t: c - 0.5 * x)
    k, knots = 2, 4
    want = torch.tensor([[0.0, 0.1 * i, 0.05 * j] for i in range(knots) for j in range(k)])
    exact = 2.0 * (c - want)
    seeds = want.clone()
    seeds[:k] = exact[:k]
    args = (field, want, torch.zeros(k * knots, 3),
            torch.tensor([[1.0, 0, 0, 0]]).repeat(k * knots, 1), torch.zeros(k * knots, 1),
            seeds, torch.full((k * knots,), 0.1))
    *_, alone = solve_places(*args)
    assert float(alone[:k].max()) < 1e-4 and float(alone[k:].min()) > 1.0
    mu, *_, left = solve_places(*args, neighbours=k)
    assert float(left.max()) < 0.25 * 0.1  # retried until within a quarter of a step's reach
    assert float((mu - exact).norm(dim=1).max()) < 0.5 * 0.1


def _written_out_at(obj, t: float) -> np.ndarray:
    """The means at time t of a carried object's members written out (`materialise`, each
    copy living 0.05) through a field that moves nothing, every one of them placed."""
    from nehad.carry import materialise
    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    field = DeformationField(FieldConfig(), np.array([[-2.0] * 3, [2.0] * 3]), 4.0)
    new, miss = materialise(obj, field, GaussianParameters.random_in_box(0, sh_degree=0), 0.05)
    assert float(miss.max()) < 1e-5
    g = GaussianParameters.empty_like_state(new)
    g.load_state_dict(GaussianParameters.with_defaults(new))
    with torch.no_grad():
        return NeHaDModel(g, field).gaussians_at(t)[0].numpy()


def test_a_spinning_carried_objects_members_turn_with_it():
    """A carried object turning at w: at a knot's time its members sit at the path's point plus
    their offsets turned by exp([w] (t - spin_time)), their rotations turned alike; written out
    through a field that moves nothing, a member a little later is where the turning body puts
    it to second order in the time (it moves along w x its offset)."""
    from nehad.carry import CarriedObject
    from nehad.splat.projection import quat_to_rotmat

    def leaf(x):
        return torch.as_tensor(x, dtype=torch.float32).clone().requires_grad_(True)

    omega = np.array([0.0, 3.0, 4.0])  # 5 rad per unit about (0, 0.6, 0.8)
    offsets = np.array([[0.3, 0.0, 0.0], [0.0, 0.0, 0.2]])
    knots = np.array([0.2, 0.3])
    obj = CarriedObject(knots, np.array([[1.0, 0, 0], [1.0, 0.5, 0]]),
                        np.array([[0.0, 5.0, 0], [0.0, 5.0, 0]]), 0.3, leaf(offsets),
                        leaf(np.full((2, 3), -3.0)), leaf([[1.0, 0, 0, 0]] * 2),
                        leaf([[2.0], [2.0]]), leaf(np.zeros((2, 1, 3))), None, leaf(omega), 0.1)
    means, _, quats, _, _ = obj.members_at(0.3, 1e-3)
    turn = _axis_angle(omega, 5.0 * 0.2)
    assert np.allclose(means.detach().numpy(), [1.0, 0.5, 0.0] + offsets @ turn.T, atol=1e-5)
    assert np.allclose(quat_to_rotmat(quats.detach()).numpy(), turn, atol=1e-5)
    dt = 0.01
    drawn = _written_out_at(obj, 0.3 + dt)[2:]
    body = [1.0, 0.5 + 5.0 * dt, 0.0] + offsets @ _axis_angle(omega, 5.0 * (0.2 + dt)).T
    assert np.abs(drawn - body).max() < 0.5 * 25.0 * dt ** 2 * 0.3 + 1e-5


def test_a_carried_objects_path_correction_moves_and_carries_its_members():
    """A path correction (`path_fix`, linear between its times) adds its value at each knot's
    time to the members' places and its slope to their velocities: through a field that moves
    nothing, a member written out at a knot is, a little later, where the corrected path is."""
    from nehad.carry import CarriedObject

    def leaf(x):
        return torch.as_tensor(x, dtype=torch.float32).clone().requires_grad_(True)

    fix = np.array([[0.0, 0.0, 0.0], [0.4, -0.2, 0.0], [0.4, -0.2, 0.0]])
    obj = CarriedObject(np.array([0.2, 0.3]), np.array([[1.0, 0, 0], [1.0, 0.5, 0]]),
                        np.array([[0.0, 5.0, 0], [0.0, 5.0, 0]]), 0.3, leaf([[0.1, 0.0, 0.0]]),
                        leaf(np.full((1, 3), -3.0)), leaf([[1.0, 0, 0, 0]]), leaf([[2.0]]),
                        leaf(np.zeros((1, 1, 3))), None, leaf(np.zeros(3)), 0.25,
                        leaf(fix), np.array([0.0, 0.4, 0.8]))
    means = obj.members_at(0.3, 1e-3)[0].detach().numpy()
    assert np.allclose(means, [[1.1 + 0.3, 0.5 - 0.15, 0.0]], atol=1e-6)  # 3/4 of the way
    dt = 0.01
    drawn = _written_out_at(obj, 0.3 + dt)[1]
    assert np.allclose(drawn, [1.1 + 0.3 + dt, 0.5 + 5.0 * dt - 0.15 - 0.5 * dt, 0.0], atol=1e-5)


def test_a_path_corrections_times_are_times_its_track_saw():
    """The correction's times are blob times at least `every` apart, the last blob's included,
    none inside a gap of the track (a held-out block, where no view would fit it)."""
    from nehad.carry import _path_fix

    seen = np.concatenate([np.arange(0, 14), np.arange(20, 34), np.arange(40, 45)]) / 120.0
    fix, times = _path_fix(seen, 5 / 120.0)
    assert np.allclose(times * 120, [0, 5, 10, 20, 25, 30, 40, 44])
    assert fix.shape == (8, 3) and not fix.detach().any() and fix.requires_grad
    assert len(_path_fix(np.array([0.3, 0.3]), 0.04)[1]) == 1


def test_a_spinning_bodys_path_is_smoothed_over_its_wandering_centroids():
    """A body that does not move, whose blob centroids wander about its centre (seeded noise
    of 2 pixels): across a held-out gap the smoothed path stays within a quarter of the
    distance the track's own curve strays."""
    from nehad.spin_tracks import smooth_path
    from nehad.tracks import Blob, TrackSettings, fit_tracks

    rng = np.random.default_rng(3)
    times = np.array([t for t in np.linspace(0.0, 1.0, 120) if (t * 119) % 20 < 14])
    blobs, cams = [], []
    for i, t in enumerate(times):
        cam = rig_camera(i, 200)
        uv = cam.project(CENTRE)[0][0] + rng.normal(0, 2.0, 2)
        d = np.array([(uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy, 1.0])
        d = cam.camera_to_world[:3, :3] @ d
        blobs.append(Blob(i, float(t), uv, 200, np.array([0.9, 0.2, 0.2]),
                          cam.camera_to_world[:3, 3].copy(), d / np.linalg.norm(d)))
        cams.append(cam)
    tracks = fit_tracks(cams, blobs, TrackSettings(gate_px=8.0))
    track = max(tracks, key=lambda tr: len(tr.blobs))
    gap = np.linspace(track.times[0], track.times[-1], 200)
    own = np.abs(track.smooth_at(gap)[0] - CENTRE).max()
    smooth = np.abs(smooth_path(track, gap)[0] - CENTRE).max()
    assert smooth < 0.25 * own, (smooth, own)


def test_pieces_of_one_spinning_body_are_joined(rod):
    """The rod's blobs cut into two tracks a frame apart are joined into one, spinning as the
    rod does; a second half that turns the other way is not joined to the first."""
    from nehad.spin_tracks import join_spinning
    from nehad.tracks import TrackSettings, fit_tracks

    blobs, cams = rod
    spacing = 1.0 / (FRAMES - 1)

    def track(part):
        (tr,) = fit_tracks(cams, part, TrackSettings(gate_px=30.0))
        return tr

    first = track([b for b in blobs if b.time < 0.5])
    second = track([b for b in blobs if b.time > 0.5])
    ((whole, spin),) = join_spinning([second, first], cams, spacing, 0.08)
    assert len(whole.blobs) == len(first.blobs) + len(second.blobs)
    assert abs(float(np.linalg.norm(spin.omega)) - RATE) < 0.01 * RATE
    back, _ = _blobs(lambda t: Box("rod", CENTRE, np.array([0.5, 0.025, 0.025]),
                                   _axis_angle(AXIS, -RATE * t), (0.9, 0.25, 0.2)))
    other = track([b for b in back if b.time > 0.5])
    assert len(join_spinning([first, other], cams, spacing, 0.08)) == 2


def test_a_short_piece_after_a_hidden_stretch_is_joined_to_the_spinning_body(rod):
    """The rod followed over t < 0.3, hidden until 0.45 (longer than the tracker's 0.08, as
    when another object passes before it), then a piece of 6 blobs, too few to show a spin of
    its own: joined, the whole spinning as the rod does. The same piece after a hidden stretch
    longer than the first piece was followed is not joined, nor is a piece 6 blobs long
    elsewhere."""
    from nehad.spin_tracks import join_spinning
    from nehad.tracks import TrackSettings, fit_tracks

    blobs, cams = rod
    spacing = 1.0 / (FRAMES - 1)

    def track(lo, hi, part=blobs):
        (tr,) = fit_tracks(cams, [b for b in part if lo <= b.time < hi],
                           TrackSettings(gate_px=30.0, min_blobs=4))
        return tr

    first, short = track(0.0, 0.3), track(0.45, 0.55)
    assert len(short.blobs) == 6 and not estimate_spin(
        short.blobs, cams, np.repeat(CENTRE[None], 6, 0), spacing).spins
    ((whole, spin),) = join_spinning([short, first], cams, spacing, 0.08)
    assert len(whole.blobs) == len(first.blobs) + 6
    assert abs(float(np.linalg.norm(spin.omega)) - RATE) < 0.02 * RATE
    early = track(0.0, 0.2)  # followed for 0.19 of time, hidden for 0.27
    assert estimate_spin(early.blobs, cams, np.repeat(CENTRE[None], len(early.blobs), 0),
                         spacing).spins
    assert len(join_spinning([early, short], cams, spacing, 0.08)) == 2
    away, _ = _blobs(lambda t: Box("rod", CENTRE + np.array([1.2, 0.0, 0.0]),
                                   np.array([0.5, 0.025, 0.025]), _axis_angle(AXIS, RATE * t),
                                   (0.9, 0.25, 0.2)))
    assert len(join_spinning([first, track(0.45, 0.55, away)], cams, spacing, 0.08)) == 2
