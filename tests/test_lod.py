"""Layered progressive optimisation and streaming export (docs/design.md section 7-8; nehad.lod, nehad.export.layers,
nehad.runtime.layers): per-layer resolutions, frozen lower layers, opacity threshold, resume
inside a layer, the `layer` output, ONNX parity of every prefix of layers, chunk checks and the
fall back to the layers that arrived intact, and `nehad render --lod`."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from click.testing import CliRunner  # noqa: E402

from nehad.cli.main import main  # noqa: E402
from nehad.export.onnx_export import ExportError, export_run, parity_error  # noqa: E402
from nehad.runtime.layers import (LayeredModel, LayerError, decode_chunk,  # noqa: E402
                                  encode_chunk)
from torch_blocker import blocked_torch_env  # noqa: E402

OUTPUTS = ("means", "scales", "quats", "opacities", "sh")
SETS = ["lod.levels=3", "lod.iterations=12", "coarse.iterations=12", "fine.iterations=12",
        "densify.interval=4", "train.sh_degree_interval=10",
        "train.checkpoint_interval=1000", "lod.opacity_threshold=0.02"]


def _config(extra=()):
    from nehad.config import build_config

    return build_config("test", None, SETS + list(extra))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from nehad.data.synth import synthesize_scene

    root = tmp_path_factory.mktemp("lod")
    synthesize_scene(root / "scene", resolution=32, frames=8, points=300, seed=1)
    return root / "scene"


@pytest.fixture(scope="module")
def trained(scene, tmp_path_factory):
    """A 3-layer run stepped by hand, with snapshots at each layer end; then its model.pt with a
    clearly non-identity field (random adapters) for the export tests."""
    from nehad.checkpoint import atomic_torch_save, load_state
    from nehad.trainer import Trainer

    run = tmp_path_factory.mktemp("lodrun") / "run"
    tr = Trainer(_config(), scene, run, progress=False)
    snaps, fields, records = {}, {}, []
    while tr.step < tr.total_steps:
        records.append(tr.train_step(tr.step))
        tr.step += 1
        for layer in range(tr.schedule.levels):
            if tr.step == tr.schedule.layer_end(layer):
                g = tr.model.gaussians
                snaps[layer] = {n: getattr(g, n).detach().clone() for n in g.NAMES}
                fields[layer] = {k: v.clone() for k, v in tr.model.field.state_dict().items()}
    atomic_torch_save(tr.model_state(), run / "model.pt")
    state = load_state(run / "model.pt")
    gen = torch.Generator().manual_seed(3)
    for name, p in state["field"].items():
        if name.startswith("adapters."):
            state["field"][name] = torch.randn(p.shape, generator=gen) * 0.3
    gs = state["gaussians"]
    gs["t_eq"] = torch.rand(gs["t_eq"].shape, generator=gen)
    randomised = run.parent / "random_field"
    randomised.mkdir()
    atomic_torch_save(state, randomised / "model.pt")
    return {"trainer": tr, "run": run, "snaps": snaps, "fields": fields, "records": records,
            "export_run": randomised}


def test_layer_downscales_and_views(trained):
    from nehad.lod import layer_downscales, layer_ids

    assert layer_downscales(3, 2) == [8, 4, 2] and layer_downscales(1, 1) == [1]
    assert layer_ids([2, 0, 3]).tolist() == [0, 0, 2, 2, 2]
    tr = trained["trainer"]
    sizes = [tr.schedule.views(tr, k).images[0].shape[:2] for k in range(3)]
    assert sizes == [(8, 8), (16, 16), (32, 32)]  # 32 px scene: 1/4, 1/2, full
    # each step trained on its layer's resolution, and the layers follow each other
    assert [r["layer"] for r in trained["records"]] == [0] * 24 + [1] * 12 + [2] * 12
    assert tr.total_steps == 48


def test_lower_layers_frozen_and_field_shared(trained):
    tr, snaps = trained["trainer"], trained["snaps"]
    sizes = tr.layer_sizes
    assert len(sizes) == 3 and all(n > 0 for n in sizes)
    print(f"layer sizes {sizes}")
    g = tr.model.gaussians
    for layer in (0, 1):
        n = sum(sizes[:layer + 1])
        for name in g.NAMES:  # bit-identical after the later layers trained
            assert torch.equal(getattr(g, name)[:n], snaps[layer][name][:n]), (layer, name)
    # the field trained in layer 0 only (lod.train_field false)
    for k, v in trained["fields"][0].items():
        assert torch.equal(v, trained["fields"][2][k]), k
    # every kept Gaussian of every layer is at or above the opacity threshold
    opac = torch.sigmoid(g.opacity_logits.detach())
    assert float(opac.min()) >= 0.02
    assert tr.schedule.frozen == len(g) == sum(sizes)


def test_model_pt_layers(trained):
    from nehad.checkpoint import load_state

    state = load_state(trained["run"] / "model.pt")
    layer = state["layer"]
    assert layer.dtype == torch.int32 and layer.shape == (len(state["gaussians"]["means"]),)
    assert np.all(np.diff(layer.numpy()) >= 0)
    assert np.bincount(layer.numpy()).tolist() == state["lod"]["layer_sizes"]
    assert state["lod"]["downscales"] == [4, 2, 1] and state["lod"]["levels"] == 3


def test_opacity_threshold_controls_layer_size(scene, tmp_path):
    from nehad.trainer import Trainer

    def run(thr, name):
        tr = Trainer(_config([f"lod.opacity_threshold={thr}", "lod.levels=2"]), scene,
                          tmp_path / name, progress=False, log=None)
        tr.train()
        return tr

    loose = run(0.0, "loose")
    n0 = loose.layer_sizes[0]
    opac0 = torch.sigmoid(loose.model.gaussians.opacity_logits.detach()[:n0])
    thr = float(opac0.median())  # layer 0 ends identically in both runs (deterministic)
    tight = run(thr, "tight")
    print(f"layer sizes: threshold 0 {loose.layer_sizes}, threshold {thr:.4f} {tight.layer_sizes}")
    assert tight.layer_sizes[0] == int((opac0 >= thr).sum()) < n0
    assert tight.layer_sizes[1] < loose.layer_sizes[1]
    # a threshold above every opacity keeps the layer whole instead of emptying it
    assert run(0.99, "all").layer_sizes[0] == n0


def test_layer_caps(scene, tmp_path):
    """lod.base_max_gaussians caps layer 0; densify.max_gaussians caps each enhancement layer
    on its own (it counts the trainable Gaussians, not the frozen ones below)."""
    from nehad.trainer import Trainer

    free = Trainer(_config(["lod.levels=2", "lod.opacity_threshold=0",
                                 "densify.max_gaussians=0"]), scene,
                        tmp_path / "free", progress=False, log=None)
    free.train()
    n0, n1 = free.layer_sizes
    base_cap = n0 - 40
    layer_cap = n0 + 5  # below what layer 1 grows to, above the n0 children it starts with
    assert n1 > layer_cap, free.layer_sizes
    capped = Trainer(_config(["lod.levels=2", "lod.opacity_threshold=0",
                                   f"lod.base_max_gaussians={base_cap}",
                                   f"densify.max_gaussians={layer_cap}"]), scene,
                          tmp_path / "capped", progress=False, log=None)
    capped.train()
    c0, c1 = capped.layer_sizes
    print(f"layers without caps {free.layer_sizes}, with caps {capped.layer_sizes}")
    assert c0 <= base_cap < n0
    assert c0 < c1 <= layer_cap  # layer 1 grew past its c0 children, up to its own cap


def test_resume_inside_an_enhancement_layer(scene, tmp_path, trained):
    from nehad.checkpoint import save_checkpoint
    from nehad.trainer import Trainer

    run = tmp_path / "r"
    tr = Trainer(_config(), scene, run, progress=False)
    while tr.step < 30:  # 6 steps into layer 1
        tr.train_step(tr.step)
        tr.step += 1
    save_checkpoint(run, tr.step, tr.checkpoint_state(), 2)
    del tr
    resumed = Trainer(_config(), scene, run, resume=True, progress=False)
    assert resumed.step == 30 and resumed.layer_sizes == trained["trainer"].layer_sizes[:1]
    assert resumed.schedule.frozen == resumed.layer_sizes[0]
    resumed.train()
    ref = trained["trainer"].model.gaussians
    got = resumed.model.gaussians
    assert resumed.layer_sizes == trained["trainer"].layer_sizes
    for name in got.NAMES:
        assert torch.allclose(getattr(got, name), getattr(ref, name), atol=1e-6), name


def test_every_construction_follows_the_config_schedule(scene, tmp_path):
    """The schedule follows from the config wherever the trainer is built: `Trainer(cfg)`
    (`nehad train`, bench/quality.py) and `nehad demo` train the layers lod.levels asks for."""
    from nehad.checkpoint import load_state
    from nehad.configtools import ConfigError
    from nehad.demo import run_demo
    from nehad.lod import LayeredSchedule, schedule_for
    from nehad.schedule import StagedSchedule
    from nehad.trainer import Trainer

    assert type(schedule_for(_config(["lod.levels=1"]))) is StagedSchedule
    assert type(schedule_for(_config())) is LayeredSchedule
    tr = Trainer(_config(["lod.levels=2"]), scene, tmp_path / "direct", progress=False)
    assert isinstance(tr.schedule, LayeredSchedule) and tr.total_steps == 36
    # enhancement layers without steps: refused before anything is written
    with pytest.raises(ConfigError, match="lod.iterations"):
        Trainer(_config(["lod.iterations=0", "fine.iterations=0"]), scene, tmp_path / "no")
    assert not (tmp_path / "no").exists()
    out = run_demo(tmp_path / "demo", resolution=24, frames=8, preset="test",
                   overrides=["lod.levels=2", "coarse.iterations=6", "fine.iterations=6",
                              "lod.iterations=4"], progress=False, log=lambda *a: None)
    state = load_state(out["run"] / "model.pt")
    assert state["steps"] == 16 and state["lod"]["levels"] == 2
    assert np.bincount(state["layer"].numpy()).tolist() == state["lod"]["layer_sizes"]


def test_export_layer_output_parity(trained, tmp_path):
    from nehad.model import load_run

    run = trained["export_run"]
    path = tmp_path / "m.onnx"
    rep = export_run(run, path, static=False)  # every row through the field, held to torch
    proto = onnx.load(str(path))
    md = {p.key: p.value for p in proto.metadata_props}
    parts = len(json.loads(md.get("parts", "[0, 0]"))) - 1  # docs/design.md section 7
    assert parts > 1  # this run is large enough to be cut into parts
    assert [o.name for o in proto.graph.output] == list(OUTPUTS) + ["layer"] + [
        f"{name}.part{p}" for p in range(parts) for name in OUTPUTS[:4]]
    model, meta = load_run(run)
    assert json.loads(md["lod_layers"]) == meta.lod["layer_sizes"]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for t in (0.0, 0.4, 1.0):
        got = sess.run(None, {"time": np.array([t], np.float32)})
        with torch.no_grad():
            ref = [o.numpy() for o in model.gaussians_at(t)]
        ref[4] = ref[4][:, :got[4].shape[1]]
        for a, b in zip(got[:5], ref):
            worst = max(worst, parity_error(a, b))
        assert got[5].dtype == np.int32 and np.array_equal(got[5], meta.layer)
    print(f"layered export parity {worst:.3g} (report {rep.parity})")
    assert worst <= 1e-5
    m0 = sess.run(["means"], {"time": np.array([0.0], np.float32)})[0]
    m1 = sess.run(["means"], {"time": np.array([1.0], np.float32)})[0]
    assert np.abs(m0 - m1).max() > 1e-2  # the deformation is not the identity
    from nehad.runtime.onnx_model import OnnxModel

    side, one = OnnxModel(path, threads=2), OnnxModel(path, threads=1)  # parts side by side
    assert side.workers == 2
    for t in (0.0, 0.7):
        a, b = side.outputs(t), one.outputs(t)
        assert list(a) == list(OUTPUTS) + ["layer"]
        for name in a:
            np.testing.assert_array_equal(a[name], b[name])
        assert np.array_equal(a["layer"], meta.layer)


@pytest.fixture(scope="module")
def split(trained, tmp_path_factory):
    folder = tmp_path_factory.mktemp("split") / "layers"
    res = CliRunner().invoke(main, ["export", str(trained["export_run"]), "--split-layers",
                                    str(folder)])
    assert res.exit_code == 0, res.output
    print(res.output)
    return folder


def test_split_manifest_and_chunks(split, trained):
    import hashlib

    man = json.loads((split / "manifest.json").read_text())
    sizes = trained["trainer"].layer_sizes
    assert [e["gaussians"] for e in man["layers"]] == sizes
    assert [e["file"] for e in man["layers"]] == ["base.onnx", "layer_1.bin", "layer_2.bin"]
    for e in man["layers"]:
        data = (split / e["file"]).read_bytes()
        assert len(data) == e["bytes"] and hashlib.sha256(data).hexdigest() == e["sha256"]
    assert man["layers"][-1]["cumulative_bytes"] == sum(e["bytes"] for e in man["layers"])
    # a chunk is the layer's canonical Gaussians: 4 bytes x (3+3+4+1+3K+3+1) each + header
    k = (man["sh_degree"] + 1) ** 2
    assert man["bytes_per_gaussian"] == 4 * (15 + 3 * k)
    header, arrays = decode_chunk((split / "layer_2.bin").read_bytes())
    assert header["count"] == sizes[2] and arrays["sh"].shape == (sizes[2], k, 3)
    assert 0 < man["layers"][2]["bytes"] - sizes[2] * man["bytes_per_gaussian"] < 2048
    # the base model is a normal nehad-onnx/1 file: layer 0 alone, time as its only input
    proto = onnx.load(str(split / "base.onnx"))
    from nehad.export.checks import check_graph

    check_graph(proto)
    opts = ort.SessionOptions()
    opts.log_severity_level = 3  # (the extra_* inputs are initializers too: ORT would say so)
    sess = ort.InferenceSession(str(split / "base.onnx"), opts,
                                providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["time"]
    assert len(sess.run(None, {"time": np.array([0.5], np.float32)})[0]) == sizes[0]


def test_split_prefixes_match_torch(split, trained):
    from nehad.model import load_run

    model, meta = load_run(trained["export_run"])
    sizes = trained["trainer"].layer_sizes
    worst = 0.0
    for k in range(3):
        lm = LayeredModel(split, max_layer=k)
        assert lm.loaded_layers == k + 1 and lm.problems == []
        n = sum(sizes[:k + 1])
        for t in (0.0, 0.7, 1.0):
            out = lm.outputs(t)
            with torch.no_grad():
                ref = [o.numpy()[:n] for o in model.gaussians_at(t)]
            ref[4] = ref[4][:, :out["sh"].shape[1]]
            for name, b in zip(OUTPUTS, ref):
                assert out[name].shape == b.shape
                worst = max(worst, parity_error(out[name], b))
            assert np.array_equal(out["layer"], meta.layer[:n])
    print(f"split layers parity vs torch prefixes {worst:.3g}")
    assert worst <= 1e-5


def test_split_export_carries_layer0_lives_and_velocities(trained, tmp_path):
    """Carving's chains (finite life, a velocity; nehad.carve_pass) live in layer 0: the split
    export carries them, and its prefixes still match torch's gaussians_at."""
    from nehad.export.layers import export_split_model
    from nehad.model import load_run

    model, info = load_run(trained["export_run"])
    g, sizes = model.gaussians, trained["trainer"].layer_sizes
    with torch.no_grad():
        g.life_rate[:sizes[0]:3] = 4.0
        g.velocity[:sizes[0]:3] = torch.tensor([0.3, -0.2, 0.1])
    export_split_model(model, info, tmp_path / "layers", cfg=info.config)
    lm = LayeredModel(tmp_path / "layers")
    assert lm.loaded_layers == 3 and lm.problems == []
    worst = 0.0
    for t in (0.0, 0.7, 1.0):
        out = lm.outputs(t)
        with torch.no_grad():
            ref = [o.numpy() for o in model.gaussians_at(t)]
        ref[4] = ref[4][:, :out["sh"].shape[1]]
        for name, b in zip(OUTPUTS, ref):
            worst = max(worst, parity_error(out[name], b))
    assert worst <= 1e-5
    with torch.no_grad():  # the lives matter: without them the opacities differ
        g.life_rate.zero_()
        plain = model.gaussians_at(0.0)[3].numpy()
    assert np.abs(lm.outputs(0.0)["opacities"] - plain).max() > 1e-3
    with torch.no_grad():  # a finite life in an enhancement layer cannot be carried
        g.life_rate[sizes[0]] = 1.0
    with pytest.raises(ExportError, match="layer 0 only"):
        export_split_model(model, info, tmp_path / "other", cfg=info.config)


