"""The `nehad` command line: help, synth, render (against an independent float64 reference, in a
process where torch cannot be imported), and the one-line errors for bad inputs."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime.cameras import load_view
from nehad.runtime.gaussians import GaussianCloud
from nehad.runtime.images import read_image
from nehad.runtime.ply import read_gaussian_ply, write_gaussian_ply

import stacks
from raster_reference import reference_forward, reference_project
from torch_blocker import blocked_torch_env  # noqa: E402

WIDTH, HEIGHT = 96, 72  # not multiples of 16: partial edge tiles
BACKGROUND = (0.2, 0.4, 0.6)


def _psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _random_cloud(n=300, seed=0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    means = rng.normal(0.0, 0.45, (n, 3))
    means[:4] = [[0.0, 0.0, 2.9], [0.1, 0.0, 2.95], [0.0, 0.1, 3.5], [0.0, 0.0, -3.0]]  # near plane
    q = rng.normal(size=(n, 4))
    sh = np.concatenate([rng.normal(0.0, 0.6, (n, 1, 3)), rng.normal(0.0, 0.25, (n, 3, 3))], 1)
    return GaussianCloud(means=means, scales=np.exp(rng.uniform(np.log(0.01), np.log(0.12), (n, 3))),
                         quats=q / np.linalg.norm(q, axis=1, keepdims=True),
                         opacities=rng.uniform(0.05, 0.95, n), sh=sh)


def _cam_doc(**over) -> dict:
    # OpenGL camera-to-world: camera at z = 3 looking down -z at the origin, slightly off-axis
    doc = {"width": WIDTH, "height": HEIGHT, "fx": 90.0, "fy": 88.0, "cx": 47.0, "cy": 37.5,
           "camera_to_world": [[1, 0, 0, 0.05], [0, 1, 0, -0.1], [0, 0, 1, 3.0], [0, 0, 0, 1]],
           "convention": "opengl"}
    doc.update(over)
    return doc


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A small 3DGS PLY (SH degree 1) and a cam.json looking at it."""
    root = tmp_path_factory.mktemp("cli_scene")
    ply = write_gaussian_ply(root / "cloud.ply", _random_cloud())
    cam = root / "cam.json"
    cam.write_text(json.dumps(_cam_doc()))
    return ply, cam


def _files(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


# ---------------------------------------------------------------------------------------------
# help and version


def test_help_lists_commands_and_flags():
    runner = CliRunner()
    res = runner.invoke(main, ["--help"])
    assert res.exit_code == 0, res.output
    assert "render" in res.output and "synth" in res.output
    res = runner.invoke(main, ["render", "--help"])
    assert res.exit_code == 0, res.output
    for flag in ("--view", "--output", "--depth", "--alpha", "--background", "--size", "--sh-degree"):
        assert flag in res.output
    res = runner.invoke(main, ["synth", "--help"])
    assert res.exit_code == 0
    for flag in ("--scene", "--resolution", "--frames", "--seed", "--fixed-time", "--gaussians"):
        assert flag in res.output
    res = runner.invoke(main, ["--version"])
    assert res.exit_code == 0 and "nehad" in res.output


def test_imports_stay_light_and_torch_free():
    """`nehad --help` loads neither numpy nor numba; nehad, every nehad.runtime module and the CLI
    import without importing torch (checked where torch IS importable, so a guarded import
    would show up too)."""
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        import nehad.cli.main
        heavy = sorted(m for m in ("numpy", "numba", "torch") if m in sys.modules)
        assert not heavy, f"nehad.cli.main imports {heavy} at import time"
        import nehad, nehad.runtime, nehad.cli
        names = []
        for pkg in (nehad.runtime, nehad.cli):
            for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
                importlib.import_module(info.name)
                names.append(info.name)
        assert "nehad.runtime.raster" in names and "nehad.cli.scenes" in names, names
        assert "torch" not in sys.modules, "torch was imported"
        print("ok", len(names))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("ok")


# ---------------------------------------------------------------------------------------------
# synth


def test_synth_writes_layout_and_gaussians(tmp_path):
    out = tmp_path / "demo"
    res = CliRunner().invoke(main, ["synth", str(out), "--resolution", "32", "--frames", "6",
                                    "--gaussians", "1500"])
    assert res.exit_code == 0, res.output
    for split, n in (("train", 6), ("val", 1), ("test", 1)):
        doc = json.loads((out / f"transforms_{split}.json").read_text())
        assert len(doc["frames"]) == n
        assert len(list((out / split).glob("r_*.png"))) == n
    assert (out / "points3d.ply").is_file()
    cloud = read_gaussian_ply(out / "gaussians.ply")
    assert 1400 <= len(cloud) <= 1600 and cloud.sh_degree == 0
    assert "gaussians.ply" in res.output and "nehad render" in res.output
    assert not [p for p in out.rglob(".*")], "temporary files left behind"


def test_synth_without_gaussians_and_bad_scene(tmp_path):
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "s"), "--resolution", "8",
                                    "--frames", "2", "--gaussians", "0"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "s" / "gaussians.ply").exists()
    res = CliRunner().invoke(main, ["synth", str(tmp_path / "t"), "--scene", "cubes"])
    assert res.exit_code != 0 and "--scene" in res.output and "cubes" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "t").exists()


