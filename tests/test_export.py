"""`nehad export`: the nehad-onnx/1 file of docs/design.md section 7 (operators, checker, metadata, parity with the
torch model and with torch-side renders, fp16 weights, bad inputs)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from click.testing import CliRunner  # noqa: E402

from nehad.cli.main import main  # noqa: E402
from nehad.export.checks import ALLOWED_OPS, check_graph, opset_of, operator_counts  # noqa: E402
from nehad.export.onnx_export import (ExportError, export_model, export_run,  # noqa: E402
                                      parity_error)

OUTPUTS = ("means", "scales", "quats", "opacities", "sh")
TIMES = (0.0, 0.13, 0.5, 0.77, 1.0)


def make_run(root, decoder: str, seed: int = 0, extra=()):
    """A tiny trained run (test preset) whose deformation is made clearly non-trivial: the
    adapters / last head layers get random weights (a fresh field is the identity), the
    equilibrium parameters are spread out. Returns (run dir, data dir)."""
    from nehad.checkpoint import atomic_torch_save, load_state
    from nehad.config import build_config
    from nehad.data.synth import synthesize_scene
    from nehad.trainer import Trainer

    data = root / "scene"
    if not data.exists():
        synthesize_scene(data, resolution=24, frames=8, points=300, seed=seed)
    run = root / (f"run_{decoder}" + "".join(f"_{x.split('=')[-1]}" for x in extra))
    # short stages; the HNN run ends at SH degree 0 of the stored 1 (the export truncates)
    sets = [f"field.decoder={decoder}", "coarse.iterations=10", "fine.iterations=6",

            f"train.sh_degree_interval={100 if decoder == 'hnn' else 5}", *extra]
    Trainer(build_config("test", None, sets), data, run, progress=False).train()
    state = load_state(run / "model.pt")
    g = torch.Generator().manual_seed(seed + 7)
    for name, p in state["field"].items():
        if name.startswith("adapters.") or (name.startswith("heads.") and ".3." in name):
            # 0.1: the softplus trunk's features are all positive, and 0.3 gave 1e5-wide
            # Gaussians, whose renders differ in float32 rounding alone
            state["field"][name] = torch.randn(p.shape, generator=g) * 0.1
        elif name.startswith("hexplane.") and p.is_floating_point():
            state["field"][name] = p + torch.randn(p.shape, generator=g) * 0.5
    gs = state["gaussians"]
    gs["t_eq"] = torch.rand(gs["t_eq"].shape, generator=g)
    gs["mu_eq"] = gs["mu_eq"] + torch.randn(gs["mu_eq"].shape, generator=g) * 0.2
    atomic_torch_save(state, run / "model.pt")
    return run, data


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    return {d: make_run(root, d)[0] for d in ("hnn", "mlp")}


def ops_after_constant_folding(path, out):
    """Operator counts of the graph onnxruntime runs after its constant folding (what is
    evaluated in every call)."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    opts.optimized_model_filepath = str(out)
    ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    return operator_counts(onnx.load(str(out)))


def torch_reference(run, t):
    from nehad.model import load_run

    model, meta = load_run(run)
    k = (meta.sh_degree + 1) ** 2
    with torch.no_grad():
        out = [o.numpy() for o in model.gaussians_at(t)]
    out[4] = out[4][:, :k]
    return out


