"""Independent brute-force references for the rasterizer tests (docs/design.md section 6).

Nothing here calls the project's kernels: tile membership is recomputed from the 3-sigma rule,
every Gaussian of a tile is evaluated at every pixel of the tile in float64, and the compositing
rules are applied pixel by pixel. `dense_composite_torch` is the same compositing written with
torch tensor operations, so autograd gives reference gradients.
"""

from __future__ import annotations

import math

import numpy as np

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def tile_lists(means2d, radii, depths, width, height):
    """For each tile, the Gaussians whose 3-sigma box overlaps it (3DGS getRect), by depth."""
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    lists = [[] for _ in range(ntx * nty)]
    order = np.argsort(depths, kind="stable")
    for g in order:
        r = int(radii[g])
        if r <= 0:
            continue
        px, py = float(means2d[g, 0]) - 0.5, float(means2d[g, 1]) - 0.5
        x0 = min(ntx, max(0, math.floor((px - r) / TILE)))
        x1 = min(ntx, max(0, math.floor((px + r + TILE - 1) / TILE)))
        y0 = min(nty, max(0, math.floor((py - r) / TILE)))
        y1 = min(nty, max(0, math.floor((py + r + TILE - 1) / TILE)))
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                lists[ty * ntx + tx].append(int(g))
    return lists, ntx, nty


def reference_forward(means2d, conics, colors, opacities, depths, radii, width, height,
                      background=(0, 0, 0), alpha_tol=2e-5, t_tol=2e-4):
    """float64 brute force. Returns rgb, alpha, depth and `ambiguous`: pixels where some decision
    (alpha >= 1/255, T >= 1e-4) sits within float32 rounding of its threshold."""
    means2d, conics, colors = (np.asarray(a, np.float64) for a in (means2d, conics, colors))
    opacities, depths = np.asarray(opacities, np.float64), np.asarray(depths, np.float64)
    bg = np.asarray(background, np.float64)
    rgb = np.zeros((height, width, 3))
    alpha_img = np.zeros((height, width))
    depth_img = np.zeros((height, width))
    ambiguous = np.zeros((height, width), bool)
    lists, ntx, nty = tile_lists(means2d, radii, depths, width, height)
    for tile, ids in enumerate(lists):
        tx, ty = tile % ntx, tile // ntx
        xs = np.arange(tx * TILE, min(width, tx * TILE + TILE))
        ys = np.arange(ty * TILE, min(height, ty * TILE + TILE))
        px, py = np.meshgrid(xs + 0.5, ys + 0.5)
        T = np.ones(px.shape)
        C = np.zeros(px.shape + (3,))
        D = np.zeros(px.shape)
        done = np.zeros(px.shape, bool)
        amb = np.zeros(px.shape, bool)
        for g in ids:
            dx, dy = px - means2d[g, 0], py - means2d[g, 1]
            a, b, c = conics[g]
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            alpha = np.minimum(ALPHA_MAX, opacities[g] * np.exp(power))
            amb |= ~done & (np.abs(alpha - ALPHA_MIN) < alpha_tol * ALPHA_MIN)
            live = ~done & (alpha >= ALPHA_MIN)
            t_next = T * (1 - alpha)
            amb |= live & (np.abs(t_next - T_MIN) < t_tol * T_MIN)
            halt = live & (t_next < T_MIN)
            go = live & ~halt
            w = np.where(go, alpha * T, 0.0)
            C += w[..., None] * colors[g]
            D += w * depths[g]
            T = np.where(go, t_next, T)
            done |= halt
        sl = (slice(ys[0], ys[-1] + 1), slice(xs[0], xs[-1] + 1))
        rgb[sl] = C + T[..., None] * bg
        alpha_img[sl] = 1 - T
        depth_img[sl] = D / np.maximum(1 - T, 1e-8)
        ambiguous[sl] = amb
    return rgb, alpha_img, depth_img, ambiguous