def test_split_fp16_field(split, trained, tmp_path):
    """--fp16-weights with --split-layers: the field is stored as float16 (the base file
    shrinks), the Gaussians stay float32 (chunks byte-identical), and every prefix matches the
    torch model with its field rounded to float16."""
    from nehad.export.layers import export_split_layers
    from nehad.model import load_run

    rep = export_split_layers(trained["export_run"], tmp_path / "half", fp16_field=True)
    man32 = json.loads((split / "manifest.json").read_text())
    man16 = rep.manifest
    model, meta = load_run(trained["export_run"])
    plane_values = sum(p.numel() for n, p in model.field.named_parameters()
                       if n.startswith("hexplane."))
    print(f"field bytes float32 {man32['field_bytes']}, float16 field {man16['field_bytes']}; "
          f"{plane_values} hex-plane values")
    # every hex-plane value is stored in 2 bytes instead of 4
    assert man32["field_bytes"] - man16["field_bytes"] >= 2 * plane_values
    for e32, e16 in zip(man32["layers"][1:], man16["layers"][1:]):
        assert e16["sha256"] == e32["sha256"]
    proto = onnx.load(str(tmp_path / "half" / "base.onnx"))
    assert {p.key: p.value for p in proto.metadata_props}["fp16_weights"] == "field"
    with torch.no_grad():
        for p in model.field.parameters():
            p.copy_(p.half().float())
    n_all = sum(trained["trainer"].layer_sizes)
    lm = LayeredModel(tmp_path / "half")
    assert lm.loaded_layers == 3
    worst = 0.0
    for t in (0.0, 0.7):
        out = lm.outputs(t)
        with torch.no_grad():
            ref = [o.numpy()[:n_all] for o in model.gaussians_at(t)]
        ref[4] = ref[4][:, :out["sh"].shape[1]]
        worst = max(worst, *(parity_error(out[nm], b) for nm, b in zip(OUTPUTS, ref)))
    assert worst <= 1e-5