@pytest.mark.parametrize("decoder", ["hnn", "mlp"])
def test_export_parity_operators_metadata(runs, tmp_path, decoder):
    run = runs[decoder]
    path = tmp_path / "model.onnx"
    res = CliRunner().invoke(main, ["export", str(run), "-o", str(path)])
    assert res.exit_code == 0, res.output
    proto = onnx.load(str(path))
    onnx.checker.check_model(proto, full_check=True)
    ops = operator_counts(proto)
    print(f"{decoder}: {path.stat().st_size} bytes, operators {dict(sorted(ops.items()))}")
    assert set(ops) <= ALLOWED_OPS, set(ops) - ALLOWED_OPS
    assert all(n.domain in ("", "ai.onnx") for n in proto.graph.node)
    assert [imp.domain for imp in proto.opset_import] in ([""], ["ai.onnx"])
    assert opset_of(proto) >= 17
    # the plane lookups run in every call are Gathers (onnxruntime's CPU GridSample was 75% of the
    # deformation time); GridSample only samples the spatial planes at the canonical means, a
    # constant subgraph that onnxruntime folds when the session is created
    folded = ops_after_constant_folding(path, tmp_path / "folded.onnx")
    assert "Gather" in folded and "GridSample" not in folded
    assert sum(folded.values()) < 0.5 * sum(ops.values())
    assert "Atan2" not in ops and "Gradient" not in ops
    if decoder == "hnn":
        assert {"Atan", "Tanh", "Where"} <= set(ops)
        # softplus written as relu(z) + log1p(exp(-|z|)) with the log1p from Exp, Mul and Add:
        # onnxruntime's Softplus kernel was more than half of the deformation time, its Log 14x
        # its Exp (nehad/field/hnn.py)
        assert "Softplus" not in ops and "Log" not in ops and {"Relu", "Exp"} <= set(ops)
    check_graph(proto)
    assert [i.name for i in proto.graph.input] == ["time"]
    assert [o.name for o in proto.graph.output] == list(OUTPUTS)
    md = {p.key: p.value for p in proto.metadata_props}
    assert md["format"] == "nehad-onnx/1"
    assert md["sh_degree"] == ("0" if decoder == "hnn" else "1")
    assert json.loads(md["time_range"]) == [0.0, 1.0]
    assert len(json.loads(md["background"])) == 3 and len(json.loads(md["aabb"])) == 2
    assert json.loads(md["default_camera"])["width"] == 24
    assert len(md["config_hash"]) == 16 and md["nehad_version"]

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = {n: 0.0 for n in OUTPUTS}
    for t in TIMES:
        got = sess.run(None, {"time": np.array([t], np.float32)})
        ref = torch_reference(run, t)
        assert int(md["num_gaussians"]) == len(ref[0])
        for n, a, b in zip(OUTPUTS, got, ref):
            assert a.shape == b.shape and a.dtype == np.float32, n
            worst[n] = max(worst[n], parity_error(a, b))
    print(f"{decoder}: parity vs torch gaussians_at {worst}")
    assert max(worst.values()) <= 1e-5
    # the deformation is not trivially the identity (randomised adapters)
    m0 = sess.run(["means"], {"time": np.array([0.0], np.float32)})[0]
    m1 = sess.run(["means"], {"time": np.array([1.0], np.float32)})[0]
    print(f"{decoder}: max |means(0) - means(1)| = {np.abs(m0 - m1).max():.3g}")
    assert np.abs(m0 - m1).max() > 1e-2


@pytest.mark.parametrize("decoder", ["hnn", "mlp"])
def test_render_from_onnx_matches_run_render(runs, tmp_path, decoder):
    from nehad.runtime.images import read_image

    run = runs[decoder]
    path = tmp_path / "m.onnx"
    export_run(run, path)
    cam = f"{run.parent / 'scene' / 'transforms_test.json'}:0"
    runner = CliRunner()
    for t in (0.0, 0.6, 1.0):
        a, b = tmp_path / f"run_{t}.exr", tmp_path / f"onnx_{t}.exr"
        for src, out in ((run, a), (path, b)):
            res = runner.invoke(main, ["render", str(src), "--view", cam, "--time", str(t),
                                       "--size", "64x64", "-o", str(out)])
            assert res.exit_code == 0, res.output
        x, y = read_image(a), read_image(b)
        mse = float(np.mean((x.astype(np.float64) - y) ** 2))
        psnr = 10 * np.log10(1.0 / max(mse, 1e-30))
        print(f"{decoder} t={t}: ONNX vs torch render PSNR {psnr:.1f} dB")
        assert psnr > 60.0
        assert 0.02 < float(np.mean(np.abs(x - 1.0))) or x.std() > 0.01  # something is drawn


