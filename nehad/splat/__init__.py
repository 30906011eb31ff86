"""Torch side of Gaussian splatting: projection and SH in torch (for autograd) and the autograd
wrapper around the shared Numba rasterizer kernels of `nehad.runtime.raster` (docs/design.md section 6)."""
