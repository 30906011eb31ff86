"""A round body's spin from its texture (nehad.texture_spin, nehad.spin_tracks.texture_spin), on
ray-cast views of a checkered sphere whose spin is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nehad.data.synth import Sphere, Surface, _axis_angle, render_view
from nehad.data.synth_stress import rig_camera
from nehad.spin import estimate_spin, rotations
from nehad.spin_tracks import texture_spin
from nehad.texture_spin import (
    SurfaceSamples,
    estimate_texture_spin,
    surface_samples,
    texture_misfit,
)
from nehad.tracks import find_blobs

SIZE = 80
FRAMES = 60
SPACING = 1.0 / (FRAMES - 1)
RADIUS = 0.3
AXIS = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
RATE = 4.0 * math.pi  # two turns over t in [0, 1]


def _centre(t: float) -> np.ndarray:
    return np.array([0.5 * t - 0.25, 0.0, 0.6])


def _views(rate: float):
    """One rig camera a frame: a checkered sphere on a line, turning `rate` about AXIS, over
    white; [(camera, time, image (H, W, 3))]."""
    out = []
    for i, t in enumerate(np.linspace(0.0, 1.0, FRAMES)):
        cam = rig_camera(i, SIZE)
        ball = Sphere("s", _centre(t), RADIUS, (0.6, 0.2, 0.8),
                      rotation=_axis_angle(AXIS, rate * t),
                      surface=Surface("checker", (0.95, 0.9, 0.3), cells=8))
        full = render_view([ball], cam, supersample=2)
        out.append((cam, float(t), full[..., :3] + (1.0 - full[..., 3:])))
    return out


@pytest.fixture(scope="module")
def spinning():
    return _views(RATE)


def _angle_deg(a, b) -> float:
    cos = float(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def test_a_spinning_checkered_spheres_texture_gives_its_spin(spinning):
    """Its outline is the same at every turn; its checkers give its rate within 2% and its
    axis within 3 degrees, and fit it far better than no spin."""
    samples = surface_samples(spinning, [_centre(t) for _, t, _ in spinning], RADIUS)
    spin = estimate_texture_spin(samples, SPACING, RADIUS)
    assert spin.round and spin.spins
    assert abs(np.linalg.norm(spin.omega) - RATE) < 0.02 * RATE
    assert _angle_deg(spin.omega, AXIS) < 3.0
    assert spin.fit < 0.6 * spin.fit_still


def test_a_track_seen_only_at_its_ends_gives_its_spin(spinning):
    """No view within 0.15 of the track's middle time: the search starts on the first window
    that has samples."""
    ends = [v for v in spinning if abs(v[1] - 0.5) > 0.15]
    samples = surface_samples(ends, [_centre(t) for _, t, _ in ends], RADIUS)
    spin = estimate_texture_spin(samples, SPACING, RADIUS)
    assert spin.spins and abs(np.linalg.norm(spin.omega) - RATE) < 0.02 * RATE
    assert not estimate_texture_spin(SurfaceSamples(np.zeros(0), np.zeros((0, 3)),
                                                    np.zeros((0, 3))), SPACING, RADIUS).spins


def test_a_still_checkered_sphere_reports_no_spin():
    views = _views(0.0)
    samples = surface_samples(views, [_centre(t) for _, t, _ in views], RADIUS)
    assert not estimate_texture_spin(samples, SPACING, RADIUS).spins


def test_surface_samples_lie_on_the_ball_under_their_pixels(spinning):
    """Each sample's point of the ball projects into a pixel of the ball's colours, and its
    direction is a unit vector facing the camera."""
    cam, t, image = spinning[7]
    samples = surface_samples([(cam, t, image)], [_centre(t)], RADIUS)
    assert len(samples.times) > 30
    assert np.allclose(np.linalg.norm(samples.directions, axis=1), 1.0)
    points = _centre(t) + RADIUS * samples.directions
    uv, _ = cam.project(points)
    assert np.all((uv >= 0) & (uv < SIZE))
    assert np.all(((cam.centre - points) * samples.directions).sum(1) > 0.0)
    white = (image[uv[:, 1].astype(int), uv[:, 0].astype(int)] > 0.99).all(1)
    assert white.mean() < 0.02  # on the sphere, not the backdrop


def test_the_misfit_is_the_spread_within_patches_counted_directly():
    """Against a direct count: each sample turned back by its own rotation matrix, its patch
    found, each patch's colours' squared deviations from their mean summed."""
    rng = np.random.default_rng(3)
    n, patches = 500, 5
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    samples = SurfaceSamples(rng.random(n), dirs, rng.random((n, 3)))
    omegas = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, 3.0], [0.0, 7.0, 0.5]])
    got = texture_misfit(omegas, samples, 0.4, patches)
    for omega, value in zip(omegas, got):
        turned = np.stack([rotations(-omega * (t - 0.4)) @ d
                           for t, d in zip(samples.times, dirs)])
        box = np.clip(((turned + 1.0) * 0.5 * patches).astype(int), 0, patches - 1)
        cells = {}
        for key, colour in zip(map(tuple, box), samples.chroma):
            cells.setdefault(key, []).append(colour)
        total = sum(((np.array(c) - np.mean(c, 0)) ** 2).sum() for c in cells.values())
        assert value == pytest.approx(total / n, rel=1e-9)


def test_a_round_track_off_its_path_still_gives_its_spin(spinning):
    """`nehad.spin_tracks.texture_spin` on the blobs of the views: the track's path a fifth of
    the radius off the ball across the view, its centres taken on the blobs' rays at the
    path's depth; the spin found as from the true centres. A rod's shape is not round: its
    shape's spin (none here) is returned as it is."""
    cams = [v[0] for v in spinning]
    times = np.array([v[1] for v in spinning])
    alphas = [(v[2] < 0.99).any(-1).astype(np.float32) for v in spinning]
    blobs = find_blobs(cams, times, [v[2] for v in spinning], alphas,
                       [np.ones_like(v[2]) for v in spinning], min_area=1)
    assert len(blobs) == FRAMES

    def off_path(ts):
        return np.stack([_centre(t) + np.array([0.0, 0.06, 0.0]) for t in ts]), None

    track = SimpleNamespace(blobs=blobs, smooth_at=off_path)
    views = SimpleNamespace(images=[torch.from_numpy(np.ascontiguousarray(v[2]))
                                    for v in spinning])
    shape = estimate_spin(blobs, cams, np.stack([_centre(b.time) for b in blobs]), SPACING)
    assert not shape.spins
    spin = texture_spin(track, cams, views, SPACING, shape)
    assert spin.spins and abs(np.linalg.norm(spin.omega) - RATE) < 0.03 * RATE
    assert _angle_deg(spin.omega, AXIS) < 5.0
    rod = SimpleNamespace(spread=np.diag([0.2, 0.001, 0.001]), spins=False)
    assert texture_spin(track, cams, views, SPACING, rod) is rod


