"""Deformation time per call: onnxruntime on the exported graph vs. the torch model's own forward.

For 10k, 100k and 1M Gaussians with the D-NeRF field (hex-plane 64^3 x 25, multires (1, 2),
W = 64, HNN decoder with randomised adapters so the deformation is not the identity): export
with `nehad.export.onnx_export.export_model`, then time
  torch:       NeHaDModel.gaussians_at(t) under torch.no_grad (the HNN gradient by autograd,
               create_graph=False), torch on --threads threads
  onnxruntime: OnnxModel session.run for `time` (no cache), intra-op threads = --threads
Median of --repeats calls at random times after a warm-up. Target: onnxruntime <= 0.5x torch at
100k.

    python bench/deform.py [--sizes 10000,100000,1000000] [--threads 2] [--repeats 7]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def build_model(n: int, seed: int = 0):
    import torch

    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.trainer import NeHaDModel

    torch.manual_seed(seed)
    gaussians = GaussianParameters.random_in_box(n, sh_degree=3, seed=seed)
    with torch.no_grad():
        gaussians.log_scales.fill_(np.log(0.01))
        gaussians.t_eq.uniform_(0.0, 1.0)
    aabb = torch.tensor([[-1.3] * 3, [1.3] * 3])
    field = DeformationField(FieldConfig(), aabb, extent=2.6)
    g = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for name, p in field.named_parameters():
            if name.startswith("adapters."):
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    return NeHaDModel(gaussians, field).eval()


def median_ms(fn, times, repeats: int) -> float:
    fn(0.5)
    out = []
    for i in range(repeats):
        t0 = time.perf_counter()
        fn(float(times[i % len(times)]))
        out.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    import onnxruntime as ort
    import torch

    from nehad.export.onnx_export import export_model

    torch.set_num_threads(args.threads)
    times = np.random.default_rng(0).uniform(0, 1, 64)
    print(f"threads: torch {torch.get_num_threads()}, onnxruntime intra-op {args.threads}")
    print(f"{'gaussians':>9} {'torch ms':>9} {'onnxrt ms':>9} {'ratio':>6} {'file MB':>8} "
          f"{'export s':>8}")
    for n in (int(s) for s in args.sizes.split(",")):
        model = build_model(n)
        meta = {"sh_degree": 3, "time_range": (0.0, 1.0), "background": (1.0, 1.0, 1.0)}
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.onnx"
            t0 = time.perf_counter()
            export_model(model, meta, path, times=(0.0, 1.0))
            export_s = time.perf_counter() - t0
            size_mb = path.stat().st_size / 1e6
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = args.threads
            opts.inter_op_num_threads = 1
            sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

            def run_ort(t):
                sess.run(None, {"time": np.array([t], np.float32)})

            def run_torch(t):
                with torch.no_grad():
                    model.gaussians_at(t)

            t_torch = median_ms(run_torch, times, args.repeats)
            t_ort = median_ms(run_ort, times, args.repeats)
        print(f"{n:>9} {t_torch:>9.1f} {t_ort:>9.1f} {t_ort / t_torch:>6.2f} {size_mb:>8.1f} "
              f"{export_s:>8.1f}", flush=True)
        del model, sess


if __name__ == "__main__":
    main()
