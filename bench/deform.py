"""Deformation time per call: onnxruntime on the exported graph vs. the torch model's own forward.

For 10k, 100k and 1M Gaussians with the D-NeRF field (hex-plane 64^3 x 25, multires (1, 2),
W = 64, HNN decoder with randomised adapters so the deformation is not the identity): export
with `nehad.export.onnx_export.export_model` (its docs/design.md section 7 parity check against the torch model
included, at t = 0 and 1), then time, back to back at each thread count of --threads:
  torch:       NeHaDModel.gaussians_at(t) under torch.no_grad (the HNN gradient by autograd,
               create_graph=False), torch.set_num_threads(threads)
  onnxruntime: session.run for `time` (CPU provider, default optimisation level), intra-op
               threads = threads
Median of --repeats calls at random times after a warm-up. `load s` is the onnxruntime session
creation (it folds the time-independent part of the graph once). Target: onnxruntime <= 0.5x
torch at 100k.

The Gaussians are built directly (random means, rotations, SH, equilibrium parameters), not with
`GaussianParameters.random_in_box`, whose nearest-neighbour scale initialisation takes minutes
at 200k and did not finish at 1M.

    python bench/deform.py [--sizes 10000,100000,1000000] [--threads 1,2] [--repeats 7]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def build_model(n: int, seed: int = 0, **field_options):
    import torch

    from nehad.field.config import FieldConfig
    from nehad.field.deformation import DeformationField
    from nehad.gaussians import GaussianParameters
    from nehad.model import NeHaDModel

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1.3, 1.3, (n, 3)).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    gaussians = GaussianParameters(
        means, np.full((n, 3), np.log(0.01), np.float32), quats,
        rng.normal(size=n).astype(np.float32), rng.normal(0, 0.5, (n, 1, 3)).astype(np.float32),
        rng.normal(0, 0.1, (n, 15, 3)).astype(np.float32),
        mu_eq=means + rng.normal(0, 0.05, (n, 3)).astype(np.float32),
        t_eq=rng.uniform(0, 1, (n, 1)).astype(np.float32))
    aabb = torch.tensor([[-1.3] * 3, [1.3] * 3])
    field = DeformationField(FieldConfig(**field_options), aabb, extent=2.6)
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
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()

    import onnxruntime as ort
    import torch

    from nehad.export.onnx_export import export_model
    from nehad.model import RunInfo

    times = np.random.default_rng(0).uniform(0, 1, 64)
    print(f"onnxruntime {ort.__version__}, torch {torch.__version__}")
    print(f"{'gaussians':>9} {'threads':>7} {'torch ms':>9} {'onnxrt ms':>9} {'ratio':>6} "
          f"{'file MB':>8} {'export s':>8} {'load s':>6} {'parity':>8}")
    for n in (int(s) for s in args.sizes.split(",")):
        model = build_model(n)
        meta = RunInfo(sh_degree=3, time_range=(0.0, 1.0), background=(1.0, 1.0, 1.0))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "model.onnx"
            t0 = time.perf_counter()
            report = export_model(model, meta, path, times=(0.0, 1.0))
            export_s = time.perf_counter() - t0
            size_mb = path.stat().st_size / 1e6
            for threads in (int(s) for s in args.threads.split(",")):
                torch.set_num_threads(threads)
                opts = ort.SessionOptions()
                opts.intra_op_num_threads = threads
                opts.inter_op_num_threads = 1
                t0 = time.perf_counter()
                sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
                load_s = time.perf_counter() - t0

                def run_ort(t):
                    sess.run(None, {"time": np.array([t], np.float32)})

                def run_torch(t):
                    with torch.no_grad():
                        model.gaussians_at(t)

                # onnxruntime first: torch's OpenMP workers keep spinning for a while after a
                # call and, on a 2-core machine, slowed a following onnxruntime run at 2 threads
                # from 91 to 131 ms at 100k (onnxruntime's own workers spin less long).
                t_ort = median_ms(run_ort, times, args.repeats)
                t_torch = median_ms(run_torch, times, args.repeats)
                print(f"{n:>9} {threads:>7} {t_torch:>9.1f} {t_ort:>9.1f} "
                      f"{t_ort / t_torch:>6.2f} {size_mb:>8.1f} {export_s:>8.1f} {load_s:>6.1f} "
                      f"{max(report.parity.values()):>8.1e}", flush=True)
                sess = None
        model = None


if __name__ == "__main__":
    main()
