"""The shared rasterizer against independent references (docs/design.md section 6).

Forward: the brute-force float64 rasterizer of raster_reference.py (every Gaussian of a tile at every
pixel). Backward: torch autograd through a dense torch compositing, plus float64 finite
differences of the brute-force forward. Projection: the NumPy/Numba stage against its torch twin.
"""

from __future__ import annotations

import numpy as np
import pytest

from nehad.runtime.cameras import Camera
from nehad.runtime.gaussians import GaussianCloud
from nehad.runtime.raster import project_gaussians, rasterize, rasterize_backward, render

from raster_reference import dense_composite_torch, random_screen_scene, reference_forward

torch = pytest.importorskip("torch")

SCREEN_CASES = [
    # n, width, height, min_sigma, max_sigma, background, seed
    (300, 64, 48, 0.3, 12.0, (0.0, 0.0, 0.0), 0),
    (2000, 100, 77, 0.3, 6.0, (1.0, 1.0, 1.0), 1),  # sizes not multiples of 16, dense
    (600, 33, 130, 0.2, 40.0, (0.2, 0.5, 0.9), 2),  # large, anisotropic, tiny ones
    (12000, 48, 48, 1.0, 4.0, (0.0, 0.0, 0.0), 3),  # saturating: most pixels stop early
]


@pytest.mark.parametrize("n,width,height,smin,smax,bg,seed", SCREEN_CASES)
def test_forward_matches_brute_force(n, width, height, smin, smax, bg, seed):
    rng = np.random.default_rng(seed)
    m, cn, col, op, dep, rad = random_screen_scene(rng, n, width, height, min_sigma=smin,
                                                   max_sigma=smax)
    out = rasterize(m, cn, col, op, dep, rad, width, height, bg)
    rgb, alpha, depth, ambiguous = reference_forward(m, cn, col, op, dep, rad, width, height, bg)
    ok = ~ambiguous
    # pixels whose result hinges on a threshold within float32 rounding are few
    assert ambiguous.mean() < 0.005
    print(f"forward vs brute force, {n} Gaussians {width}x{height}: max |diff| rgb "
          f"{np.abs(out.rgb - rgb)[ok].max():.2g}, alpha {np.abs(out.alpha - alpha)[ok].max():.2g}")
    assert np.abs(out.rgb - rgb)[ok].max() <= 1e-4
    assert np.abs(out.alpha - alpha)[ok].max() <= 1e-4
    # depth is a weighted mean of z in [0.5, 10]: compare relative to the depth range
    covered = ok & (alpha > 0.05)
    assert np.abs(out.depth - depth)[covered].max() <= 1e-4 * 10
    if n == 12000:
        assert (out.stop < 2 ** 30).mean() > 0.5, "scene meant to exercise the early stop"


def _camera(width, height, fov_deg=60.0, distance=3.0):
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, -distance]  # OpenCV: looking along +z at the origin
    return Camera.from_camera_to_world(c2w, width, height, f, f, convention="opencv")


