"""Run directories and checkpoints (SPEC section 5): state dicts only, written atomically, loaded
with `weights_only=True`.

    RUN/config.yaml        the resolved config
    RUN/checkpoints/step_000500.pt
    RUN/model.pt           the final model (gaussians + field + what rendering needs)
    RUN/metrics.jsonl      one JSON object per log line
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import torch


def atomic_torch_save(obj, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def load_state(path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def checkpoint_dir(run: Path) -> Path:
    return Path(run) / "checkpoints"


def list_checkpoints(run: Path) -> list[Path]:
    d = checkpoint_dir(run)
    return sorted(d.glob("step_*.pt")) if d.is_dir() else []


def save_checkpoint(run: Path, step: int, state: dict, keep: int) -> Path:
    path = atomic_torch_save(state, checkpoint_dir(run) / f"step_{step:07d}.pt")
    for old in list_checkpoints(run)[:-max(keep, 1)]:
        old.unlink(missing_ok=True)
    return path


def append_metrics(run: Path, record: dict) -> None:
    with open(Path(run) / "metrics.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")
