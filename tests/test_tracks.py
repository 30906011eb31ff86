"""Tracks of unexplained blobs (nehad.tracks): a small sphere on a loop, one camera per time, some
of it behind a wall, found and followed where it is, on ray-cast views whose geometry is known."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from nehad.data.synth import Box, Sphere, render_view
from nehad.data.synth_stress import rig_camera, rig_cameras
from nehad.runtime.cameras import Camera
from nehad.tracks import (Blob, TrackSettings, blob_axes, fit_motion, fit_tracks, find_blobs,
                          motion_at, seeds_along)

SIZE = 96
RADIUS = 0.18
COLOUR = (0.9, 0.45, 0.1)


def _centre(t):
    """The sphere's path: a loop of radius 1.2 m, a full turn over t in [0, 1], rising 0.4 m."""
    a = 2.0 * math.pi * t
    return np.array([1.2 * math.cos(a), 1.2 * math.sin(a), 0.4 + 0.4 * t])


def _camera(i):
    return rig_camera(i, SIZE)


WALL = Box("wall", np.array([1.6, 0.0, 0.6]), np.array([0.05, 0.7, 0.6]), np.eye(3),
           (0.2, 0.3, 0.8))


def _scene(times, with_wall=True):
    """Per time: the camera (the rig's cameras in turn), the target over white with its
    alpha, and a render of a model that draws the wall but not the sphere."""
    cams, targets, alphas, drawn = [], [], [], []
    for i, t in enumerate(times):
        cam = _camera(i)
        sphere = Sphere("s", _centre(t), RADIUS, COLOUR)
        objects = [sphere, WALL] if with_wall else [sphere]
        full = render_view(objects, cam, supersample=2)
        model = render_view([WALL] if with_wall else [], cam, supersample=2)
        cams.append(cam)
        targets.append(full[..., :3] + (1.0 - full[..., 3:]))
        alphas.append(full[..., 3])
        drawn.append(model[..., :3] + (1.0 - model[..., 3:]))
    return cams, targets, alphas, drawn


def test_motion_through_exact_rays_is_recovered():
    """Rays through the points of a quadratic motion from four cameras: fit_motion returns its
    coefficients; with every ray from one camera centre the depth is undetermined (None)."""
    coef = np.array([[0.2, -0.1, 0.5], [1.5, 0.3, -0.7], [0.4, -2.0, 0.1]])
    blobs = []
    for i, t in enumerate(np.linspace(0.3, 0.5, 8)):
        cam = _camera(i)
        origin = cam.camera_to_world[:3, 3]
        d = motion_at(coef, 0.4, t) - origin
        blobs.append(Blob(i, float(t), np.zeros(2), 10, np.ones(3), origin, d / np.linalg.norm(d)))
    assert np.allclose(fit_motion(blobs, 0.4, degree=2), coef, atol=1e-8)
    one_view = [Blob(0, b.time, b.centre, b.area, b.colour, blobs[0].origin,
                     (motion_at(coef, 0.4, b.time) - blobs[0].origin)
                     / np.linalg.norm(motion_at(coef, 0.4, b.time) - blobs[0].origin))
                for b in blobs[:2]]
    assert fit_motion(one_view, 0.4, degree=1) is None


@pytest.fixture(scope="module")
def loop():
    times = np.linspace(0.0, 1.0, 61)
    keep = (times < 0.47) | (times > 0.53)  # no view in 0.47-0.53 (held out, as MuJoCo splits)
    times = times[keep]
    return times, _scene(times)


def test_the_missing_sphere_is_one_track_that_follows_it(loop):
    times, (cams, targets, alphas, drawn) = loop
    blobs = find_blobs(cams, times, targets, alphas, drawn)
    # the wall is drawn, so the blobs are the sphere's (where it is not behind the wall)
    visible = sum(1 for b in blobs)
    assert visible >= 0.7 * len(times)
    tracks = fit_tracks(cams, blobs)
    assert len(tracks) == 1, [len(t.blobs) for t in tracks]
    track = tracks[0]
    assert len(track.blobs) >= 0.9 * visible
    truth = np.stack([_centre(t) for t in track.times])
    err = np.linalg.norm(track.points - truth, axis=1)
    assert np.median(err) < 0.03 and err.max() < 0.12, err
    # across the stretch with no view and between the views
    held = np.array([0.48, 0.5, 0.52, 0.21, 0.77])
    pts, vel = track.at(held)
    err = np.linalg.norm(pts - np.stack([_centre(t) for t in held]), axis=1)
    assert err.max() < 0.15, err  # under the sphere's radius
    speed = 2.0 * math.pi * 1.2  # m per unit time along the loop
    assert np.allclose(np.linalg.norm(vel, axis=1), speed, rtol=0.25)
    # the chain of Gaussians: one per spacing over the span, as wide as half the sphere
    pts, vel, taus, cols, widths, shapes = seeds_along(track, cams, 1 / 60, 0.0, 1.0)
    assert len(taus) >= 55 and np.all(np.diff(taus) > 0)
    chroma = lambda c: np.asarray(c) / np.sum(c)  # the shading divided out
    assert np.allclose(chroma(cols.mean(0)), chroma(COLOUR), atol=0.08), cols.mean(0)
    assert 0.25 * RADIUS < widths[0] < RADIUS


