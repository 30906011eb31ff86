"""nehad: Neural Hamiltonian Deformation Fields for dynamic Gaussian splatting.

Importing this package must not import torch (docs/design.md section 2): the runtime
(`nehad.runtime`) and the CLI (`nehad.cli`) work without it. Training code lives
in submodules that import torch themselves.
"""

__version__ = "0.1.0"