def test_two_tracks_of_one_round_spinning_body_are_joined(spinning):
    """The tracker's two overlapping pieces of the sphere (views 0-39 and 30-59) become one
    track of its 60 views, spinning as the sphere does; a piece elsewhere is left apart."""
    from nehad.spin_tracks import join_round
    from nehad.tracks import Track

    cams = [v[0] for v in spinning]
    times = np.array([v[1] for v in spinning])
    alphas = [(v[2] < 0.99).any(-1).astype(np.float32) for v in spinning]
    blobs = sorted(find_blobs(cams, times, [v[2] for v in spinning], alphas,
                              [np.ones_like(v[2]) for v in spinning], min_area=1),
                   key=lambda b: b.time)
    views = SimpleNamespace(images=[torch.from_numpy(np.ascontiguousarray(v[2]))
                                    for v in spinning])
    shape = estimate_spin(blobs, cams, np.stack([_centre(b.time) for b in blobs]), SPACING)

    def piece(part, shift=np.zeros(3)):
        t = np.array([b.time for b in part])
        points = np.stack([_centre(x) for x in t]) + shift
        track = Track(part, t, points, np.tile([0.5, 0.0, 0.0], (len(t), 1)))
        return track, texture_spin(track, cams, views, SPACING, shape)

    first, second = piece(blobs[:40]), piece(blobs[30:])
    assert first[1].spins and second[1].spins
    joined = join_round([first, second], cams, views, SPACING, 0.05)
    assert len(joined) == 1
    track, spin = joined[0]
    assert sorted(b.view for b in track.blobs) == list(range(FRAMES))
    assert np.all(np.diff(track.times) > 0)
    assert abs(np.linalg.norm(spin.omega) - RATE) < 0.02 * RATE
    far = piece(blobs[30:], np.array([0.0, 0.5, 0.0]))
    assert len(join_round([first, (far[0], second[1])], cams, views, SPACING, 0.05)) == 2


def test_the_field_path_is_the_centroid_of_what_the_field_draws_there():
    """A stand-in field: 40 Gaussians about a bouncing centre (symmetric pairs, so their
    centroid is the centre), 30 still ones far off; a track that cuts the bounce's corner by
    a tenth. The field's path is the centre at the track's times and its velocity the
    centre's over a frame; with the ball's Gaussians elsewhere the track is kept."""
    from nehad.spin_tracks import field_path
    from nehad.tracks import Track

    rng = np.random.default_rng(5)
    half = rng.normal(size=(20, 3)) * 0.1
    offsets = np.concatenate([half, -half])
    still = rng.normal(size=(30, 3)) + np.array([3.0, 0.0, 0.0])

    def centre(t):
        return np.array([t, 0.0, 0.4 + 0.5 * abs(math.sin(2 * math.pi * t))])

    def means_at(t, index):
        every = np.concatenate([centre(float(t)) + offsets, still])
        return torch.as_tensor(every[np.asarray(index)], dtype=torch.float32)

    model = SimpleNamespace(means_at=means_at, gaussians=SimpleNamespace(
        opacity_logits=torch.zeros((70, 1))))
    times = np.linspace(0.1, 0.9, 30)
    cut = np.stack([centre(t) - np.array([0.0, 0.0, 0.1]) for t in times])
    track = Track([None] * len(times), times, cut, np.zeros_like(cut))
    spacing = 0.01
    got = field_path(model, track, 0.3, np.arange(70), spacing)
    assert np.allclose(got.points, np.stack([centre(t) for t in times]), atol=1e-5)
    slope = np.stack([(centre(t + spacing / 2) - centre(t - spacing / 2)) / spacing
                      for t in times])
    assert np.allclose(got.velocities, slope, atol=1e-3)
    far = Track([None] * len(times), times, cut + 2.0, np.zeros_like(cut))
    assert field_path(model, far, 0.3, np.arange(70), spacing) is far