def _random_cloud(rng, n, degree, spread=1.5):
    q = rng.normal(size=(n, 4))
    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.3, size=(n, k, 3))
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    means = rng.uniform(-spread, spread, (n, 3))
    means[: n // 10, 2] = rng.uniform(-6.0, -3.0, n // 10)  # some behind the camera
    scales = np.exp(rng.uniform(np.log(0.005), np.log(0.3), (n, 3)))
    return GaussianCloud(means, scales, q / np.linalg.norm(q, axis=1, keepdims=True),
                         rng.uniform(0.05, 0.99, n), sh)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_projection_numba_matches_torch(degree):
    from nehad.splat.projection import project_gaussians_torch

    rng = np.random.default_rng(10 + degree)
    cloud = _random_cloud(rng, 3000, degree)
    cam = _camera(96, 80)
    p = project_gaussians(cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh, cam)
    t = lambda a: torch.tensor(a, dtype=torch.float64)
    pt = project_gaussians_torch(t(cloud.means), t(cloud.scales), t(cloud.quats),
                                 t(cloud.opacities), t(cloud.sh), cam)
    assert (p.radii == pt.radii.numpy()).mean() > 0.999
    vis = (p.radii > 0) & (pt.radii.numpy() > 0)
    assert vis.sum() > 500 and (p.radii == 0).sum() >= 300  # culled ones include those behind
    for name in ("means2d", "conics", "colors", "depths"):
        a = getattr(p, name)[vis]
        b = getattr(pt, name).detach().numpy()[vis]
        assert np.abs(a - b).max() <= 1e-5 * max(1.0, np.abs(b).max()), name


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_projection_gradients_match_autograd(degree):
    """The Numba projection's backward (what training uses) against torch autograd through the
    twin in float64, for random upstream gradients on the visible Gaussians; the cloud has
    Gaussians beyond the frustum clamp and large ones."""
    from nehad.splat.projection import project_gaussians_numba, project_gaussians_torch

    rng = np.random.default_rng(20 + degree)
    cloud = _random_cloud(rng, 3000, degree)
    cam = _camera(96, 80)
    w2c = np.asarray(cam.world_to_camera)
    in_cam = cloud.means @ w2c[:3, :3].T + w2c[:3, 3]
    lim = 1.3 * cam.width / (2 * cam.fx)
    params64 = [torch.tensor(np.asarray(a, np.float64), requires_grad=True)
                for a in (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh)]
    params32 = [torch.tensor(a, requires_grad=True)
                for a in (cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh)]
    ref = project_gaussians_torch(*params64, cam)
    ours = project_gaussians_numba(*params32, cam)
    vis = ours.radii.numpy() > 0
    clamped = (np.abs(in_cam[:, 0] / in_cam[:, 2]) > lim) & vis
    assert vis.sum() > 500 and clamped.sum() >= 5
    ups = [torch.tensor(rng.normal(size=(3000, c)) * vis[:, None]) for c in (2, 3, 3)]
    for proj, dt in ((ref, torch.float64), (ours, torch.float32)):
        loss = sum((out * up.to(dt)).sum()
                   for out, up in zip((proj.means2d, proj.conics, proj.colors), ups))
        loss.backward()
    for name, a, b in zip(("means", "scales", "quats", "opacities", "sh"), params32, params64):
        if name == "opacities":
            continue  # they pass through the projection
        got, want = a.grad.numpy(), b.grad.numpy()
        assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max(), name
        assert np.abs(want).max() > 0, name


def test_render_of_cloud_matches_brute_force_with_torch_projection():
    """Whole pipeline: Numba projection + rasterizer vs. torch projection + brute force."""
    from nehad.splat.projection import project_gaussians_torch

    rng = np.random.default_rng(7)
    cloud = _random_cloud(rng, 1500, 2)
    cam = _camera(72, 56)
    out = render(cloud, cam, background=(1.0, 1.0, 1.0))
    t = lambda a: torch.tensor(a, dtype=torch.float64)
    pt = project_gaussians_torch(t(cloud.means), t(cloud.scales), t(cloud.quats),
                                 t(cloud.opacities), t(cloud.sh), cam)
    rgb, alpha, _, amb = reference_forward(pt.means2d.numpy(), pt.conics.numpy(),
                                           pt.colors.numpy(), pt.opacities.numpy(),
                                           pt.depths.numpy(), pt.radii.numpy(), 72, 56,
                                           (1.0, 1.0, 1.0))
    assert amb.mean() < 0.01
    assert np.abs(out.rgb - rgb)[~amb].max() <= 1e-4
    assert np.abs(out.alpha - alpha)[~amb].max() <= 1e-4


def _rel_err(a, b):
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)