def test_nothing_missing_no_track(loop):
    times, (cams, targets, alphas, drawn) = loop
    assert find_blobs(cams, times, targets, alphas, targets) == []
    assert fit_tracks(cams, []) == []


def test_closing_joins_a_body_striped_with_the_backdrops_colour():
    """The stress suite's striped box from above over white: its near-white stripes match the
    backdrop, so its unexplained pixels are four stripes of green; closed with a 7-pixel disc
    (nehad.spin_tracks.CLOSE_FRACTION at 200 pixels) they are one blob, as wide as the box."""
    from nehad.data.synth_stress import stress_objects

    cam = rig_camera(4, 200)
    full = render_view(stress_objects("spinning_textures", 0.3)[2:3], cam, supersample=1)
    target = full[..., :3] + (1.0 - full[..., 3:])

    def blobs(close):
        return find_blobs([cam], [0.3], [target], [full[..., 3]], [np.ones_like(target)],
                          min_area=1, close_px=close)

    assert len(blobs(0)) == 4
    (whole,) = blobs(7)
    assert whole.area > 0.9 * int((full[..., 3] >= 0.5).sum())


def test_a_blobs_cover_is_the_renders_mean_alpha_over_its_pixels():
    """Two unexplained squares over white: where the render's alpha is 1 on the left 6 of one's
    16 columns and 0.25 over all of the other, their covers are 6/16 and 0.25; without the
    alphas, nan."""
    cam = rig_camera(0, 64)
    target = np.ones((64, 64, 3))
    target[10:18, 10:26] = (0.9, 0.1, 0.1)
    target[40:50, 40:50] = (0.1, 0.1, 0.9)
    drawn_alpha = np.zeros((64, 64))
    drawn_alpha[10:18, 10:16] = 1.0
    drawn_alpha[40:50, 40:50] = 0.25
    blobs = find_blobs([cam], [0.5], [target], [None], [np.ones_like(target)],
                       covers=[drawn_alpha])
    covers = sorted((b.area, b.cover) for b in blobs)
    assert [a for a, _ in covers] == [100, 128]
    assert covers[0][1] == pytest.approx(0.25) and covers[1][1] == pytest.approx(6 / 16)
    (plain, _) = sorted(find_blobs([cam], [0.5], [target], [None], [np.ones_like(target)]),
                        key=lambda b: b.area)
    assert math.isnan(plain.cover)


def test_a_blob_widened_to_its_objects_pixels_is_centred_on_the_object():
    """A red disc of radius 6 px over white, beside a red square 30 px away and a disc of
    another hue touching it; the render draws the disc's right half (in its own colour), so
    the unexplained blob is its left half, 2.5 px left of the centre on its own. Widened
    (`widen_tol`), the blob's centroid is the disc's centre to 0.05 px and its colour the
    disc's; the square (beyond the reach) and the other hue are left out; its area and cover
    stay the left half's."""
    cam = rig_camera(0, 96)
    yy, xx = np.mgrid[0:96, 0:96] + 0.5
    disc = (xx - 40.0) ** 2 + (yy - 50.0) ** 2 <= 36.0
    other = ((xx - 52.0) ** 2 + (yy - 50.0) ** 2 <= 36.0) & ~disc
    target = np.ones((96, 96, 3))
    target[disc] = (0.8, 0.1, 0.1)
    target[other] = (0.1, 0.1, 0.8)
    target[45:55, 70:80] = (0.8, 0.1, 0.1)  # 30 px right of the disc's centre
    drawn, drawn_alpha = np.ones_like(target), np.zeros((96, 96))
    right = disc & (xx > 40.0)
    drawn[right], drawn_alpha[right] = target[right], 1.0
    drawn[other] = target[other]
    drawn[45:55, 70:80] = target[45:55, 70:80]
    plain, = find_blobs([cam], [0.5], [target], [None], [drawn], covers=[drawn_alpha])
    wide, = find_blobs([cam], [0.5], [target], [None], [drawn], covers=[drawn_alpha],
                       widen_tol=0.08)
    assert plain.centre[0] < 40.0 - 2.0  # the left half's centroid
    assert np.abs(wide.centre - [40.0, 50.0]).max() < 0.05
    assert np.allclose(wide.colour, (0.8, 0.1, 0.1))
    assert wide.area == plain.area == int((disc & ~right).sum())
    assert wide.cover == plain.cover == 0.0
    disc_var = np.cov(np.stack([xx[disc], yy[disc]]), bias=True) + np.eye(2) / 12
    assert np.allclose(wide.shape, disc_var, atol=0.05)  # the whole disc's spread


