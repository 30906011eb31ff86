"""Static Gaussians written pre-deformed at export (nehad.export.static_split, issue 27)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from click.testing import CliRunner  # noqa: E402

from nehad.cli.main import main  # noqa: E402
from nehad.export.onnx_export import export_model, parity_error  # noqa: E402
from nehad.export.static_split import StaticBounds, find_static  # noqa: E402

OUTPUTS = ("means", "scales", "quats", "opacities", "sh")


@pytest.fixture(scope="module")
def half_still(tmp_path_factory):
    """A trained test-preset run with the 4DGS decoder whose heads are random (a clear motion)
    and whose xy spatial planes are zero where x < 0: there the hex-plane features are 0 at every
    time, so those Gaussians keep one constant offset (static); the others move."""
    from nehad.checkpoint import atomic_torch_save, load_state
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.model import load_run
    from nehad.trainer import Trainer

    root = tmp_path_factory.mktemp("static")
    data = root / "scene"
    synthesize_scene(data, resolution=24, frames=8, points=300, seed=0)
    run = root / "run"
    Trainer(build_config("test", None, ["field.decoder=mlp", "coarse.iterations=10",
                                        "fine.iterations=6"]), data, run, progress=False).train()
    state = load_state(run / "model.pt")
    g = torch.Generator().manual_seed(3)
    for name, p in state["field"].items():
        if name.startswith("heads.") and ".3." in name:
            state["field"][name] = torch.randn(p.shape, generator=g) * 0.1
        elif name.startswith("hexplane.") and p.is_floating_point():
            p = p + torch.randn(p.shape, generator=g) * 0.5
            if name.endswith(".0"):  # the xy plane (1, C, res_y, res_x): zero for x < 0
                p[..., : p.shape[-1] // 2 - 1] = 0.0
            state["field"][name] = p
    atomic_torch_save(state, run / "model.pt")
    model, meta = load_run(run)
    return run, model, meta


def _outputs(path, t):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(None, {"time": np.array([t], np.float32)})


def test_static_gaussians_are_found_and_frozen(half_still, tmp_path):
    run, model, meta = half_still
    split = find_static(model, 1)
    x = model.gaussians.means.detach().numpy()[:, 0]
    box = model.field.aabb.numpy()
    xn = 2 * (x - box[0, 0]) / (box[1, 0] - box[0, 0]) - 1  # normalised as the planes see it
    assert 0 < split.num_static < len(x)
    assert split.mask[xn < -0.45].all()  # inside the zeroed columns (the 3rd sits at -0.43)
    assert not split.mask[xn > 0.3].any()  # the other half moves under random heads
    # the frozen rows hold at times the grid did not sample, within the bounds
    for t in (0.013, 0.377, 0.981):
        with torch.no_grad():
            out = [o.numpy() for o in model.gaussians_at(torch.tensor([t]))]
        moved = np.abs(out[0][split.mask] - split.frozen[0]).max() / float(model.field.extent)
        assert moved <= StaticBounds().position


def test_split_export_matches_the_unsplit_one(half_still, tmp_path):
    run, model, meta = half_still
    whole = export_model(model, meta, tmp_path / "whole.onnx", static=False)
    split = export_model(model, meta, tmp_path / "split.onnx")
    assert whole.num_static == 0 and "static_gaussians" not in whole.metadata
    assert 0 < split.num_static < split.num_gaussians
    assert split.metadata["static_gaussians"] == str(split.num_static)
    assert max(split.parity.values()) <= 1e-5  # against the model with those rows frozen
    for t in (0.0, 0.31, 0.5, 0.9, 1.0):
        a, b = _outputs(tmp_path / "whole.onnx", t), _outputs(tmp_path / "split.onnx", t)
        for name, u, v in zip(OUTPUTS, a, b):
            assert u.shape == v.shape
            assert parity_error(v, u) <= 2e-2, (name, t)  # the frozen rows, within the bounds
    # the renders: well above the 45 dB the issue allows
    from nehad.runtime.render import render_view
    from nehad.runtime.scene import open_scene

    whole_m, split_m = open_scene(tmp_path / "whole.onnx"), open_scene(tmp_path / "split.onnx")
    cam = whole_m.default_camera
    for t in (0.0, 0.6):
        ra = render_view(whole_m, cam, t, adapt_threads=False).image
        rb = render_view(split_m, cam, t, adapt_threads=False).image
        mse = float(np.mean((ra.astype(np.float64) - rb) ** 2))
        assert mse == 0 or -10 * np.log10(mse) >= 45.0
    res = CliRunner().invoke(main, ["info", str(tmp_path / "split.onnx")])
    assert res.exit_code == 0 and f"static:       {split.num_static} of" in res.output


def test_split_export_in_parts_matches_the_split_one(half_still, tmp_path):
    """Parts with static and moving rows (each part puts its own rows back in the model's order)
    and parts without static rows give the outputs of the split file without parts; the
    runtime's parts side by side give them too."""
    import json

    from nehad.runtime.onnx_model import OnnxModel

    run, model, meta = half_still
    one = export_model(model, meta, tmp_path / "one.onnx", parts=1)
    three = export_model(model, meta, tmp_path / "three.onnx", parts=3, min_part_rows=1)
    assert three.num_static == one.num_static > 0
    bounds = json.loads(three.metadata["parts"])
    still = find_static(model, 1).mask
    assert len(bounds) == 4
    held = [int(still[a:b].sum()) for a, b in zip(bounds[:-1], bounds[1:])]
    assert any(0 < k < b - a for k, a, b in zip(held, bounds[:-1], bounds[1:])), held
    assert 0 in held, held  # and a part with none
    side = OnnxModel(tmp_path / "three.onnx", threads=2, cache_size=0)
    assert side.workers == 2
    for t in (0.0, 0.45, 1.0):
        a = dict(zip(OUTPUTS, _outputs(tmp_path / "one.onnx", t)))
        b = dict(zip(OUTPUTS, _outputs(tmp_path / "three.onnx", t)))
        c = side.outputs(t)
        for name in OUTPUTS:
            np.testing.assert_allclose(b[name], a[name], rtol=1e-6, atol=1e-6)
            np.testing.assert_array_equal(c[name], b[name])


def test_nothing_static_means_no_split(tmp_path, half_still):
    run, model, meta = half_still
    with torch.no_grad():  # every Gaussian gets a finite life: opacity changes with time
        model.gaussians.life_rate.fill_(3.0)
    try:
        rep = export_model(model, meta, tmp_path / "m.onnx")
    finally:
        with torch.no_grad():
            model.gaussians.life_rate.zero_()
    assert rep.num_static == 0 and "static_gaussians" not in rep.metadata