def test_missing_or_corrupt_chunk_falls_back(split, tmp_path):
    sizes = json.loads((split / "manifest.json").read_text())["layers"]
    cases = {
        "missing2": lambda d: (d / "layer_2.bin").unlink(),
        "flipped1": lambda d: _flip(d / "layer_1.bin", 200),
        "truncated2": lambda d: (d / "layer_2.bin").write_bytes((d / "layer_2.bin").read_bytes()[:-7]),
    }
    expect = {"missing2": (2, "missing"), "flipped1": (1, "sha256"), "truncated2": (2, "bytes")}
    for name, damage in cases.items():
        d = tmp_path / name
        shutil.copytree(split, d)
        damage(d)
        lm = LayeredModel(d)
        layers, needle = expect[name]
        assert lm.loaded_layers == layers, name
        assert len(lm.problems) == 1 and needle in lm.problems[0], lm.problems
        assert f"rendering layers 0..{layers - 1}" in lm.problems[0]
        assert len(lm.gaussians(0.5)) == sum(e["gaussians"] for e in sizes[:layers])
    # the chunk arrives later: refresh picks it up
    d = tmp_path / "missing2"
    shutil.copy(split / "layer_2.bin", d / "layer_2.bin")
    lm = LayeredModel(d)
    assert lm.loaded_layers == 3 and lm.problems == []
    # a damaged base cannot be rendered at all: an error naming it
    d = tmp_path / "badbase"
    shutil.copytree(split, d)
    _flip(d / "base.onnx", 100)
    with pytest.raises(LayerError, match="base.onnx does not match its sha256"):
        LayeredModel(d)