def test_a_pale_blob_is_not_widened_into_a_white_floor():
    """A pale lilac disc (an object's edge blended with the floor: the second occluder
    variant's sphere, docs/results.md, 2026-12-02) on a white floor, a blue wall left of it,
    all of it unexplained. Its chromaticity is within 2 `widen_tol` of grey's, so widening
    would take the white floor for it (the blob's centroid pulled right onto the floor, its
    colour white); it is left as it is."""
    cam = rig_camera(0, 96)
    yy, xx = np.mgrid[0:96, 0:96] + 0.5
    disc = (xx - 40.0) ** 2 + (yy - 50.0) ** 2 <= 16.0
    target = np.ones((96, 96, 3))
    target[xx < 36.0] = (0.1, 0.1, 0.6)
    target[disc] = (0.64, 0.55, 0.78)
    drawn = target.copy()
    drawn[disc] = 1.0
    plain, = find_blobs([cam], [0.5], [target], [None], [drawn])
    wide, = find_blobs([cam], [0.5], [target], [None], [drawn], widen_tol=0.08)
    assert np.abs(plain.centre - [40.0, 50.0]).max() < 0.05
    assert np.array_equal(wide.centre, plain.centre)
    assert np.allclose(wide.colour, (0.64, 0.55, 0.78))
    assert np.array_equal(wide.shape, plain.shape)


def test_blobs_with_no_common_path_make_no_track():
    """A sphere drawn nowhere that jumps to a random place at every time: one blob per view,
    but no smooth path through their rays, so no track (the same views with the loop's sphere
    make one, the first test)."""
    rng = np.random.default_rng(3)
    times = np.linspace(0.0, 1.0, 30)
    cams, targets, alphas, drawn = [], [], [], []
    for i, t in enumerate(times):
        cam = _camera(i)
        where = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(0.2, 1.0)])
        full = render_view([Sphere("s", where, RADIUS, COLOUR)], cam, supersample=2)
        cams.append(cam)
        targets.append(full[..., :3] + (1.0 - full[..., 3:]))
        alphas.append(full[..., 3])
        drawn.append(np.ones_like(targets[-1]))
    blobs = find_blobs(cams, times, targets, alphas, drawn)
    assert len(blobs) >= 25
    assert fit_tracks(cams, blobs) == []


def test_a_seed_where_the_model_already_draws_its_object_is_dropped():
    """drawn_already against a brute-force count: a seed is covered when at least 3 opaque
    Gaussians of its chromaticity lie within its reach; the wrong colour, too faint or too far
    does not cover it."""
    from nehad.tracks import drawn_already

    rng = np.random.default_rng(3)
    orange, blue = np.array([0.9, 0.45, 0.1]), np.array([0.2, 0.3, 0.8])
    seeds = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [4.0, 0.0, 0.0], [6.0, 0.0, 0.0],
                      [8.0, 0.0, 0.0]])
    means, rgb, opac = [], [], []
    for centre, colour, alpha in (((0, 0, 0), orange, 0.9),  # the object, drawn
                                  ((2, 0, 0), blue, 0.9),  # something else there (a wall)
                                  ((4, 0, 0), orange, 0.05),  # faint
                                  ((6.3, 0, 0), orange * 0.5, 0.9)):  # shaded, 0.3 away
        means.append(np.asarray(centre) + rng.normal(0.0, 0.02, (5, 3)))
        rgb.append(np.repeat(colour[None, :], 5, axis=0))
        opac.append(np.full(5, alpha))
    means, rgb, opac = np.concatenate(means), np.concatenate(rgb), np.concatenate(opac)
    colours = np.repeat(orange[None, :], len(seeds), axis=0)
    got = drawn_already(seeds, colours, np.full(len(seeds), 0.2), means, opac, rgb, 0.08)
    assert got.tolist() == [True, False, False, False, False]
    wider = drawn_already(seeds, colours, np.full(len(seeds), 0.4), means, opac, rgb, 0.08)
    assert wider.tolist() == [True, False, False, True, False]  # same chromaticity, shaded
    # brute force: the count of alike, opaque Gaussians within the reach, per seed
    for reach, flags in ((0.2, got), (0.4, wider)):
        for s, flag in zip(seeds, flags):
            d = np.linalg.norm(means - s, axis=1)
            alike = np.abs(rgb / rgb.sum(1, keepdims=True) - orange / orange.sum()).max(1) <= 0.08
            assert flag == (int(((d <= reach) & (opac >= 0.3) & alike).sum()) >= 3)


