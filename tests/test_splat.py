"""The antimatter15 .splat export (issue 8: viewer interop)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from click.testing import CliRunner

from nehad.cli.main import main
from nehad.runtime.gaussians import SH_C0, GaussianCloud
from nehad.runtime.splat import (ROW_BYTES, SplatError, read_splat, splat_bytes, splat_order,
                                 write_splat)



def _random_cloud(n=500, seed=0, degree=1) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return GaussianCloud(rng.uniform(-2, 2, (n, 3)), np.exp(rng.uniform(-5, -1, (n, 3))), q,
                         rng.uniform(0.01, 0.99, n), rng.normal(0, 1.2, (n, (degree + 1) ** 2, 3)))


def test_layout_matches_the_viewer_byte_for_byte():
    """Two Gaussians written by hand with struct, following antimatter15's PLY converter:
    float32 position and exp'd scale, uint8 (0.5 + C0 dc) * 255 and sigmoid(o) * 255, uint8
    q / |q| * 128 + 128, all rounded and clamped like a Uint8ClampedArray; sorted by
    exp(s0 + s1 + s2) * sigmoid(o), largest first."""
    means = [[1.0, -2.0, 3.5], [0.25, 0.5, -0.75]]
    scales = [[0.01, 0.02, 0.03], [0.1, 0.2, 0.3]]  # the second is 1000x larger
    quats = [[1.0, 0.0, 0.0, 0.0], [0.5, -0.5, 0.5, -0.5]]
    opac = [0.8, 0.2]
    rgb = np.array([[0.2, 0.6, 1.3], [0.5, -0.4, 0.75]])  # 1.3 and -0.4 clamp
    cloud = GaussianCloud(np.array(means), np.array(scales), np.array(quats), np.array(opac),
                          ((rgb - 0.5) / SH_C0)[:, None, :])
    expect = b""
    for i in (1, 0):
        col = [min(255, max(0, round(c * 255))) for c in rgb[i]] + [round(opac[i] * 255)]
        rot = [min(255, max(0, round(q * 128 + 128))) for q in quats[i]]
        expect += struct.pack("<3f3f4B4B", *means[i], *scales[i], *col, *rot)
    data = splat_bytes(cloud)
    assert len(data) == 2 * ROW_BYTES == 64
    assert data == expect
    # (1, 0, 0, 0) -> (255 (clamped from 256), 128, 128, 128)
    assert data[32 + 28:32 + 32] == bytes([255, 128, 128, 128])


def test_base_rgb_is_the_clipped_degree_zero_colour():
    """GaussianCloud.base_rgb against colours written by hand: dc = (rgb - 0.5) / C0 gives rgb
    back, clipped to [0, 1]; the higher SH coefficients do not enter."""
    rgb = np.array([[0.2, 0.6, 1.3], [0.5, -0.4, 0.75]])
    sh = np.zeros((2, 4, 3))
    sh[:, 0, :] = (rgb - 0.5) / SH_C0
    sh[:, 1:, :] = 5.0
    cloud = GaussianCloud(np.zeros((2, 3)), np.ones((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)),
                          np.full(2, 0.5), sh)
    np.testing.assert_allclose(cloud.base_rgb(), [[0.2, 0.6, 1.0], [0.5, 0.0, 0.75]], atol=1e-6)


def test_round_trip(tmp_path):
    cloud = _random_cloud(500)
    path = write_splat(tmp_path / "a.splat", cloud)
    assert path.stat().st_size == 500 * 32
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.splat"]  # no temporary left
    back = read_splat(path)
    order = splat_order(cloud)
    assert back.sh_degree == 0 and len(back) == 500
    np.testing.assert_array_equal(back.means, cloud.means[order])  # float32, exact
    np.testing.assert_array_equal(back.scales, cloud.scales[order])
    np.testing.assert_allclose(back.opacities, cloud.opacities[order], atol=0.5 / 255 + 1e-7)
    rgb = np.clip(0.5 + SH_C0 * cloud.sh[order, 0], 0, 1)
    np.testing.assert_allclose(0.5 + SH_C0 * back.sh[:, 0], rgb, atol=0.5 / 255 + 1e-6)
    q, qb = cloud.quats[order], back.quats
    sign = np.sign((q * qb).sum(1, keepdims=True))
    assert np.abs(q - sign * qb).max() < 0.02  # 8 bits per component
    # sorted: volume x opacity never increases
    imp = np.prod(back.scales.astype(np.float64), 1) * cloud.opacities[order]
    assert (np.diff(imp) <= 0).all()


def test_render_of_the_splat_matches_the_dc_render():
    """What a viewer draws from the file: our rasterizer on the decoded .splat against the same
    Gaussians at SH degree 0 (what .splat keeps)."""
    from nehad.runtime.cameras import Camera
    from nehad.runtime.raster import render

    rng = np.random.default_rng(4)
    n = 800
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cloud = GaussianCloud(rng.normal(0, 0.4, (n, 3)), np.exp(rng.uniform(-4, -2.5, (n, 3))), q,
                          rng.uniform(0.3, 0.95, n), rng.uniform(-1.5, 1.5, (n, 1, 3)))
    w2c = np.eye(4)
    w2c[:3, :3] = np.diag([1.0, -1.0, -1.0])
    w2c[2, 3] = 3.0
    cam = Camera(96, 96, 110.0, 110.0, 48.0, 48.0, w2c)
    tmp = read_splat_bytes(splat_bytes(cloud))
    a = render(cloud, cam, (1, 1, 1)).rgb
    b = render(tmp, cam, (1, 1, 1)).rgb
    mse = float(np.mean((a - b) ** 2))
    assert 10 * np.log10(1 / mse) > 35


def read_splat_bytes(data: bytes) -> GaussianCloud:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.splat"
        p.write_bytes(data)
        return read_splat(p)


def test_bad_inputs(tmp_path):
    cloud = _random_cloud(3)
    cloud.means[1, 0] = np.nan
    with pytest.raises(SplatError, match="means"):
        write_splat(tmp_path / "x.splat", cloud)
    assert not (tmp_path / "x.splat").exists()
    (tmp_path / "t.splat").write_bytes(b"\0" * 33)
    with pytest.raises(SplatError, match="33 bytes"):
        read_splat(tmp_path / "t.splat")
    with pytest.raises(SplatError, match="no such file"):
        read_splat(tmp_path / "none.splat")


def test_cli_ply_writes_splat(tiny_run, tiny_run_model, tmp_path):
    from nehad.model import cloud_at

    data, run = tiny_run
    model, meta = tiny_run_model
    runner = CliRunner()
    res = runner.invoke(main, ["ply", str(run), "--time", "0.25", "-o", str(tmp_path / "f.splat")])
    assert res.exit_code == 0, res.output
    back = read_splat(tmp_path / "f.splat")
    want = cloud_at(model, 0.25, meta.sh_degree)
    np.testing.assert_allclose(back.means, want.means[splat_order(want)], rtol=0, atol=1e-6)
    res = runner.invoke(main, ["ply", str(run), "--frames", "3", "--format", "splat", "-o",
                               str(tmp_path / "seq")])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "seq").iterdir())
    assert names == ["frame_0000.splat", "frame_0001.splat", "frame_0002.splat"]
    assert (tmp_path / "seq" / "frame_0001.splat").stat().st_size == 32 * len(want)
    # the PLY path is unchanged
    res = runner.invoke(main, ["ply", str(run), "--time", "0.25", "-o", str(tmp_path / "f.ply")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["ply", str(run), "--time", "0.25", "--format", "splat", "-o",
                               str(tmp_path / "g.ply")])
    assert res.exit_code != 0 and "must end in .splat" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "g.ply").exists()
