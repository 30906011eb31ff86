"""Detect graph capture (ONNX export, torch.jit tracing, torch.compile/dynamo export), where the
field must take its export-friendly paths: closed-form HNN gradients (docs/design.md section 4.4, 7) and a single
grid_sample batch."""

from __future__ import annotations

import torch


def is_capturing() -> bool:
    """True while torch.onnx.export, torch.jit.trace or torch.compile/export captures a graph."""
    if torch.jit.is_tracing():
        return True
    if getattr(torch.onnx, "is_in_onnx_export", lambda: False)():
        return True
    compiler = getattr(torch, "compiler", None)
    return bool(getattr(compiler, "is_compiling", lambda: False)())


__all__ = ["is_capturing"]