def test_chains_are_found_again_from_their_gaussians():
    """chains_of: two chains that cross in time (apart in space), and a third later one, are
    three groups; a chain with a missing member (a gap of two spacings) is cut in two."""
    from nehad.tracks import chains_of

    s = 0.01
    t1 = np.arange(10) * s  # along +x at 10 units per unit time
    t2 = np.arange(10) * s  # standing still 3 units away
    t3 = 0.3 + np.arange(5) * s  # along +y, later
    means = np.concatenate([np.c_[10 * t1, 0 * t1, 0 * t1], np.c_[0 * t2, 0 * t2 + 3, 0 * t2],
                            np.c_[0 * t3 + 5, 10 * (t3 - 0.3), 0 * t3]])
    vel = np.concatenate([np.tile([10.0, 0, 0], (10, 1)), np.zeros((10, 3)),
                          np.tile([0, 10.0, 0], (5, 1))])
    times = np.concatenate([t1, t2, t3])
    labels = chains_of(means, vel, times, s, np.full(len(times), 0.05))
    assert len(set(labels[:10])) == 1 and len(set(labels[10:20])) == 1
    assert len(set(labels[20:])) == 1 and len(set(labels)) == 3
    cut = np.r_[0:4, 6:10]  # members 4 and 5 of the first chain gone
    assert len(set(chains_of(means[cut], vel[cut], times[cut], s, np.full(8, 0.05)))) == 2