# ---------------------------------------------------------------------------------------------
# render




def test_render_matches_reference_without_torch(scene, tmp_path):
    ply, cam = scene
    out = tmp_path / "render.png"
    env = blocked_torch_env(tmp_path)
    blocked = subprocess.run([sys.executable, "-c", "import torch"], env=env, capture_output=True)
    assert blocked.returncode != 0  # the blocker works
    bg = ",".join(str(v) for v in BACKGROUND)
    proc = stacks.run([sys.executable, "-m", "nehad.cli.main", "render", str(ply), "--view",
                       str(cam), "-o", str(out), "--background", bg], timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    image = read_image(out)
    assert image.shape == (HEIGHT, WIDTH, 3)

    cloud = read_gaussian_ply(ply)
    camera = load_view(cam)
    proj = reference_project(cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh,
                             camera)
    assert (proj[5] > 0).sum() > 200 and (proj[5] == 0).sum() >= 2  # visible ones and culled ones
    rgb, alpha, _, _ = reference_forward(*proj, WIDTH, HEIGHT, BACKGROUND)
    assert 0.15 < alpha.mean() < 0.99  # a real picture, not all background or all saturated
    ours = np.round(image.astype(np.float64) * 255.0)  # the PNG's 8-bit codes
    ref8 = np.round(np.clip(rgb, 0.0, 1.0) * 255.0)
    psnr = _psnr(ours / 255.0, ref8 / 255.0)
    print(f"CLI render vs float64 reference, 8-bit: PSNR {psnr:.1f} dB, "
          f"{int((ours != ref8).sum())} of {ours.size} values differ")
    assert psnr > 50.0, psnr


def test_render_depth_alpha_size_and_sh_degree(scene, tmp_path):
    ply, cam = scene
    runner = CliRunner()
    rgba, depth = tmp_path / "rgba.png", tmp_path / "depth.exr"
    res = runner.invoke(main, ["render", str(ply), "--view", str(cam), "-o", str(rgba), "--alpha",
                               "--depth", str(depth)])
    assert res.exit_code == 0, res.output
    img = read_image(rgba)
    assert img.shape == (HEIGHT, WIDTH, 4)
    d = read_image(depth)[:, :, 0]
    a = img[:, :, 3]
    assert d.shape == (HEIGHT, WIDTH)
    assert (a > 0.5).sum() > 100
    assert np.isfinite(d[a > 0.5]).all() and (d[a > 0.5] > 0.2).all()
    assert np.isfinite(d).all()

    cloud = read_gaussian_ply(ply)
    camera = load_view(cam)
    proj = reference_project(cloud.means, cloud.scales, cloud.quats, cloud.opacities, cloud.sh,
                             camera, sh_degree=0)
    rgb, alpha, ref_depth, amb = reference_forward(*proj, WIDTH, HEIGHT, (0, 0, 0))
    res = runner.invoke(main, ["render", str(ply), "--view", str(cam), "-o",
                               str(tmp_path / "sh0.png"), "--sh-degree", "0"])
    assert res.exit_code == 0, res.output
    assert _psnr(read_image(tmp_path / "sh0.png"), np.round(np.clip(rgb, 0, 1) * 255) / 255) > 50
    ok = (alpha > 0.5) & ~amb
    np.testing.assert_allclose(d[ok], ref_depth[ok], rtol=1e-3, atol=1e-3)

    res = runner.invoke(main, ["render", str(ply), "--view", str(cam), "-o",
                               str(tmp_path / "big.png"), "--size", "48x36"])
    assert res.exit_code == 0, res.output
    assert read_image(tmp_path / "big.png").shape == (36, 48, 3)


def test_render_transforms_frame_syntax(tmp_path):
    """--view accepts file.json:K, and refuses a multi-camera file without an index."""
    out = tmp_path / "demo"
    runner = CliRunner()
    assert runner.invoke(main, ["synth", str(out), "--resolution", "16", "--frames", "20",
                                "--gaussians", "300"]).exit_code == 0
    res = runner.invoke(main, ["render", str(out / "gaussians.ply"), "--view",
                               f"{out / 'transforms_test.json'}:1", "-o", str(tmp_path / "f.png")])
    assert res.exit_code == 0, res.output
    assert read_image(tmp_path / "f.png").shape == (16, 16, 3)
    res = runner.invoke(main, ["render", str(out / "gaussians.ply"), "--view",
                               str(out / "transforms_train.json"), "-o", str(tmp_path / "g.png")])
    assert res.exit_code != 0 and ":0" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "g.png").exists()


