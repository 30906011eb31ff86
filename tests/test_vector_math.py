"""MKL's vector math is set up by a serial call before torch can run it in parallel
(nehad.vector_math; bench/mkl_first_call.py measures why: 10 of 100 fresh processes got a wrong
half from their first parallel `torch.exp`, 0 of 100 after the serial call)."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("torch")


@pytest.mark.parametrize("module", ["nehad.gaussians", "nehad.model", "nehad.trainer",
                                    "nehad.export.onnx_export"])
def test_torch_entry_points_set_up_mkl_before_computing(module):
    code = (f"import sys, {module}\n"
            "assert 'nehad.vector_math' in sys.modules, 'nehad.vector_math was not imported'\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-1500:]