def test_a_seed_as_seven_members_keeps_its_place_motion_and_chain():
    """cluster_seeds: 7 members per seed centred on it (the offsets cancel), each at `spread`
    of an axis from it, with its velocity, time and colour and half its axes; the members of
    a chain of seeds are one chain (`chains_of`, reach twice the members' largest scale, as
    `check_chains` measures it); members=1 changes nothing."""
    from nehad.tracks import chains_of, cluster_seeds

    rng = np.random.default_rng(3)
    n, s = 6, 0.01
    times = np.arange(n) * s
    vel = np.tile([4.0, 0.0, 1.0], (n, 1))
    pts = vel * times[:, None] + 0.2
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    shapes = np.stack([q * np.array([0.06, 0.04, 0.02]) for _ in range(n)])  # axes as columns
    widths = np.full(n, 0.04)
    cols = rng.uniform(size=(n, 3))
    same = cluster_seeds(pts, vel, times, cols, widths, shapes, 1)
    assert all(a is b for a, b in zip(same, (pts, vel, times, cols, widths, shapes)))
    m_pts, m_vel, m_t, m_cols, m_w, m_shapes = cluster_seeds(pts, vel, times, cols, widths,
                                                             shapes, 7, spread=0.6)
    assert m_pts.shape == (7 * n, 3) and m_shapes.shape == (7 * n, 3, 3)
    np.testing.assert_allclose(m_pts.reshape(n, 7, 3).mean(1), pts, atol=1e-12)
    off = m_pts.reshape(n, 7, 3) - pts[:, None, :]
    np.testing.assert_allclose(off[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sort(np.linalg.norm(off[0, 1:], axis=1)),
                               np.sort(0.6 * np.repeat([0.06, 0.04, 0.02], 2)), rtol=1e-9)
    np.testing.assert_array_equal(m_vel, np.repeat(vel, 7, 0))
    np.testing.assert_array_equal(m_t, np.repeat(times, 7))
    np.testing.assert_array_equal(m_cols, np.repeat(cols, 7, 0))
    np.testing.assert_allclose(m_shapes, 0.5 * np.repeat(shapes, 7, 0))
    np.testing.assert_allclose(m_w, 0.02)
    reach = 2.0 * np.linalg.norm(m_shapes, axis=1).max(axis=1)
    assert len(set(chains_of(m_pts, m_vel, m_t, s, reach))) == 1
    with pytest.raises(ValueError, match="members"):
        cluster_seeds(pts, vel, times, cols, widths, shapes, 3)


def _moments(weight):
    """(angle of the principal axis in degrees mod 180, ratio of the principal stds) of an
    image's weight."""
    rows, cols = np.nonzero(weight > 1e-3)
    w = weight[rows, cols]
    pts = np.stack([cols, rows], 1).astype(np.float64)
    mean = np.average(pts, axis=0, weights=w)
    cov = np.cov((pts - mean).T, aweights=w)
    lam, vec = np.linalg.eigh(cov)
    return math.degrees(math.atan2(vec[1, 1], vec[0, 1])) % 180.0, math.sqrt(lam[1] / lam[0])


def test_a_rods_blob_seeds_a_gaussian_drawn_along_the_rod():
    """A thin rod that no Gaussian draws: its blob's shape (`Blob.shape`) gives the seed's axes
    (`blob_axes`); the seed as `nehad.carve.new_gaussians` makes it, rendered through the same
    camera by the project's rasterizer, lies along the ray-cast rod (principal axis within 3
    degrees) and is long and thin like it; a round blob gives a round seed of the given
    size."""
    from nehad.carve import new_gaussians
    from nehad.gaussians import GaussianParameters
    from nehad.runtime.gaussians import GaussianCloud
    from nehad.runtime.raster import render

    like = GaussianParameters.from_points(np.zeros((3, 3)), sh_degree=0)
    cam = _camera(0)
    centre = np.array([0.0, 0.0, 0.6])
    for angle in (0.3, 1.2, 2.5):
        c, s = math.cos(angle), math.sin(angle)
        rod = Box("rod", centre, np.array([0.5, 0.02, 0.02]),
                  np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), COLOUR)
        full = render_view([rod], cam, supersample=2)
        target = full[..., :3] + (1.0 - full[..., 3:])
        (blob,) = find_blobs([cam], [0.0], [target], [full[..., 3]], [np.ones_like(target)],
                             min_area=1)
        _, depth = cam.project(centre[None])
        size = 0.8 * math.sqrt(blob.area / math.pi) * depth[0] / cam.fx  # seeds_along's width
        axes = blob_axes(blob, cam, size)
        scales = np.linalg.norm(axes, axis=0)
        assert np.isclose(np.prod(scales[:2]), size ** 2, rtol=1e-6)
        seed = new_gaussians(centre[None], np.ones((1, 3)), np.array([size]), 0.0, like, 0.9,
                             shapes=axes[None])  # the seed as training appends it
        cloud = GaussianCloud(centre[None], np.exp(seed["log_scales"].numpy()),
                              seed["quats"].numpy(), np.ones(1), np.zeros((1, 1, 3)))
        drawn = render(cloud, cam, (0.0, 0.0, 0.0), adapt_threads=False).alpha
        want_angle, want_ratio = _moments(full[..., 3])
        got_angle, got_ratio = _moments(drawn)
        diff = abs(want_angle - got_angle)
        assert min(diff, 180.0 - diff) < 3.0, (angle, want_angle, got_angle)
        assert want_ratio > 5 and got_ratio > 0.5 * want_ratio, (want_ratio, got_ratio)
    disc = Blob(0, 0.0, np.zeros(2), 50, np.ones(3), np.zeros(3), np.array([0.0, 0.0, 1.0]),
                np.eye(2) * 4.0)
    assert np.allclose(np.linalg.norm(blob_axes(disc, cam, 0.05), axis=0), 0.05)


def _exact_blob(view: int, t: float, cam, centre) -> Blob:
    """The blob a sphere centred at centre(t) leaves in `cam`: its centroid where the centre
    projects, 50 pixels, orange."""
    x = centre(t)
    w2c = cam.world_to_camera
    p = w2c[:3, :3] @ x + w2c[:3, 3]
    uv = np.array([cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy])
    o = cam.camera_to_world[:3, 3]
    return Blob(view, t, uv, 50, np.array([0.9, 0.5, 0.1]), o, (x - o) / np.linalg.norm(x - o))


def _rig_view(i: int, stride: int) -> Camera:
    """View i of a 200x200 walk through the stress rig, `stride` cameras on at each view."""
    f = 0.5 * 200 / math.tan(math.radians(25.0))
    rig = rig_cameras()
    return Camera.from_camera_to_world(rig[(stride * i) % len(rig)], 200, 200, f, f)


