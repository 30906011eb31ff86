"""Compute floors for the training step and the frame (issue 27, item 4), as bench/raster.py has
the rasterizer's: the work a part cannot avoid, at the best rate this machine does that work.

- **Field**: its multiply-adds at the machine's measured float32 matrix-multiply rate (torch,
  the threads in use, at the decoder's shape: N x 64 by 64 x 64). The dense layers (trunk, HNN,
  its closed-form gradient, adapters) are counted by torch's FlopCounterMode while the field runs
  (forward, and forward + backward); the hex-plane lookup, which that counter does not see (it
  runs in a Numba kernel or in grid_sample), adds 4 bilinear taps x its feature width per plane,
  scale and Gaussian forward, three times that backward (the features' and the coordinates'
  gradients). Element-wise work (activations, BED masks, Verlet, quaternions) is not counted: a
  floor, not an estimate.
- **Loss** (L1 + D-SSIM): per pixel and channel, the SSIM's separable 11-tap Gaussian window on
  five maps (two passes each) forward, twice that backward, plus the L1 and the SSIM formula, at
  the same rate (a floor: a stencil runs slower than a matrix multiply).

- **Deformation of an exported model** (bench/render.py): the multiply-adds of its graph's
  Gemm/MatMul nodes per Gaussian (weights of shape K x N: K N each; counted from the ONNX file)
  and of its GridSample nodes (4 taps x the plane's channels), times the Gaussians that go
  through the field (all but the export's static ones), at onnxruntime's float32 matmul rate
  with the threads the model runs with.
- **Rasterization** (bench/render.py): the frame's contributing pairs at the forward inner
  loop's rate (bench/raster.py, as its own floor).

Used by bench/train_step.py and bench/render.py; run alone to print the rate.
"""

from __future__ import annotations

import json
import time

import numpy as np

#: D-SSIM per pixel and channel: 5 maps (mu_x, mu_y, x^2, y^2, xy) x 2 separable passes x 11
#: taps forward; the backward twice that; plus ~10 for the SSIM formula and the L1.
LOSS_MACS_FORWARD = 5 * 2 * 11 + 10
LOSS_MACS_BACKWARD = 2 * 5 * 2 * 11 + 10


def _seconds_per_call(fn, repeats: int) -> float:
    """Median over `repeats` batches of 10 calls of `fn`, after one call to warm up."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(10):
            fn()
        times.append((time.perf_counter() - t0) / 10)
    return float(np.median(times))


def matmul_rate(rows: int = 10000, width: int = 64, repeats: int = 30) -> float:
    """Multiply-adds per second of torch's float32 (rows x width) @ (width x width), the
    median of `repeats` after a warm-up, with torch's current threads."""
    import torch

    a = torch.randn(rows, width)
    b = torch.randn(width, width)
    return rows * width * width / _seconds_per_call(lambda: torch.mm(a, b), repeats)


def hexplane_macs(field_cfg, n: int) -> int:
    """Forward multiply-adds of the hex-plane lookup of `n` Gaussians (6 planes, each scale)."""
    return int(n * 6 * len(field_cfg.multires) * field_cfg.out_dim * 4)


def _in_place_products() -> dict:
    """FlopCounterMode formulas for the in-place products addmm_ and baddbmm_ (the fused
    decoder accumulates its weight gradients with them), which torch's counter leaves out: 2 m k
    n flops each, as for addmm and baddbmm. Before 2026-11-28 the field's floor missed them
    (1.069 G multiply-adds for 10k Gaussians where 1.438 G are done)."""
    import torch

    aten = torch.ops.aten

    def addmm_(target, a, b, *args, out_val=None, **kwargs):
        return 2 * a.shape[0] * a.shape[1] * b.shape[1]

    def baddbmm_(target, a, b, *args, out_val=None, **kwargs):
        return 2 * a.shape[0] * a.shape[1] * a.shape[2] * b.shape[2]

    for f in (addmm_, baddbmm_):
        f._get_raw = True  # called with the tensors, not their shapes
    return {aten.addmm_: addmm_, aten.baddbmm_: baddbmm_}


def field_macs(model, t: float) -> tuple[int, int]:
    """(forward, forward + backward) multiply-adds of the deformation of every Gaussian of
    `model` (a NeHaDModel) at time `t` (module doc)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    n = len(model.gaussians)
    mapping = _in_place_products()
    with torch.no_grad(), FlopCounterMode(display=False, custom_mapping=mapping) as fwd:
        model.gaussians_at(t, deform=True)
    with FlopCounterMode(display=False, custom_mapping=mapping) as both:
        params = model.gaussians_at(t, deform=True)
        sum(p.sum() for p in params).backward()
    if hasattr(model, "zero_grad"):  # the counting pass leaves no gradient behind
        model.zero_grad(set_to_none=True)
    grid = hexplane_macs(model.field.cfg, n)
    return (fwd.get_total_flops() // 2 + grid, both.get_total_flops() // 2 + 4 * grid)


def loss_macs(width: int, height: int, channels: int = 3) -> tuple[int, int]:
    """(forward, forward + backward) multiply-adds of the photometric loss of one image."""
    px = width * height * channels
    return px * LOSS_MACS_FORWARD, px * (LOSS_MACS_FORWARD + LOSS_MACS_BACKWARD)


if __name__ == "__main__":
    import torch

    print(f"torch {torch.get_num_threads()} threads: float32 matmul "
          f"{matmul_rate() / 1e9:.1f} G multiply-adds/s")


def onnx_matmul_rate(threads: int | None = None, rows: int = 10000, width: int = 64,
                     repeats: int = 30) -> float:
    """Multiply-adds per second of onnxruntime's float32 (rows x width) @ (width x width) (a
    one-node graph; `threads`: intra-op threads, None = onnxruntime's default)."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    w = np.random.default_rng(1).standard_normal((width, width)).astype(np.float32)
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "w"], ["y"])], "mm",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, width])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [rows, width])],
        [numpy_helper.from_array(w, "w")])
    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    session = ort.InferenceSession(model.SerializeToString(), opts,
                                   providers=["CPUExecutionProvider"])
    x = {"x": np.random.default_rng(0).standard_normal((rows, width)).astype(np.float32)}
    return rows * width * width / _seconds_per_call(lambda: session.run(None, x), repeats)


def onnx_field_macs(path) -> tuple[int, int]:
    """(multiply-adds per Gaussian through the field, Gaussians through it) of an exported
    model (module doc)."""
    import onnx

    model = onnx.load(str(path))
    inits = {i.name: list(i.dims) for i in model.graph.initializer}
    made_by = {o: node for node in model.graph.node for o in node.output}
    per_row = 0
    for node in model.graph.node:
        if node.op_type in ("Gemm", "MatMul"):
            name = node.input[1]
            if name not in inits and name in made_by and made_by[name].op_type == "Transpose":
                name = made_by[name].input[0]
            if len(inits.get(name, [])) == 2:
                per_row += inits[name][0] * inits[name][1]
        elif node.op_type == "GridSample" and len(inits.get(node.input[0], [])) == 4:
            per_row += 4 * inits[node.input[0]][1]
    meta = {p.key: p.value for p in model.metadata_props}
    rows = int(meta.get("num_gaussians", 0)) - int(meta.get("static_gaussians", 0))
    parts = len(json.loads(meta.get("parts", "[0, 0]"))) - 1  # each part's nodes: its rows
    return per_row // parts, rows