def dense_composite_torch(means2d, conics, colors, opacities, depths, radii, width, height,
                          background=(0, 0, 0)):
    """The same compositing with torch ops over dense (pixels x tile-Gaussians) matrices.

    Differentiable in means2d, conics, colors, opacities. Stopping decisions are taken on
    detached values (they are piecewise constant). Returns rgb (H, W, 3) and alpha (H, W).
    """
    import torch

    dt = means2d.dtype
    bg = torch.as_tensor(background, dtype=dt)
    lists, ntx, nty = tile_lists(means2d.detach().numpy(), radii, depths.detach().numpy(),
                                 width, height)
    rows = []
    for ty in range(nty):
        row = []
        for tx in range(ntx):
            ids = lists[ty * ntx + tx]
            xs = torch.arange(tx * TILE, min(width, tx * TILE + TILE), dtype=dt) + 0.5
            ys = torch.arange(ty * TILE, min(height, ty * TILE + TILE), dtype=dt) + 0.5
            py, px = torch.meshgrid(ys, xs, indexing="ij")
            px, py = px.reshape(-1, 1), py.reshape(-1, 1)
            if not ids:
                rgb = bg.expand(px.shape[0], 3)
                alpha = torch.zeros(px.shape[0], dtype=dt)
            else:
                idx = torch.as_tensor(ids)
                m, cn = means2d[idx], conics[idx]
                dx, dy = px - m[:, 0], py - m[:, 1]
                power = -0.5 * (cn[:, 0] * dx * dx + cn[:, 2] * dy * dy) - cn[:, 1] * dx * dy
                a = torch.clamp(opacities[idx] * torch.exp(power), max=ALPHA_MAX)
                with torch.no_grad():
                    ad = a.detach().numpy()
                    live = ad >= ALPHA_MIN
                    keep = np.zeros_like(live)
                    T = np.ones(ad.shape[0])
                    done = np.zeros(ad.shape[0], bool)
                    for i in range(ad.shape[1]):
                        li = live[:, i] & ~done
                        tn = T * (1 - ad[:, i])
                        halt = li & (tn < T_MIN)
                        go = li & ~halt
                        keep[:, i] = go
                        T = np.where(go, tn, T)
                        done |= halt
                keep_t = torch.as_tensor(keep)
                a = torch.where(keep_t, a, torch.zeros((), dtype=dt))
                one_minus = 1 - a
                T = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus], 1), 1)
                w = a * T[:, :-1]
                rgb = w @ colors[idx] + T[:, -1:] * bg
                alpha = 1 - T[:, -1]
            row.append((rgb.reshape(len(ys), len(xs), 3), alpha.reshape(len(ys), len(xs))))
        rows.append(row)
    rgb = torch.cat([torch.cat([r[0] for r in row], 1) for row in rows], 0)
    alpha = torch.cat([torch.cat([r[1] for r in row], 1) for row in rows], 0)
    return rgb, alpha


def random_screen_scene(rng, n, width, height, *, min_sigma=0.3, max_sigma=12.0, offscreen=0.15):
    """Random screen-space Gaussians: varied sizes, anisotropic and tiny ones, some across the
    image border. Returns means2d, conics, colors, opacities, depths, radii (float64/int)."""
    margin = offscreen * max(width, height)
    means2d = np.stack([rng.uniform(-margin, width + margin, n),
                        rng.uniform(-margin, height + margin, n)], 1)
    sig = np.exp(rng.uniform(np.log(min_sigma), np.log(max_sigma), (n, 2)))
    theta = rng.uniform(0, np.pi, n)
    c, s = np.cos(theta), np.sin(theta)
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0] = c * c * sig[:, 0] ** 2 + s * s * sig[:, 1] ** 2 + 0.3
    cov[:, 1, 1] = s * s * sig[:, 0] ** 2 + c * c * sig[:, 1] ** 2 + 0.3
    cov[:, 0, 1] = cov[:, 1, 0] = c * s * (sig[:, 0] ** 2 - sig[:, 1] ** 2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    conics = np.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], 1)
    mid = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    lam = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
    radii = np.ceil(3 * np.sqrt(lam)).astype(np.int32)
    colors = rng.uniform(0, 1, (n, 3))
    opacities = rng.uniform(0.02, 1.0, n)
    depths = rng.uniform(0.5, 10.0, n)
    f32 = lambda a: a.astype(np.float32)
    return f32(means2d), f32(conics), f32(colors), f32(opacities), f32(depths), radii


# ---------------------------------------------------------------------------------------------
# projection (3D Gaussians + camera -> the screen-space inputs of reference_forward)

# Standard 3DGS SH constants (computeColorFromSH), written out again here so that the reference
# shares nothing with nehad.runtime.raster.sh.
_REF_C0 = 0.28209479177387814
_REF_C1 = 0.4886025119029199
_REF_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
           0.5462742152960396)