def exported_with_parity(run, path):
    """`nehad export RUN -o PATH`, its session, after every output at every test time is held
    to torch's gaussians_at within 1e-5."""
    res = CliRunner().invoke(main, ["export", str(run), "-o", str(path)])
    assert res.exit_code == 0, res.output
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for t in TIMES:
        got = sess.run(None, {"time": np.array([t], np.float32)})
        for a, b in zip(got, torch_reference(run, t)):
            worst = max(worst, parity_error(a, b))
    assert worst <= 1e-5
    return sess


def test_bed_deformed_reading_exports_with_parity(tmp_path):
    """field.bed_distance=deformed (M_pos from the integrated position, docs/design.md section
    4.7): the exported graph computes the same Gaussians as torch, and the reading changes them."""
    from nehad.checkpoint import atomic_torch_save, load_state

    run, _ = make_run(tmp_path, "hnn",
                      extra=("field.bed_position=true", "field.bed_distance=deformed"))
    sess = exported_with_parity(run, tmp_path / "model.onnx")
    # the same weights read the other way place the Gaussians elsewhere
    state = load_state(run / "model.pt")
    state["config"]["field"]["bed_distance"] = "canonical"
    atomic_torch_save(state, run / "model.pt")
    other = torch_reference(run, 0.13)[0]
    assert np.abs(got_means_at(sess, 0.13) - other).max() > 1e-3


def test_bed_floor_on_the_deformation_exports_with_parity(tmp_path):
    """field.bed_floor=deformation (docs/design.md section 4.7): the exported graph floors the
    blend weight as torch does, and the reading changes the Gaussians."""
    from nehad.checkpoint import atomic_torch_save, load_state

    run, _ = make_run(tmp_path, "hnn", extra=("field.bed_position=true", "field.bed_scale=true",
                                            "field.bed_floor=deformation"))
    sess = exported_with_parity(run, tmp_path / "model.onnx")
    state = load_state(run / "model.pt")
    state["config"]["field"]["bed_floor"] = "mask"
    atomic_torch_save(state, run / "model.pt")
    assert np.abs(got_means_at(sess, 0.13) - torch_reference(run, 0.13)[0]).max() > 1e-4


def test_quadratic_hamiltonian_exports_with_parity(tmp_path):
    """field.hnn_quadratic (docs/design.md section 4.3): the exported graph adds the quadratic
    terms' gradients, and they matter (zeroing them moves the Gaussians)."""
    from nehad.checkpoint import atomic_torch_save, load_state

    run, _ = make_run(tmp_path, "hnn", extra=("field.hnn_quadratic=true",))
    state = load_state(run / "model.pt")
    g = torch.Generator().manual_seed(11)
    for name in ("field.quad1", "field.quad2"):
        state["field"][name] = torch.randn(state["field"][name].shape, generator=g) * 0.05
    atomic_torch_save(state, run / "model.pt")
    sess = exported_with_parity(run, tmp_path / "model.onnx")
    for name in ("field.quad1", "field.quad2"):
        state["field"][name] = torch.zeros_like(state["field"][name])
    atomic_torch_save(state, run / "model.pt")
    assert np.abs(got_means_at(sess, 0.13) - torch_reference(run, 0.13)[0]).max() > 1e-3


def got_means_at(sess, t):
    return sess.run(["means"], {"time": np.array([t], np.float32)})[0]


def test_fp16_weights_smaller_and_exact_vs_rounded_model(runs, tmp_path):
    full, half = tmp_path / "full.onnx", tmp_path / "half.onnx"
    r32 = export_run(runs["hnn"], full)
    r16 = export_run(runs["hnn"], half, fp16_weights=True)
    print(f"fp32 {r32.file_size} B in {r32.seconds:.2f} s; fp16 {r16.file_size} B; "
          f"fp16 vs unrounded model {r16.parity_vs_fp32}")
    # constant-folded float32 intermediates (not exact in fp16) stay float32 in this tiny model
    assert r16.file_size < 0.9 * r32.file_size
    assert max(r16.parity.values()) <= 1e-5  # vs the fp16-rounded torch model
    assert max(r16.parity_vs_fp32.values()) < 1e-2
    proto = onnx.load(str(half))
    check_graph(proto)
    assert any(i.data_type == onnx.TensorProto.FLOAT16 for i in proto.graph.initializer)
    assert {p.key: p.value for p in proto.metadata_props}["fp16_weights"] == "1"


