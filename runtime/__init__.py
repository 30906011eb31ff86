"""Torch-free runtime: cameras, image and PLY I/O, the shared CPU rasterizer (docs/design.md section 2).

Nothing below this package may import torch.
"""