@pytest.mark.parametrize("seed,n,width,height,min_sigma,max_sigma", [
    (1, 400, 50, 40, 0.3, 8.0),
    (2, 1500, 48, 48, 0.3, 8.0),
    (3, 6000, 40, 40, 1.0, 4.0),  # saturating: tiles stop before their last entries
])
def test_backward_matches_autograd(seed, n, width, height, min_sigma, max_sigma):
    rng = np.random.default_rng(seed)
    bg = (0.2, 0.3, 0.4)
    m, cn, col, op, dep, rad = random_screen_scene(rng, n, width, height, min_sigma=min_sigma,
                                                   max_sigma=max_sigma)
    out = rasterize(m, cn, col, op, dep, rad, width, height, bg)
    if n == 6000:
        assert (out.stop < 2 ** 30).mean() > 0.5, "scene meant to exercise the early stop"
    g_rgb = rng.normal(size=(height, width, 3)).astype(np.float32)
    g_alpha = rng.normal(size=(height, width)).astype(np.float32)
    grads = rasterize_backward(out, g_rgb, g_alpha)

    t = lambda a: torch.tensor(a, dtype=torch.float64, requires_grad=True)
    M, CN, COL, OP = t(m), t(cn), t(col), t(op)
    rgb, alpha = dense_composite_torch(M, CN, COL, OP, torch.tensor(dep, dtype=torch.float64),
                                       rad, width, height, bg)
    assert np.abs(rgb.detach().numpy() - out.rgb).max() < 1e-4
    loss = (rgb * torch.tensor(g_rgb, dtype=torch.float64)).sum() + \
        (alpha * torch.tensor(g_alpha, dtype=torch.float64)).sum()
    loss.backward()
    for name, ours, ref in [("means2d", grads.means2d, M.grad), ("conics", grads.conics, CN.grad),
                            ("colors", grads.colors, COL.grad),
                            ("opacities", grads.opacities, OP.grad)]:
        ref = ref.numpy()
        assert np.abs(ref).max() > 0, name
        print(f"backward vs autograd, {n} Gaussians: {name} relative error "
              f"{_rel_err(ours, ref):.2g}")
        assert _rel_err(ours, ref) <= 1e-3, name
        # and element-wise where the gradient is not tiny
        big = np.abs(ref) > 1e-2 * np.abs(ref).max()
        assert np.max(np.abs(ours - ref)[big] / np.abs(ref)[big]) <= 1e-2, name


def test_backward_finite_differences_float64():
    """Spot checks of the kernel's gradients against central differences of the float64
    brute-force forward (independent of torch and of the kernels)."""
    rng = np.random.default_rng(5)
    w = h = 32
    m, cn, col, op, dep, rad = random_screen_scene(rng, 60, w, h, min_sigma=1.0, max_sigma=5.0,
                                                   offscreen=0.0)
    weights = rng.normal(size=(h, w, 3))
    out = rasterize(m, cn, col, op, dep, rad, w, h)
    grads = rasterize_backward(out, weights.astype(np.float32))

    def loss(mm, cc, co, oo):
        rgb, _, _, _ = reference_forward(mm, cc, co, oo, dep, rad, w, h)
        return float((rgb * weights).sum())

    base = [m.astype(np.float64), cn.astype(np.float64), col.astype(np.float64),
            op.astype(np.float64)]
    ours = [grads.means2d, grads.conics, grads.colors, grads.opacities]
    checked = 0
    for slot in range(4):
        flat = np.abs(ours[slot]).ravel()
        for idx in np.argsort(flat)[-4:]:  # the largest gradients of each input
            eps = 1e-6 * max(1.0, abs(base[slot].ravel()[idx]))
            plus = [b.copy() for b in base]
            minus = [b.copy() for b in base]
            plus[slot].ravel()[idx] += eps
            minus[slot].ravel()[idx] -= eps
            fd = (loss(*plus) - loss(*minus)) / (2 * eps)
            assert abs(ours[slot].ravel()[idx] - fd) <= 2e-3 * abs(fd) + 1e-4, (slot, idx)
            checked += 1
    assert checked == 16