_REF_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
           -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def _reference_sh_basis(dirs, degree):
    """(N, (degree+1)^2) real SH basis of the 3DGS code for unit directions (N, 3)."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    cols = [np.full_like(x, _REF_C0)]
    if degree >= 1:
        cols += [-_REF_C1 * y, _REF_C1 * z, -_REF_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [_REF_C2[0] * x * y, _REF_C2[1] * y * z, _REF_C2[2] * (2 * zz - xx - yy),
                 _REF_C2[3] * x * z, _REF_C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [_REF_C3[0] * y * (3 * xx - yy), _REF_C3[1] * x * y * z,
                 _REF_C3[2] * y * (4 * zz - xx - yy), _REF_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                 _REF_C3[4] * x * (4 * zz - xx - yy), _REF_C3[5] * z * (xx - yy),
                 _REF_C3[6] * x * (xx - 3 * yy)]
    return np.stack(cols, axis=1)


def _reference_rotation(q):
    """Rotation matrix of a quaternion (w, x, y, z), normalised here."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def reference_project(means, scales, quats, opacities, sh, camera, sh_degree=None,
                      near=0.2, dilation=0.3, clamp=1.3):
    """float64 matrix-form EWA projection of activated 3D Gaussians through a `Camera`
    (docs/design.md sections 3 and 6), one Gaussian at a time.

    Sigma = R S S^T R^T; p = W mu + t (world_to_camera, OpenCV axes); cull z <= `near`;
    J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with x/z, y/z clamped to
    `clamp` tan(fov/2), tan(fov_x/2) = width / (2 fx); Sigma2D = J W Sigma W^T J^T + `dilation` I;
    conic = Sigma2D^-1 as (a, b, c); radius = ceil(3 sqrt(lambda_max)) with
    lambda_max = mid + sqrt(max(0.1, mid^2 - det)); means2d = (fx X/Z + cx, fy Y/Z + cy);
    rgb = max(sh . basis(dir) + 0.5, 0) with dir = normalize(mu - camera centre). A Gaussian whose
    3DGS tile rectangle (as in `tile_lists`) is empty gets radius 0.

    Returns means2d, conics, colors, opacities, depths, radii for `reference_forward`.
    """
    means = np.asarray(means, np.float64).reshape(-1, 3)
    scales = np.asarray(scales, np.float64).reshape(-1, 3)
    quats = np.asarray(quats, np.float64).reshape(-1, 4)
    opacities = np.asarray(opacities, np.float64).reshape(-1)
    sh = np.asarray(sh, np.float64)
    n = means.shape[0]
    sh = sh.reshape(n, -1, 3)
    stored = int(round(math.sqrt(sh.shape[1]))) - 1
    degree = stored if sh_degree is None else min(int(sh_degree), stored)
    k = (degree + 1) ** 2
    width, height = int(camera.width), int(camera.height)
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    w2c = np.asarray(camera.world_to_camera, np.float64)
    Wr, t = w2c[:3, :3], w2c[:3, 3]
    centre = -Wr.T @ t
    lim_x = clamp * width / (2.0 * fx)
    lim_y = clamp * height / (2.0 * fy)
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE

    means2d = np.zeros((n, 2))
    conics = np.zeros((n, 3))
    depths = np.zeros(n)
    radii = np.zeros(n, np.int64)
    dirs = means - centre
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    basis = _reference_sh_basis(dirs, degree)
    colors = np.maximum(np.einsum("nk,nkc->nc", basis, sh[:, :k]) + 0.5, 0.0)
    for i in range(n):
        p = Wr @ means[i] + t
        z = p[2]
        depths[i] = z
        if z <= near:
            continue
        R = _reference_rotation(quats[i])
        S = np.diag(scales[i])
        sigma = R @ S @ S.T @ R.T
        tx = np.clip(p[0] / z, -lim_x, lim_x) * z
        ty = np.clip(p[1] / z, -lim_y, lim_y) * z
        J = np.array([[fx / z, 0.0, -fx * tx / (z * z)],
                      [0.0, fy / z, -fy * ty / (z * z)]])
        cov = J @ Wr @ sigma @ Wr.T @ J.T + dilation * np.eye(2)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] * cov[1, 0]
        if det <= 0:
            continue
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        r = int(math.ceil(3.0 * math.sqrt(lam)))
        u, v = fx * p[0] / z + cx, fy * p[1] / z + cy
        px, py = u - 0.5, v - 0.5
        x0 = min(ntx, max(0, math.floor((px - r) / TILE)))
        x1 = min(ntx, max(0, math.floor((px + r + TILE - 1) / TILE)))
        y0 = min(nty, max(0, math.floor((py - r) / TILE)))
        y1 = min(nty, max(0, math.floor((py + r + TILE - 1) / TILE)))
        if x1 <= x0 or y1 <= y0:
            continue
        inv = np.linalg.inv(cov)
        radii[i] = r
        means2d[i] = (u, v)
        conics[i] = (inv[0, 0], inv[0, 1], inv[1, 1])
    return means2d, conics, colors, opacities.copy(), depths, radii
