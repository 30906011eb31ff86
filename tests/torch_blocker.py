"""A subprocess environment in which `import torch` fails: the runtime and the CLI's rendering
paths must work there (docs/design.md section 2)."""

from __future__ import annotations

import os
from pathlib import Path


def blocked_torch_env(tmp_path: Path) -> dict:
    """Environment whose PYTHONPATH starts with a fake `torch` package that raises ImportError."""
    block = Path(tmp_path) / "no_torch"
    (block / "torch").mkdir(parents=True, exist_ok=True)
    (block / "torch" / "__init__.py").write_text(
        "raise ImportError('torch is blocked in this test: this path must not need it')\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(block)] + [p for p in [env.get("PYTHONPATH")] if p])
    return env