def test_autograd_function_end_to_end_against_dense_reference():
    """Gradients w.r.t. 3D parameters: torch projection + our kernels vs. torch projection +
    dense torch compositing (float64)."""
    from nehad.splat.projection import project_gaussians_torch
    from nehad.splat.rasterize import render_torch

    rng = np.random.default_rng(11)
    cloud = _random_cloud(rng, 300, 1, spread=1.0)
    cam = _camera(40, 40)
    target = torch.tensor(rng.uniform(size=(40, 40, 3)))

    def params():
        t = lambda a: torch.tensor(a, dtype=torch.float64, requires_grad=True)
        return [t(cloud.means), t(cloud.scales), t(cloud.quats), t(cloud.opacities), t(cloud.sh)]

    ours = params()
    res = render_torch(*ours, cam, background=(1.0, 1.0, 1.0))
    ((res.rgb - target) ** 2).sum().backward()
    ref = params()
    pt = project_gaussians_torch(*ref, cam)
    rgb, _ = dense_composite_torch(pt.means2d, pt.conics, pt.colors, pt.opacities, pt.depths,
                                   pt.radii.numpy(), 40, 40, (1.0, 1.0, 1.0))
    ((rgb - target) ** 2).sum().backward()
    for name, a, b in zip(["means", "scales", "quats", "opacities", "sh"], ours, ref):
        assert _rel_err(a.grad.numpy(), b.grad.numpy()) <= 1e-3, name
    assert res.means2d.grad is not None and res.means2d.grad.abs().sum() > 0


def test_non_finite_inputs_are_invisible_not_fatal():
    rng = np.random.default_rng(9)
    m, cn, col, op, dep, rad = random_screen_scene(rng, 200, 40, 40)
    bad = [(m, 0, np.nan), (m, 1, np.inf), (cn, 2, np.nan), (cn, 3, -np.inf), (op, 4, np.nan),
           (dep, 5, np.nan), (cn, 6, 1e38)]
    for arr, i, v in bad:
        arr[i] = v
    out = rasterize(m, cn, col, op, dep, rad, 40, 40)
    assert np.isfinite(out.rgb).all() and np.isfinite(out.alpha).all()
    assert not np.isin(np.arange(7), out.bins.gauss_ids).any()
    grads = rasterize_backward(out, np.ones((40, 40, 3), np.float32))
    assert np.isfinite(grads.means2d).all()


def test_culled_and_empty_inputs():
    cam = _camera(32, 32)
    behind = GaussianCloud(np.array([[0.0, 0.0, -5.0]]), np.full((1, 3), 0.1),
                           np.array([[1.0, 0, 0, 0]]), np.array([0.9]), np.zeros((1, 1, 3)))
    out = render(behind, cam, background=(0.25, 0.5, 0.75))
    assert np.allclose(out.rgb, [0.25, 0.5, 0.75]) and np.all(out.alpha == 0)
    grads = rasterize_backward(out, np.ones((32, 32, 3), np.float32))
    assert np.all(grads.means2d == 0)


def test_hidden_gaussians_get_exactly_zero_gradient():
    """Entries behind every pixel's stopping point receive no gradient, whatever memory the
    gradient buffers were carved from (a regression: they once summed uninitialised memory)."""
    rng = np.random.default_rng(4)
    w = h = 32
    n_wall, n_hidden = 400, 300
    means2d = np.concatenate([rng.uniform(0, w, (n_wall, 2)), rng.uniform(4, w - 4, (n_hidden, 2))])
    conics = np.tile([[0.02, 0.0, 0.02]], (n_wall + n_hidden, 1))
    colors = rng.uniform(0, 1, (n_wall + n_hidden, 3))
    opac = np.concatenate([np.full(n_wall, 0.99), np.full(n_hidden, 0.9)])
    depths = np.concatenate([rng.uniform(1, 2, n_wall), rng.uniform(5, 6, n_hidden)])
    radii = np.full(n_wall + n_hidden, 22, np.int32)
    f32 = lambda a: np.asarray(a, np.float32)
    out = rasterize(f32(means2d), f32(conics), f32(colors), f32(opac), f32(depths), radii, w, h)
    assert (out.stop < 2 ** 30).all()
    for _ in range(3):
        # leave NaN-filled blocks of the gradient buffer's size behind in the allocator
        junk = [np.full((out.bins.gauss_ids.shape[0], 9), np.nan, np.float32) for _ in range(4)]
        del junk
        grads = rasterize_backward(out, np.ones((h, w, 3), np.float32))
        for a in (grads.means2d, grads.conics, grads.colors, grads.opacities):
            assert np.isfinite(a).all()
        assert np.all(grads.colors[n_wall:] == 0) and np.all(grads.opacities[n_wall:] == 0)


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="glibc only")
def test_heap_keeps_freed_frame_buffers():
    """Importing the rasterizer raises glibc's mmap/trim thresholds (runtime/raster/heap.py): a
    16 MB array then comes from the heap (below the program break) instead of fresh mmap pages;
    with NEHAD_KEEP_HEAP=0 the allocator is left alone."""
    import subprocess
    import sys

    probe = ("import ctypes, numpy as np; import nehad.runtime.raster as r; "
             "from nehad.runtime.raster.heap import keep_freed_memory as k; "
             "libc = ctypes.CDLL('libc.so.6'); libc.sbrk.restype = ctypes.c_void_p; "
             "a = np.empty(16 << 20, np.uint8); brk = libc.sbrk(0); "
             "print(k(), a.ctypes.data < brk)")
    env = {k: v for k, v in __import__("os").environ.items() if k != "NEHAD_KEEP_HEAP"}
    on = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                        env=env)
    off = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                         env={**env, "NEHAD_KEEP_HEAP": "0"})
    assert on.stdout.split() == ["True", "True"], on.stdout + on.stderr
    assert off.stdout.split() == ["False", "False"], off.stdout + off.stderr


