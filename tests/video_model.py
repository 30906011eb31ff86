"""A tiny exported model shared by the video, distribution and batch tests (issue 5).

`build_tiny_export(tmp_path_factory)` trains a `--preset test` run on a 32 px synthetic scene and exports
it, once per pytest session (the files live in the session's base temp folder, so every test
module that asks gets the same model). Needs torch and onnx: the tests that use it skip without.
"""

from __future__ import annotations

from pathlib import Path

import pytest


def build_tiny_export(tmp_path_factory) -> tuple[Path, Path]:
    """(model.onnx, scene folder): 2000 Gaussians, SH degree 1, default camera 32x32."""
    root = tmp_path_factory.getbasetemp() / "nehad-video-model"
    model, scene = root / "model.onnx", root / "scene"
    if model.is_file():
        return model, scene
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.export.onnx_export import export_run
    from nehad.trainer import Trainer

    root.mkdir(exist_ok=True)
    synthesize_scene(scene, resolution=32, frames=20, points=500, seed=0)
    Trainer(build_config("test", None, []), scene, root / "run", progress=False).train()
    export_run(root / "run", model)
    return model, scene


def build_moving_export(tmp_path_factory) -> tuple[Path, Path]:
    """(model.onnx, scene folder): the shared tiny model, whose 70 training steps hardly move
    anything (its renders at t = 0.2 and 0.8 differ by 50 dB), with its field's adapters and
    equilibrium times randomised (as tests/test_lod.py does) so that the Gaussians move."""
    torch = pytest.importorskip("torch")
    from nehad.checkpoint import atomic_torch_save, load_state
    from nehad.export.onnx_export import export_run

    onnx, scene = build_tiny_export(tmp_path_factory)
    moving = onnx.parent / "moving.onnx"
    if moving.is_file():
        return moving, scene
    state = load_state(onnx.parent / "run" / "model.pt")
    gen = torch.Generator().manual_seed(3)
    for name, p in state["field"].items():
        if name.startswith("adapters."):
            state["field"][name] = torch.randn(p.shape, generator=gen) * 0.3
    state["gaussians"]["t_eq"] = torch.rand(state["gaussians"]["t_eq"].shape, generator=gen)
    run = onnx.parent / "moving"
    run.mkdir(exist_ok=True)
    atomic_torch_save(state, run / "model.pt")
    export_run(run, moving)
    return moving, scene