# ---------------------------------------------------------------------------------------------
# bad inputs: one line naming the input, non-zero exit, no traceback, nothing written


def _ply_missing_property(src: Path, dst: Path) -> Path:
    data = src.read_bytes()
    assert b"property float opacity\n" in data
    dst.write_bytes(data.replace(b"property float opacity\n", b"property float opacitz\n", 1))
    return dst


def _ply_with_nan(src: Path, dst: Path) -> Path:
    data = bytearray(src.read_bytes())
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    nprops = header.count("property float")
    row = 5
    off = end + (row * nprops + 1) * 4  # property y of vertex 5
    data[off:off + 4] = np.float32(np.nan).tobytes()
    dst.write_bytes(bytes(data))
    return dst


def _bad_inputs(ply: Path, cam: Path, work: Path):
    bad_cam = work / "skewed_cam.json"
    doc = _cam_doc(camera_to_world=[[1.1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
    bad_cam.write_text(json.dumps(doc))
    out = str(work / "out" / "x.png")
    return {
        "missing PLY": ([str(work / "nope.ply"), "--view", str(cam), "-o", out], "nope.ply"),
        "PLY missing a property": (
            [str(_ply_missing_property(ply, work / "noopacity.ply")), "--view", str(cam), "-o", out],
            "opacity"),
        "PLY with NaN": ([str(_ply_with_nan(ply, work / "nan.ply")), "--view", str(cam), "-o", out],
                         "nan.ply"),
        "non-orthonormal camera": ([str(ply), "--view", str(bad_cam), "-o", out],
                                   "skewed_cam.json: camera_to_world"),
        "bad --background": ([str(ply), "--view", str(cam), "-o", out, "--background", "1,2"],
                             "--background"),
        "bad --size": ([str(ply), "--view", str(cam), "-o", out, "--size", "64by64"], "--size"),
        "missing output folder": ([str(ply), "--view", str(cam), "-o",
                                   str(work / "out" / "missing" / "x.png")], "missing"),
        "missing depth folder": ([str(ply), "--view", str(cam), "-o", out, "--depth",
                                  str(work / "nodepth" / "d.exr")], "nodepth"),
    }


def test_bad_inputs_fail_cleanly(scene, tmp_path):
    ply, cam = scene
    (tmp_path / "out").mkdir()
    runner = CliRunner()
    for name, (args, needle) in _bad_inputs(ply, cam, tmp_path).items():
        res = runner.invoke(main, ["render"] + args)
        assert res.exit_code != 0, name
        assert isinstance(res.exception, SystemExit), f"{name}: {res.exception!r}"  # not a crash
        assert "Traceback" not in res.output, name
        assert needle in res.output, f"{name}: {res.output!r}"
        errors = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
        assert len(errors) == 1, f"{name}: {res.output!r}"
        assert _files(tmp_path / "out") == set(), f"{name}: wrote {_files(tmp_path / 'out')}"
    assert not (tmp_path / "nodepth").exists()


def test_bad_input_in_a_real_process(scene, tmp_path):
    """The installed entry point's stderr: one line, no traceback (no CliRunner in between)."""
    _, cam = scene
    proc = stacks.run([sys.executable, "-m", "nehad.cli.main", "render",
                       str(tmp_path / "missing.ply"), "--view", str(cam), "-o",
                       str(tmp_path / "x.png")], timeout=120)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [f"Error: {tmp_path / 'missing.ply'}: no such PLY file"]
    assert not (tmp_path / "x.png").exists()


def test_unsupported_sources(scene, tmp_path):
    _, cam = scene
    runner = CliRunner()
    (tmp_path / "model.onnx").write_bytes(b"")
    for src, needle in ((tmp_path / "model.onnx", "not an ONNX model"),
                        (tmp_path, "not a finished training run"),
                        (tmp_path / "scene.xyz", "no such file")):
        res = runner.invoke(main, ["render", str(src), "--view", str(cam), "-o",
                                   str(tmp_path / "o.png")])
        assert res.exit_code != 0 and needle in res.output and "Traceback" not in res.output
        assert not (tmp_path / "o.png").exists()