def test_export_refuses_and_writes_nothing(runs, tmp_path):
    from nehad.model import load_run

    model, meta = load_run(runs["hnn"])
    model.field.set_grad_mode("autograd")  # not the export's closed form: it must stay so
    out = tmp_path / "x.onnx"
    with pytest.raises(ExportError, match="does not match"):
        export_model(model, meta, out, tol=-1.0)  # an impossible tolerance: the check fails
    with pytest.raises(ExportError, match="opset"):
        export_model(model, meta, out, opset=16)
    assert list(tmp_path.iterdir()) == []  # no temp file left, nothing written
    # the caller's model is untouched (grad mode, requires_grad)
    assert model.field.field.grad_mode == "autograd"
    assert all(p.requires_grad for p in model.parameters())


def test_export_cli_bad_inputs(runs, tmp_path):
    runner = CliRunner()
    cases = [
        ([str(tmp_path / "nope"), "-o", str(tmp_path / "a.onnx")], "not a finished training run"),
        ([str(runs["hnn"]), "-o", str(tmp_path / "missing" / "a.onnx")], "does not exist"),
        ([str(runs["hnn"]), "-o", str(tmp_path / "a.onx")], "must end in .onnx"),
        ([str(runs["hnn"]), "-o", str(tmp_path / "a.onnx"), "--opset", "16"], "opset"),
    ]
    for args, needle in cases:
        res = runner.invoke(main, ["export"] + args)
        assert res.exit_code != 0 and needle in res.output, res.output
        assert "Traceback" not in res.output
    assert not any(p.suffix.startswith(".on") for p in tmp_path.rglob("*"))