def _flip(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_chunk_codec_rejects_garbage():
    arrays = {"means": np.ones((2, 3)), "log_scales": np.zeros((2, 3)), "quats": np.ones((2, 4)),
              "opacity_logits": np.zeros(2), "sh": np.zeros((2, 4, 3)), "mu_eq": np.ones((2, 3)),
              "t_eq": np.full((2, 1), 0.5)}
    blob = encode_chunk(1, arrays)
    header, back = decode_chunk(blob)
    assert header["layer"] == 1 and header["count"] == 2
    assert np.array_equal(back["quats"], np.ones((2, 4), np.float32))
    for bad, needle in ((b"garbage" * 4, "magic"), (blob[:20], "truncated"),
                        (blob[:-8], "outside")):
        with pytest.raises(LayerError, match=needle):
            decode_chunk(bad, "x.bin")


def test_render_lod_cli(split, trained, tmp_path):
    from nehad.runtime.images import read_image

    run = trained["export_run"]
    onnx_path = tmp_path / "full.onnx"
    export_run(run, onnx_path)
    cam = f"{trained['trainer'].data_dir / 'transforms_test.json'}:0"
    runner = CliRunner()
    images = {}
    for k in (0, 2):
        for name, src in (("run", run), ("onnx", onnx_path), ("split", split)):
            out = tmp_path / f"{name}{k}.exr"
            res = runner.invoke(main, ["render", str(src), "--view", cam, "--time", "0.3",
                                       "--lod", str(k), "-o", str(out)])
            assert res.exit_code == 0, res.output
            assert f"layers 0..{k}" in res.output
            images[name, k] = read_image(out).astype(np.float64)
    for k in (0, 2):
        for name in ("onnx", "split"):
            mse = float(np.mean((images[name, k] - images["run", k]) ** 2))
            psnr = 10 * np.log10(1.0 / max(mse, 1e-30))
            print(f"--lod {k}: {name} vs torch render PSNR {psnr:.1f} dB")
            assert psnr > 60.0
    assert float(np.abs(images["run", 0] - images["run", 2]).max()) > 0.05  # layers add detail
    # bad --lod values: one line, non-zero exit, no traceback
    for src in (run, onnx_path, split):
        res = runner.invoke(main, ["render", str(src), "--view", cam, "--time", "0.3", "--lod",
                                   "3", "-o", str(tmp_path / "x.png")])
        assert res.exit_code != 0 and "has 3 layer(s), 0..2" in res.output, res.output
        assert "Traceback" not in res.output
    # a corrupt chunk: a warning, the render of the layers before it, exit 0
    d = tmp_path / "corrupt"
    shutil.copytree(split, d)
    _flip(d / "layer_2.bin", 300)
    res = runner.invoke(main, ["render", str(d), "--view", cam, "--time", "0.3", "-o",
                               str(tmp_path / "c.exr")])
    assert res.exit_code == 0 and "warning: layer 2:" in res.output, res.output
    assert "layers 0..1 of 3" in res.output


def test_split_export_refuses_runs_without_layers(scene, tmp_path):
    from nehad.trainer import Trainer

    run = tmp_path / "plain"
    Trainer(_config(["lod.levels=1", "coarse.iterations=2", "fine.iterations=2"]), scene, run,
            progress=False).train()
    res = CliRunner().invoke(main, ["export", str(run), "--split-layers", str(tmp_path / "s")])
    assert res.exit_code != 0 and "no streaming layers" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "s").exists()
    res = CliRunner().invoke(main, ["export", str(run)])
    assert res.exit_code != 0 and "--split-layers" in res.output
    # without layers the file is exactly docs/design.md section 7's: no `layer` output, no lod metadata
    export_run(run, tmp_path / "plain.onnx")
    proto = onnx.load(str(tmp_path / "plain.onnx"))
    assert [o.name for o in proto.graph.output] == list(OUTPUTS)
    assert [i.name for i in proto.graph.input] == ["time"]
    assert "lod_layers" not in {p.key for p in proto.metadata_props}
    res = CliRunner().invoke(main, ["render", str(tmp_path / "plain.onnx"), "--view",
                                    f"{scene / 'transforms_test.json'}:0", "--lod", "1", "-o",
                                    str(tmp_path / "x.png")])
    assert res.exit_code != 0 and "has 1 layer(s), 0..0" in res.output, res.output


