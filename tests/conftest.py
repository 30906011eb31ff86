"""Fixtures shared by the test modules (pytest finds them here).

- `tiny_run`: a tiny trained run (`nehad synth` at 32 px with 8 frames, `test` preset with the
  paper's BED masks on, seconds),
  session-scoped, so it is trained once per pytest run; `tiny_run_model` its loaded (model, meta);
  `tiny_onnx` its export.

The exported model of the video, batch and distribution tests is built by
`video_model.build_tiny_export` (a plain function: some tests call it inside helpers).
"""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """(dataset folder, run folder) of a finished tiny training run."""
    pytest.importorskip("torch")
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.trainer import Trainer

    root = tmp_path_factory.mktemp("viz")
    data = synthesize_scene(root / "data", resolution=32, frames=8, seed=0)
    run = root / "run"
    # the paper's BED masks on (off in the recipe): `viz masks` and its tests read them
    cfg = build_config("test", overrides=["field.bed_position=true", "field.bed_scale=true"])
    Trainer(cfg, data, run, progress=False).train()
    return data, run


@pytest.fixture(scope="session")
def tiny_run_model(tiny_run):
    """(model, meta) of the tiny run, loaded once."""
    from nehad.model import load_run

    return load_run(tiny_run[1])


@pytest.fixture(scope="session")
def tiny_onnx(tiny_run, tmp_path_factory):
    """The tiny run exported to .onnx (needs onnx)."""
    pytest.importorskip("onnx")
    from nehad.export.onnx_export import export_run

    out = tmp_path_factory.mktemp("viz_onnx") / "model.onnx"
    export_run(tiny_run[1], out)
    return out