def test_a_track_is_followed_round_a_bend_across_held_out_times():
    """The stress suite's occluded loop (x = cos, y = 1.45 sin, z bobbing) at 120 timestamps,
    the rig's cameras in turn: no view in 0.445-0.5 or 0.615-0.67 (held out), and in 0.5-0.615
    every other view has no blob (the wall hides the sphere there), too few for a track of its
    own. Following the track with a quadratic carries it over the bend into that stretch: one
    track over all 56 blobs, on the path. With a straight line (grow_degree=1, the recipe
    before 2026-11-27) it stopped at 0.5 and 0.5-0.58 had no track: on the stress suite's
    occluder, seed 1, the sphere was missing there."""
    import dataclasses

    from nehad.tracks import TrackSettings

    def centre(t):
        a = 2.0 * math.pi * t
        return np.array([math.cos(a), 1.45 * math.sin(a), 0.4 + 0.25 * math.sin(2.0 * a)])

    times = [k / 120 for k in range(24, 100)]
    cams, blobs = [], []
    for i, t in enumerate(times):
        cams.append(_rig_view(i, 7))
        held = 0.445 < t < 0.5 or 0.615 < t < 0.67
        hidden = 0.5 <= t <= 0.615 and i % 2 == 1
        if not held and not hidden:
            blobs.append(_exact_blob(i, t, cams[-1], centre))
    tracks = fit_tracks(cams, blobs)
    assert [len(tr.blobs) for tr in tracks] == [len(blobs)] == [56]
    err = [np.linalg.norm(p - centre(t)) for t, p in zip(tracks[0].times, tracks[0].points)]
    assert max(err) < 0.01, err
    line = fit_tracks(cams, blobs, dataclasses.replace(TrackSettings(), grow_degree=1,
                                                       refit=False))
    covered = [(tr.times[0], tr.times[-1]) for tr in line]
    assert not any(lo <= 0.55 <= hi for lo, hi in covered), covered


