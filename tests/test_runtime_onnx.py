"""The torch-free runtime of exported models (nehad.runtime.onnx_model) and the `render`, `info`,
`ply` commands on .onnx files: validation, the per-time cache, rendering where torch cannot be
imported, and one-line errors for bad inputs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import stacks

ort = pytest.importorskip("onnxruntime")

from click.testing import CliRunner  # noqa: E402

from nehad.cli.main import main  # noqa: E402
from nehad.runtime.onnx_model import OnnxModel, OnnxModelError, read_model_info  # noqa: E402
from nehad.runtime.ply import read_gaussian_ply  # noqa: E402
from torch_blocker import blocked_torch_env  # noqa: E402


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(model.onnx, run dir, camera spec) from a tiny trained run with randomised adapters."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from test_export import make_run

    from nehad.export.onnx_export import export_run

    root = tmp_path_factory.mktemp("rt")
    run, data = make_run(root, "hnn", seed=3)
    path = root / "model.onnx"
    export_run(run, path)
    return path, run, f"{data / 'transforms_test.json'}:0"


def fake_model(path, n=2, sh_degree=0, means=None, metadata=None, drop_output=None):
    """A hand-built nehad-format ONNX (constant outputs) for validation tests; needs `onnx`."""
    pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    k = (sh_degree + 1) ** 2
    values = {"means": np.zeros((n, 3), np.float32) if means is None else means,
              "scales": np.full((n, 3), 0.1, np.float32),
              "quats": np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
              "opacities": np.full((n,), 0.5, np.float32),
              "sh": np.zeros((n, k, 3), np.float32)}
    if drop_output:
        values.pop(drop_output)
    nodes, inits, outs = [], [], []
    for name, v in values.items():
        inits.append(numpy_helper.from_array(v.astype(np.float32), f"{name}_c"))
        # out = c + 0 * time (uses the input)
        nodes.append(helper.make_node("Mul", ["time", "zero"], [f"{name}_z"]))
        nodes.append(helper.make_node("Add", [f"{name}_c", f"{name}_z"], [name]))
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(v.shape)))
    inits.append(numpy_helper.from_array(np.zeros(1, np.float32), "zero"))
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(
        "time", TensorProto.FLOAT, [1])], outs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # what onnxruntime reads (the onnx package may default newer)
    md = {"format": "nehad-onnx/1", "sh_degree": str(sh_degree), "num_gaussians": str(n),
          "time_range": "[0.0, 1.0]", "background": "[0, 0, 0]",
          "aabb": "[[-1, -1, -1], [1, 1, 1]]"}
    md.update(metadata or {})
    for key, value in md.items():
        if value is not None:
            e = model.metadata_props.add()
            e.key, e.value = key, value
    Path(path).write_bytes(model.SerializeToString())
    return Path(path)




def test_model_metadata_cache_and_threads(exported):
    path, _, _ = exported
    m = OnnxModel(path, threads=1, cache_size=2)
    assert m.sh_degree == 0 and m.time_range == (0.0, 1.0) and len(m) > 0
    assert m.default_camera is not None and m.default_camera.width == 24
    a = m.gaussians(0.25)
    b = m.gaussians(0.25)  # a second view at the same time: no second run
    assert m.runs == 1 and np.array_equal(a.means, b.means) and len(a) == m.num_gaussians
    m.gaussians(0.5), m.gaussians(0.75), m.gaussians(0.25)  # 0.25 was evicted (cache of 2)
    assert m.runs == 4
    assert np.allclose(np.linalg.norm(a.quats, axis=1), 1, atol=1e-5)
    assert (a.opacities > 0).all() and (a.opacities < 1).all() and (a.scales > 0).all()
    with pytest.raises(OnnxModelError, match="finite"):
        m.gaussians(float("nan"))


def test_render_frames_pipelined_equals_one_by_one(exported):
    """A sequence drawn with the next deformation on a second thread (runtime/render.py
    `render_frames`) gives each frame render_view's picture, in order, deforming each time once;
    stopping early leaves no thread behind."""
    import threading

    from nehad.runtime.render import render_frames, render_view
    from nehad.runtime.scene import choose_camera, open_scene

    path, _, spec = exported
    scene = open_scene(path, threads=1)
    camera = choose_camera(scene, spec)
    times = [0.0, 0.3, 0.6, 0.9, 0.6]
    frames = [(camera, t) for t in times]
    one_by_one = [render_view(scene, c, t, adapt_threads=False).image for c, t in frames]
    scene.model.clear_cache()
    runs = scene.model.runs
    seq = list(render_frames(scene, frames))
    assert len(seq) == len(times)
    for got, want in zip(seq, one_by_one):
        assert np.array_equal(got.image, want)
    assert scene.model.runs - runs == 4  # 0.6 a second time: from the model's cache
    # frames differ over time (the test would pass on a frozen scene otherwise)
    assert not np.array_equal(seq[0].image, seq[3].image)
    gen = render_frames(scene, [(camera, t) for t in (0.1, 0.2, 0.4)])
    next(gen)
    gen.close()
    assert not [t for t in threading.enumerate() if t.name.startswith("nehad-deform")]


def test_render_info_ply_without_torch(exported, tmp_path):
    path, _, cam = exported
    env = blocked_torch_env(tmp_path)
    assert subprocess.run([sys.executable, "-c", "import torch"], env=env,
                          capture_output=True).returncode != 0
    cli = [sys.executable, "-m", "nehad.cli.main"]
    out = tmp_path / "r.png"
    proc = stacks.run(cli + ["render", str(path), "--time", "0.4", "--view", cam, "-o",
                             str(out)], timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert out.exists()
    proc = subprocess.run(cli + ["info", str(path)], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    for needle in ("nehad-onnx/1", "Gaussians:", "SH degree:", "time range:", "bounds:",
                   "opset:", "17", "Gather", "file size:"):
        assert needle in proc.stdout, (needle, proc.stdout)
    ply = tmp_path / "f.ply"
    proc = subprocess.run(cli + ["ply", str(path), "--time", "0.3", "-o", str(ply)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    cloud = read_gaussian_ply(ply)
    ref = OnnxModel(path).gaussians(0.3)
    assert np.allclose(cloud.means, ref.means) and np.allclose(cloud.scales, ref.scales, rtol=1e-5)
    assert np.allclose(cloud.opacities, ref.opacities, atol=1e-6)


def test_ply_frames(exported, tmp_path):
    path, _, _ = exported
    out = tmp_path / "frames"
    res = CliRunner().invoke(main, ["ply", str(path), "--frames", "3", "-o", str(out)])
    assert res.exit_code == 0, res.output
    files = sorted(out.iterdir())
    assert [f.name for f in files] == ["frame_0000.ply", "frame_0001.ply", "frame_0002.ply"]
    m = OnnxModel(path)
    for f, t in zip(files, (0.0, 0.5, 1.0)):
        assert np.allclose(read_gaussian_ply(f).means, m.gaussians(t).means, atol=1e-6)


def test_validation_of_files(tmp_path):
    good = fake_model(tmp_path / "good.onnx")
    m = OnnxModel(good)
    assert len(m.gaussians(0.5)) == 2 and read_model_info(good).operators == {"Mul": 5, "Add": 5}
    cases = {
        "foreign": ({"format": None}, None, "not a nehad model"),
        "badmeta": ({"time_range": "[1, 0, 2]"}, None, "time_range"),
        "missing": ({}, "sh", "lacks outputs"),
        "shape": ({"num_gaussians": "3"}, None, "num_gaussians 3"),
    }
    for name, (md, drop, needle) in cases.items():
        p = fake_model(tmp_path / f"{name}.onnx", metadata=md, drop_output=drop)
        with pytest.raises(OnnxModelError, match=needle) as e:
            OnnxModel(p)
        assert str(p) in str(e.value)
    data = good.read_bytes()
    (tmp_path / "trunc.onnx").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.onnx").write_bytes(b"\x00\xffnot an onnx file at all" * 10)
    for name in ("trunc", "junk"):
        with pytest.raises(OnnxModelError, match=f"{name}.onnx") as e:
            OnnxModel(tmp_path / f"{name}.onnx")
        assert "nehad" in str(e.value) or "ONNX" in str(e.value)
    nan = np.zeros((2, 3), np.float32)
    nan[1, 2] = np.nan
    with pytest.raises(OnnxModelError, match="means.*NaN"):
        OnnxModel(fake_model(tmp_path / "nan.onnx", means=nan)).gaussians(0.5)


@pytest.mark.parametrize("metadata, needle", [
    ({"background": "[0, 0, 2]"}, "metadata 'background' must lie in [0, 1]"),
    ({"background": "[-0.5, 0, 0]"}, "metadata 'background' must lie in [0, 1]"),
    ({"static_gaussians": "5"}, "static_gaussians is not a whole number from 0 to num_gaussians"),
])
def test_out_of_range_metadata_is_refused_when_opened(tmp_path, metadata, needle):
    """A background outside [0, 1] and more static Gaussians than the file holds (keys outside
    the graph's digest) are refused when the file is read: `info` and `render` end with one
    line naming the file and the key, and nothing is written."""
    from clean_errors import one_error

    from nehad.runtime.cameras import Camera, save_view

    bad = fake_model(tmp_path / "bad.onnx", metadata=metadata)
    w2c = np.eye(4)
    w2c[2, 3] = 3.0
    view = save_view(tmp_path / "cam.json", Camera(16, 16, 20.0, 20.0, 8.0, 8.0, w2c))
    with pytest.raises(OnnxModelError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        read_model_info(bad)
    runner = CliRunner()
    one_error(runner.invoke(main, ["info", str(bad)]), str(bad), needle)
    one_error(runner.invoke(main, ["render", str(bad), "--time", "0.5", "--view", str(view),
                                   "-o", str(tmp_path / "o.png")]), str(bad), needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.onnx", "cam.json"]


def test_cli_bad_inputs(exported, tmp_path):
    path, _, cam = exported
    foreign = fake_model(tmp_path / "foreign.onnx", metadata={"format": "something/else"})
    (tmp_path / "trunc.onnx").write_bytes(path.read_bytes()[:1000])
    runner = CliRunner()
    png = tmp_path / "o.png"
    cases = [
        (["render", str(foreign), "--time", "0.5", "--view", cam, "-o", str(png)], "not a nehad model"),
        (["render", str(tmp_path / "trunc.onnx"), "--time", "0.5", "--view", cam, "-o", str(png)],
         "truncated or corrupt"),
        (["render", str(path), "--time", "nan", "--view", cam, "-o", str(png)], "finite"),
        (["render", str(path), "--time", "0.5", "--view", cam, "-o",
          str(tmp_path / "nodir" / "o.png")], "does not exist"),
        (["render", str(tmp_path / "absent.onnx"), "--time", "0.5", "--view", cam, "-o", str(png)],
         "no such file"),
        (["ply", str(path), "--time", "nan", "-o", str(tmp_path / "f.ply")], "finite"),
        (["ply", str(path), "--time", "0.5", "-o", str(tmp_path / "nodir" / "f.ply")],
         "does not exist"),
        (["ply", str(foreign), "--frames", "2", "-o", str(tmp_path / "seq")], "not a nehad model"),
        (["ply", str(path), "--time", "2", "-o", str(tmp_path / "f.ply")], "outside"),
        (["info", str(tmp_path / "trunc.onnx")], "truncated or corrupt"),
        (["info", str(foreign)], "not a nehad model"),
    ]
    for args, needle in cases:
        res = runner.invoke(main, args)
        assert res.exit_code != 0 and needle in res.output, (args, res.output)
        assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1
    assert not png.exists() and not (tmp_path / "f.ply").exists()
    assert not (tmp_path / "seq").exists() and not (tmp_path / "nodir").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign.onnx", "trunc.onnx"]