def test_carved_gaussians_life_exports_with_parity(tmp_path):
    """Gaussians with a finite life (life rate k > 0, nehad.gaussians): the exported graph scales
    their opacity by exp(-(k (t - t_eq))^2 / 2) as torch does, and the split-layer export refuses
    them above layer 0 with a message instead of dropping the life (tests/test_lod.py: in
    layer 0 it carries them)."""
    from nehad.checkpoint import atomic_torch_save, load_state
    from nehad.export.layers import SplitBaseGraph
    from nehad.model import load_run

    run, _ = make_run(tmp_path, "hnn")
    state = load_state(run / "model.pt")
    gs = state["gaussians"]
    n = gs["means"].shape[0]
    life = torch.zeros(n, 1)
    life[: n // 2] = torch.linspace(2.0, 30.0, n // 2).reshape(-1, 1)
    gs["life_rate"] = life
    atomic_torch_save(state, run / "model.pt")
    path = tmp_path / "model.onnx"
    res = CliRunner().invoke(main, ["export", str(run), "-o", str(path)])
    assert res.exit_code == 0, res.output
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    t_eq = gs["t_eq"].reshape(-1).numpy()
    for t in TIMES:
        got = sess.run(["opacities"], {"time": np.array([t], np.float32)})[0]
        ref = torch_reference(run, t)[3]
        assert parity_error(got, ref) <= 1e-5
        # independent of torch: the mortal half is the immortal opacity times the factor
        base = 1.0 / (1.0 + np.exp(-gs["opacity_logits"].reshape(-1).numpy()))
        expect = base * np.exp(-0.5 * (life.reshape(-1).numpy() * (t - t_eq)) ** 2)
        np.testing.assert_allclose(got, expect, rtol=1e-5, atol=1e-7)
        if t == 1.0:  # the life matters: some mortal Gaussians are mostly faded at t = 1
            assert (got[: n // 2] < 0.5 * base[: n // 2]).sum() >= 3
    model, _ = load_run(run)
    with pytest.raises(ExportError, match="finite lives in layer 0 only"):
        SplitBaseGraph(model, 0, n // 4)  # rows n/4 .. n/2 of an enhancement layer are mortal


def _exported_with_and_without_velocity(tmp_path, run, state):
    """Sessions of `run` saved with `state` and of its twin with every velocity 0, each
    exported by `nehad export`."""
    import shutil

    from nehad.checkpoint import atomic_torch_save

    atomic_torch_save(state, run / "model.pt")
    still = tmp_path / "still"  # the same model without velocities
    shutil.copytree(run, still)
    gs = state["gaussians"]
    atomic_torch_save({**state, "gaussians": {**gs, "velocity": torch.zeros_like(gs["velocity"])}},
                      still / "model.pt")
    sessions = []
    for r in (run, still):
        path = tmp_path / f"{r.name}.onnx"
        res = CliRunner().invoke(main, ["export", str(r), "-o", str(path)])
        assert res.exit_code == 0, res.output
        sessions.append(ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]))
    return sessions


def test_carved_gaussians_velocity_exports_with_parity(tmp_path):
    """A carved Gaussian's straight-line drift v (t - t_eq) (nehad.gaussians.drift) is in the
    exported means; Gaussians with k = 0 do not drift whatever their velocity holds."""
    from nehad.checkpoint import load_state

    run, _ = make_run(tmp_path, "hnn")
    state = load_state(run / "model.pt")
    gs = state["gaussians"]
    n = gs["means"].shape[0]
    life = torch.zeros(n, 1)
    life[: n // 2] = 5.0
    gs["life_rate"] = life
    gs["velocity"] = torch.linspace(-2.0, 2.0, 3 * n).reshape(n, 3)
    sessions = _exported_with_and_without_velocity(tmp_path, run, state)
    t_eq = gs["t_eq"].reshape(-1, 1).numpy()
    for t in TIMES:
        feed = {"time": np.array([t], np.float32)}
        moving, fixed = (s.run(["means"], feed)[0] for s in sessions)
        assert parity_error(moving, torch_reference(run, t)[0]) <= 1e-5
        # independent of torch: the mortal half moved by v (t - t_eq), the rest not at all
        drift = gs["velocity"].numpy() * (t - t_eq)
        np.testing.assert_allclose(moving[: n // 2] - fixed[: n // 2], drift[: n // 2],
                                   atol=2e-5)
        np.testing.assert_array_equal(moving[n // 2:], fixed[n // 2:])


def test_drift_window_exports_with_parity(tmp_path):
    """With train.drift_window W every Gaussian's drift v clamp(t - t_eq, -W, W) is in the
    exported means (nehad.gaussians.drift), times inside and outside the window."""
    from nehad.checkpoint import load_state

    run, _ = make_run(tmp_path, "hnn")
    state = load_state(run / "model.pt")
    gs = state["gaussians"]
    n = gs["means"].shape[0]
    gs["velocity"] = torch.linspace(-2.0, 2.0, 3 * n).reshape(n, 3)
    state["config"]["train"]["drift_window"] = 0.1
    sessions = _exported_with_and_without_velocity(tmp_path, run, state)
    t_eq = gs["t_eq"].reshape(-1, 1).numpy()
    for t in TIMES:
        feed = {"time": np.array([t], np.float32)}
        moving, fixed = (s.run(["means"], feed)[0] for s in sessions)
        assert parity_error(moving, torch_reference(run, t)[0]) <= 1e-5
        drift = gs["velocity"].numpy() * np.clip(t - t_eq, -0.1, 0.1)
        np.testing.assert_allclose(moving - fixed, drift, atol=2e-5)


def test_exported_softplus_matches_softplus():
    """The softplus the export writes (a cubic guess of log1p and one Newton step) is within
    7e-7 of softplus in float64, from far negative to far positive, and equal far out."""
    from unittest import mock

    import nehad.field.hnn as hnn

    z = torch.cat([torch.linspace(-60, 60, 400001), torch.tensor([-1e4, 1e4, 0.0])])
    with mock.patch.object(hnn, "is_capturing", lambda: True):
        got = hnn._softplus(z).double()
    want = torch.nn.functional.softplus(z.double())
    err = (got - want).abs() / want.clamp(min=1.0)
    assert err.max().item() < 7e-7
    assert got[-3].item() == 0.0 and got[-2].item() == 1e4
    assert abs(got[-1].item() - math.log(2.0)) < 4e-7