def _ray_blob(blob: Blob, cam, shift) -> Blob:
    """`blob` with its centroid moved by `shift` pixels and its ray through the new centroid."""
    uv = blob.centre + shift
    ray = np.array([(uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy, 1.0])
    d = np.linalg.solve(cam.world_to_camera[:3, :3], ray)
    return dataclasses.replace(blob, centre=uv, direction=d / np.linalg.norm(d))


def test_a_track_is_followed_past_centroids_a_pixel_off():
    """The stress occluder variant's loop, two blocks of 14 views with 7 held out between them
    and two views hidden near the end, each blob's centroid (and ray) off by a normal pixel:
    the quadratic fitted to a track's last six blobs predicts the next one outside its gate
    here and there, and the track loses 3-4 of its 26 blobs; with the refit (a motion through
    those six and each candidate, kept when all seven land in their gates) it keeps all 26.
    On the variant itself the prediction missed by 10-28 pixels after the hidden views, and
    the sphere's last 0.05 of time had no track, chain or carried copy (docs/results.md,
    2026-11-30)."""
    def centre(t):
        a = 2.0 * math.pi * t + 0.7
        return np.array([1.35 * math.cos(a), 0.25 + 1.1 * math.sin(a),
                         0.3 + 0.15 * math.sin(3.0 * a)])

    for seed in range(3):
        rng = np.random.default_rng(seed)
        times = [k / 119 for k in range(80, 94)] + [k / 119 for k in range(100, 114)]
        cams, blobs = [], []
        for i, t in enumerate(times):
            cams.append(_rig_view(i, 7))
            if not 0.899 < t < 0.915:
                blobs.append(_ray_blob(_exact_blob(i, t, cams[-1], centre), cams[-1],
                                       rng.normal(0.0, 1.0, 2)))
        refit = fit_tracks(cams, blobs)
        assert [len(tr.blobs) for tr in refit] == [26]
        err = [np.linalg.norm(p - centre(t)) for t, p in zip(refit[0].times, refit[0].points)]
        assert np.median(err) < 0.05 and max(err) < 0.25, err  # on the path, ends looser
        before = fit_tracks(cams, blobs, dataclasses.replace(TrackSettings(), refit=False))
        assert max(len(tr.blobs) for tr in before) <= 23


def test_a_fast_ball_seen_in_seven_views_across_a_gap_is_one_track():
    """A ball thrown across the scene (a parabola, 2.5 units in 0.12 of time) seen in four
    training views, then none for seven (held out), then three: no straight line through four
    of them lands on a fifth, so before the curved hypotheses there was no track (the stress
    suite's fast ball variant, docs/results.md, 2026-11-30); a quadratic through five lands on
    all seven. The same views with the ball jumping about make none."""
    a, b = np.array([1.3, -1.1]), np.array([-1.2, 1.0])

    def centre(t):
        u = (t - 0.58) / 0.12
        return np.array([*(a + (b - a) * u), -0.25 + 5.0 * u * (1.0 - u)])

    seen = [70, 71, 72, 73, 80, 81, 82]
    cams = [_rig_view(i, 5) for i in range(len(seen))]
    blobs = [_exact_blob(i, k / 119, cams[i], centre) for i, k in enumerate(seen)]
    tracks = fit_tracks(cams, blobs)
    assert [len(tr.blobs) for tr in tracks] == [7]
    err = [np.linalg.norm(p - centre(t)) for t, p in zip(tracks[0].times, tracks[0].points)]
    assert max(err) < 0.02, err
    assert fit_tracks(cams, blobs, dataclasses.replace(TrackSettings(), curved=False)) == []
    rng = np.random.default_rng(0)
    jumps = [_exact_blob(i, k / 119, cams[i], lambda t: np.array(
        [rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(0.1, 1.0)]))
        for i, k in enumerate(seen)]
    assert fit_tracks(cams, jumps) == []


def test_every_object_gets_a_track_up_to_the_cap():
    """Ten objects of ten colours, each on its own straight path and seen in a stretch of its
    own length (12 to 30 views): with a cap of 32 each is one track, on its path; with a cap
    of 4, four of them. The recipe's passes followed at most 8 tracks until
    2026-11-28, and 8 was reached in most passes of the stress suite and the shared scenes
    (docs/results.md): an object without one of the 8 places got no chain."""
    import colorsys
    import dataclasses

    from nehad.tracks import TrackSettings

    rig = rig_cameras()
    f = 0.5 * 200 / math.tan(math.radians(25.0))
    times = [k / 120 for k in range(120)]
    cams = [Camera.from_camera_to_world(rig[(7 * i) % len(rig)], 200, 200, f, f)
            for i in range(len(times))]
    lengths = [12 + 2 * j for j in range(10)]  # views each object is seen in

    def centre_of(j):
        a = 2.0 * math.pi * j / 10
        start = np.array([1.1 * math.cos(a), 1.1 * math.sin(a), 0.3 + 0.05 * j])
        return lambda t: start + np.array([-math.sin(a), math.cos(a), 0.0]) * 0.8 * t

    blobs = []
    for j, n in enumerate(lengths):
        colour = np.array(colorsys.hsv_to_rgb(j / 10, 0.9, 0.9))
        first = (7 * j) % (len(times) - n)
        for i in range(first, first + n):
            b = _exact_blob(i, times[i], cams[i], centre_of(j))
            blobs.append(dataclasses.replace(b, colour=colour))
    wide = fit_tracks(cams, blobs, dataclasses.replace(TrackSettings(), max_tracks=32))
    assert sorted(len(tr.blobs) for tr in wide) == lengths
    for tr in wide:  # each track on one object's path
        errs = [min(np.linalg.norm(p - centre_of(j)(t)) for j in range(10))
                for t, p in zip(tr.times, tr.points)]
        assert max(errs) < 0.01, errs
    # with a cap of 4, four whole objects (which four follows the hypotheses' local support,
    # not the stretches' lengths)
    capped = fit_tracks(cams, blobs, dataclasses.replace(TrackSettings(), max_tracks=4))
    assert len(capped) == 4 and {len(tr.blobs) for tr in capped} <= set(lengths)


def test_smooth_path_keeps_the_curve_across_a_gap():
    """Track.smooth_at between two samples of a circle 0.4 rad apart, with their exact
    velocities: within 1/50 of the chord's sagitta at the middle, its velocity tangent and of
    the circle's speed; outside the span and at the samples it is Track.at."""
    from nehad.tracks import Track

    def circle(t):
        return np.array([math.cos(t), math.sin(t), 0.0]), np.array([-math.sin(t), math.cos(t), 0.0])

    times = np.array([0.0, 0.1, 0.5, 0.6])  # a gap of 0.4 between the middle two
    pts, vel = zip(*(circle(t) for t in times))
    tr = Track([], times, np.array(pts), np.array(vel))
    p, v = tr.smooth_at(np.array([0.3]))
    want, want_v = circle(0.3)
    sagitta = 1.0 - math.cos(0.2)
    assert np.linalg.norm(tr.at(np.array([0.3]))[0][0] - want) > 0.9 * sagitta  # the chord
    assert np.linalg.norm(p[0] - want) < sagitta / 50
    assert np.linalg.norm(v[0] - want_v) < 0.01
    for t in (-0.05, 0.0, 0.1, 0.6, 0.7):  # the samples and outside: as `at`
        a, b = tr.at(np.array([t])), tr.smooth_at(np.array([t]))
        assert np.allclose(a[0], b[0], atol=1e-12) and np.allclose(a[1], b[1], atol=1e-12)


def test_a_thrown_balls_path_runs_on_with_its_acceleration():
    """The stress fast ball (flight over t 0.33-0.48, landing under the floor) seen in the 14
    training views of its flight, the rig's cameras in turn: past the track's last blob,
    Track.smooth_at follows the end sample's acceleration as well as its velocity. One to three
    frames on (the test frames) it is within a fifth of the ball's radius of the truth, and at
    the next held-out frame it is under the floor like the ball. Along the end velocity alone
    (Track.at) it is over 0.2 above the truth three frames on and still above the floor there."""
    def centre(t):
        u = (t - 0.33) / 0.15
        return np.array([-1.5 + 3.0 * u, 0.3, -0.3 + 6.4 * u * (1.0 - u)])

    times = [k / 119 for k in range(41, 54)]
    cams = [_rig_view(i, 5) for i in range(len(times))]
    blobs = [_exact_blob(i, t, cam, centre) for i, (t, cam) in enumerate(zip(times, cams))]
    tracks = fit_tracks(cams, blobs)
    assert [len(tr.blobs) for tr in tracks] == [13]
    tr = tracks[0]
    later = np.array([54, 55, 56]) / 119
    got = tr.smooth_at(later)[0]
    err = np.linalg.norm(got - np.stack([centre(t) for t in later]), axis=1)
    assert err.max() < 0.2 * 0.15, err
    landed = 57 / 119
    assert tr.smooth_at(np.array([landed]))[0][0, 2] < -0.15  # under the floor, as the ball
    straight = tr.at(np.array([landed]))[0][0, 2]
    assert straight - centre(landed)[2] > 0.2 and straight > -0.15


def test_tracks_with_a_hole_where_the_field_draws_are_completed_by_the_whole_track():
    """`completed`: a sphere on a loop over 60 views; what the model does not draw is two
    tracks, over t < 0.4 and t > 0.6 (the field draws it between), the moving objects' track
    all 60 views. The two become one track of every blob, on the path. A track of another
    object, and one over the same views whose blobs lie 12 pixels off the whole track's (past
    its gate) or are another colour, stay as they were."""
    from nehad.tracks import Track, _samples, completed

    def centre(t):
        a = 2.0 * math.pi * t
        return np.array([math.cos(a), 1.45 * math.sin(a), 0.4 + 0.25 * math.sin(2.0 * a)])

    def still(t):
        return np.array([0.0, 0.0, 0.5])

    s = TrackSettings()
    times = [k / 60 for k in range(60)]
    cams = [_rig_view(i, 7) for i in range(60)]
    blobs = [_exact_blob(i, t, c, centre) for i, (t, c) in enumerate(zip(times, cams))]
    whole = _samples(cams, Track(blobs), s)
    before = _samples(cams, Track([b for b in blobs if b.time < 0.4]), s)
    after = _samples(cams, Track([b for b in blobs if b.time > 0.6]), s)
    other = _samples(cams, Track([_exact_blob(i, t, c, still)
                                  for i, (t, c) in enumerate(zip(times, cams)) if t < 0.3]), s)
    off = Track([dataclasses.replace(b, centre=b.centre + [12.0, 0.0]) for b in before.blobs])
    blue = Track([dataclasses.replace(b, colour=np.array([0.1, 0.3, 0.9])) for b in after.blobs])
    assert len(whole.blobs) == 60 and len(before.blobs) == 24 and len(after.blobs) == 23
    out = completed([before, other, off, blue, after], [whole], cams, s)
    assert out[:3] == [other, off, blue]
    assert len(out) == 4 and len(out[3].blobs) == 60
    assert sorted(b.time for b in out[3].blobs) == times
    err = [np.linalg.norm(p - centre(t)) for t, p in zip(out[3].times, out[3].points)]
    assert max(err) < 0.01, max(err)
    assert completed([before], [], cams, s) == [before]