def test_fma32_rounds_once():
    """intrinsics.fma32 is a fused multiply-add: (1 + 2^-12)^2 - (1 + 2^-11) is 2^-24 exactly,
    which a float32 multiply then add rounds away."""
    import numba

    from nehad.runtime.raster.intrinsics import fma32

    @numba.njit
    def both(a, b, c):
        return fma32(a, b, c), a * b + c

    a = np.float32(1 + 2 ** -12)
    fused, separate = both(a, a, np.float32(-(1 + 2 ** -11)))
    assert fused == np.float32(2 ** -24)
    assert separate == 0.0


def test_frames_and_tile_lists_do_not_depend_on_the_thread_count():
    """The thread count (which runtime/threads.py changes with the load; it is also the number
    of binning chunks and the tile order's interleave) changes no byte of a frame or of its
    tile lists."""
    import numba

    rng = np.random.default_rng(5)
    n = 40_000  # enough for several binning chunks per thread
    q = rng.normal(size=(n, 4))
    cloud = GaussianCloud(rng.uniform(-1, 1, (n, 3)), rng.uniform(0.005, 0.03, (n, 3)),
                          q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(0.05, 0.9, n),
                          rng.normal(size=(n, 1, 3)))
    c2w = np.eye(4)  # OpenCV axes: x right, y down, z forward; the camera at y = -3.5 looks at 0
    c2w[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    c2w[:3, 3] = [0.0, -3.5, 0.0]
    cam = Camera.from_camera_to_world(c2w, 160, 120, 130.0, 130.0, convention="opencv")
    outs = []
    try:
        for threads in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(threads)  # also the binning's chunk count
            outs.append(render(cloud, cam, adapt_threads=False))
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    first = outs[0]
    assert (first.alpha > 0.5).mean() > 0.3  # a real picture
    for out in outs[1:]:
        np.testing.assert_array_equal(out.rgb, first.rgb)
        np.testing.assert_array_equal(out.stop, first.stop)
        np.testing.assert_array_equal(out.bins.gauss_ids, first.bins.gauss_ids)
        np.testing.assert_array_equal(out.bins.tile_offsets, first.bins.tile_offsets)


def test_an_empty_cloud_renders_the_background():
    """A model whose Gaussians were all pruned (the stress suite's thin rod) still renders and
    scores: the background everywhere, alpha 0."""
    from nehad.runtime.gaussians import GaussianCloud

    cloud = GaussianCloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0),
                          np.zeros((0, 16, 3)))
    assert cloud.sh.shape == (0, 16, 3) and cloud.sh_degree == 3
    cam = Camera.from_camera_to_world(np.eye(4), 24, 16, 20.0, 20.0)
    out = render(cloud, cam, (0.25, 0.5, 1.0))
    assert out.rgb.shape == (16, 24, 3) and np.allclose(out.rgb, [0.25, 0.5, 1.0])
    assert np.all(out.alpha == 0)