def test_layered_runtime_without_torch(split, tmp_path):
    code = ("import sys; from nehad.runtime.layers import LayeredModel; "
            f"m = LayeredModel({str(split)!r}); c = m.gaussians(0.5); "
            "assert 'torch' not in sys.modules; print(m.loaded_layers, len(c))")
    res = subprocess.run([sys.executable, "-c", code], env=blocked_torch_env(tmp_path),
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    man = json.loads((split / "manifest.json").read_text())
    assert res.stdout.split() == ["3", str(man["layers"][-1]["cumulative_gaussians"])]


def test_video_and_batch_take_every_scene_kind_with_lod(split, trained, tmp_path):
    """`nehad video` and `nehad batch` open scenes as `nehad render` does (runtime/scene.py):
    a run folder, an .onnx and a split layers folder, each with --lod / lod:, give the frame
    `nehad render` gives for the same camera, time and layers."""
    import textwrap

    from nehad.runtime.images import read_image

    run = trained["export_run"]
    onnx_path = tmp_path / "full.onnx"
    export_run(run, onnx_path)
    cam = f"{trained['trainer'].data_dir / 'transforms_test.json'}:0"
    runner = CliRunner()
    for name, src in (("run", run), ("onnx", onnx_path), ("split", split)):
        ref = tmp_path / f"{name}_ref.exr"
        res = runner.invoke(main, ["render", str(src), "--view", cam, "--time", "0.3", "--lod",
                                   "0", "-o", str(ref)])
        assert res.exit_code == 0, res.output
        reference = read_image(ref)
        frames = tmp_path / f"{name}_frames"
        res = runner.invoke(main, ["video", str(src), "--path", cam, "--time", "0.3",
                                   "--frames", "1", "--frames-dir", str(frames),
                                   "--frame-format", "exr", "--lod", "0", "--workers", "1",
                                   "--quiet"])
        assert res.exit_code == 0, res.output
        np.testing.assert_array_equal(read_image(frames / "frame_00000.exr"), reference)
        jobs = tmp_path / f"{name}_jobs.yaml"
        jobs.write_text(textwrap.dedent(f"""\
            workers: 1
            jobs:
              - {{name: still, model: {src}, output: {tmp_path / name}_still.exr, view: {cam},
                  time: 0.3, lod: 0}}
            """))
        res = runner.invoke(main, ["batch", str(jobs), "--quiet"])
        assert res.exit_code == 0, res.output
        np.testing.assert_array_equal(read_image(tmp_path / f"{name}_still.exr"), reference)
    # the layer count is checked before anything is drawn, in the scene's words
    res = runner.invoke(main, ["video", str(split), "--lod", "3", "-o",
                               str(tmp_path / "x.mp4"), "--quiet"])
    assert res.exit_code != 0 and "--lod 3:" in res.output and "has 3 layer(s)" in res.output
    assert not (tmp_path / "x.mp4").exists()


def test_enhancement_layers_spawn_no_mortal_children(scene, tmp_path):
    """A layer's seeds skip carving's chains (a finite life): a child would inherit the life,
    which the split-layer export carries in layer 0 only ("finite lives in layer 0 only" ended
    `nehad export --split-layers` of a run trained with tracks and --lod-levels 2)."""
    from nehad.export.layers import export_split_model
    from nehad.model import load_run
    from nehad.trainer import Trainer

    tr = Trainer(_config(["lod.levels=2"]), scene, tmp_path / "run", progress=False)
    end0 = tr.schedule.layer_end(0)
    while tr.step < end0 + 1:
        if tr.step == end0 - 1:
            with torch.no_grad():
                tr.model.gaussians.life_rate[::4] = 3.0
        tr.train_step(tr.step)
        tr.step += 1
    g = tr.model.gaussians
    f = tr.schedule.frozen
    mortal = int((g.life_rate[:f] != 0).sum())
    assert 0 < mortal < f
    assert float(g.life_rate.detach()[f:].abs().max()) == 0.0
    assert len(g) - f <= f - mortal  # children of the immortal only (the step may prune)
    while tr.step < tr.total_steps:
        tr.train_step(tr.step)
        tr.step += 1
    from nehad.checkpoint import atomic_torch_save

    atomic_torch_save(tr.model_state(), tmp_path / "run" / "model.pt")
    model, info = load_run(tmp_path / "run")
    export_split_model(model, info, tmp_path / "layers", cfg=info.config)
    assert LayeredModel(tmp_path / "layers").loaded_layers == 2
