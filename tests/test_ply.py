"""The 3DGS Gaussian PLY (INRIA layout, docs/design.md sections 3 and 7)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nehad.runtime.gaussians import GaussianCloud
from nehad.runtime.ply import PlyError, ply_property_names, read_gaussian_ply, write_gaussian_ply


def _random_cloud(n, degree, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return GaussianCloud(means=rng.normal(size=(n, 3)) * 3,
                         scales=np.exp(rng.normal(-3, 1, size=(n, 3))),
                         quats=q / np.linalg.norm(q, axis=1, keepdims=True),
                         opacities=rng.uniform(0.001, 0.999, size=n),
                         sh=rng.normal(size=(n, (degree + 1) ** 2, 3)))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_roundtrip(tmp_path, degree):
    cloud = _random_cloud(500, degree, seed=degree)
    path = write_gaussian_ply(tmp_path / "pc.ply", cloud)
    back = read_gaussian_ply(path)
    assert len(back) == 500 and back.sh_degree == degree
    np.testing.assert_array_equal(back.means, cloud.means)
    np.testing.assert_array_equal(back.sh, cloud.sh)
    np.testing.assert_allclose(back.scales, cloud.scales, rtol=1e-6)
    np.testing.assert_allclose(back.opacities, cloud.opacities, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(back.quats, cloud.quats, rtol=0, atol=2e-7)
    assert [p.name for p in tmp_path.iterdir()] == ["pc.ply"]  # no temp file left
    # the layout is the INRIA one, byte for byte in the header
    head = path.read_bytes()[:4000].split(b"end_header\n")[0].decode().splitlines()
    props = [ln.split()[2] for ln in head if ln.startswith("property float")]
    assert props == ply_property_names(degree)
    assert head[1] == "format binary_little_endian 1.0"


def test_f_rest_channel_major_layout(tmp_path):
    # sh[:, k, c] must land in f_rest_{c*(K-1) + k-1}
    cloud = _random_cloud(2, 3)
    sh = np.zeros((2, 16, 3), np.float32)
    for k in range(1, 16):
        for c in range(3):
            sh[:, k, c] = 100 * c + k
    cloud.sh = sh
    path = write_gaussian_ply(tmp_path / "a.ply", cloud)
    raw = path.read_bytes()
    body = np.frombuffer(raw[raw.index(b"end_header\n") + 11:], dtype="<f4").reshape(2, -1)
    names = ply_property_names(3)
    for k in range(1, 16):
        for c in range(3):
            assert body[0, names.index(f"f_rest_{c * 15 + k - 1}")] == 100 * c + k


def test_extreme_values_stay_finite(tmp_path):
    cloud = _random_cloud(4, 0)
    cloud.opacities[:] = [0.0, 1.0, 1e-30, 0.5]
    cloud.scales[0] = 0.0
    back = read_gaussian_ply(write_gaussian_ply(tmp_path / "x.ply", cloud))
    assert back.opacities[0] < 1e-14 and back.opacities[1] == 1.0 and back.opacities[3] == 0.5
    assert 0 < back.scales[0, 0] < 1e-29


ASCII = """ply
format ascii 1.0
comment hand-written: values chosen so the activations are known
element vertex 2
property float opacity
property double x
property float y
property float z
property float nx
property float rot_0
property float rot_1
property float rot_2
property float rot_3
property float scale_0
property float scale_1
property float scale_2
property float f_dc_0
property float f_dc_1
property float f_dc_2
property uchar red
end_header
0 1 2 3 0 2 0 0 0 0 0.69314718 -2.30258509 0.5 -0.5 0.25 7
2.19722458 -1 -2 -3 0 0 0 3 4 1 1 1 0 0 0 255
"""


def test_ascii_known_values(tmp_path):
    p = tmp_path / "tiny.ply"
    p.write_text(ASCII)
    c = read_gaussian_ply(p)
    np.testing.assert_allclose(c.means, [[1, 2, 3], [-1, -2, -3]])
    np.testing.assert_allclose(c.opacities, [0.5, 0.9], rtol=1e-6)
    np.testing.assert_allclose(c.scales, [[1, 2, 0.1], [math.e] * 3], rtol=1e-6)
    np.testing.assert_allclose(c.quats, [[1, 0, 0, 0], [0, 0, 0.6, 0.8]], atol=1e-7)
    assert c.sh.shape == (2, 1, 3)
    np.testing.assert_allclose(c.sh[0, 0], [0.5, -0.5, 0.25])


def _header(props, n=1, fmt="binary_little_endian"):
    return ("ply\nformat %s 1.0\nelement vertex %d\n" % (fmt, n)
            + "".join(f"property float {p}\n" for p in props) + "end_header\n").encode()


def _binary(tmp_path, values=None, props=None, n=3, name="b.ply", cut=0):
    props = props or ply_property_names(1)
    data = np.ones((n, len(props)), "<f4") if values is None else values
    raw = _header(props, n) + data.astype("<f4").tobytes()
    p = tmp_path / name
    p.write_bytes(raw[:len(raw) - cut])
    return p


def test_big_endian_and_float64(tmp_path):
    cloud = _random_cloud(10, 1)
    ref = read_gaussian_ply(write_gaussian_ply(tmp_path / "le.ply", cloud))
    raw = (tmp_path / "le.ply").read_bytes()
    i = raw.index(b"end_header\n") + 11
    body = np.frombuffer(raw[i:], "<f4").reshape(10, -1)
    (tmp_path / "be.ply").write_bytes(raw[:i].replace(b"binary_little_endian", b"binary_big_endian")
                                      + body.astype(">f4").tobytes())
    (tmp_path / "f8.ply").write_bytes(raw[:i].replace(b"property float ", b"property double ")
                                      + body.astype("<f8").tobytes())
    for name in ("be.ply", "f8.ply"):
        c = read_gaussian_ply(tmp_path / name)
        for f in ("means", "scales", "quats", "opacities", "sh"):
            np.testing.assert_array_equal(getattr(c, f), getattr(ref, f))


def test_not_a_ply(tmp_path):
    p = tmp_path / "x.ply"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(PlyError, match="not a PLY"):
        read_gaussian_ply(p)
    with pytest.raises(PlyError, match="no such PLY file"):
        read_gaussian_ply(tmp_path / "absent.ply")


def test_missing_properties_listed(tmp_path):
    props = [p for p in ply_property_names(0) if p not in ("opacity", "rot_3")]
    p = _binary(tmp_path, props=props)
    with pytest.raises(PlyError, match=r"missing vertex properties: opacity rot_3"):
        read_gaussian_ply(p)


def test_f_rest_count(tmp_path):
    props = ply_property_names(0) + [f"f_rest_{i}" for i in range(10)]
    with pytest.raises(PlyError, match="10 f_rest properties"):
        read_gaussian_ply(_binary(tmp_path, props=props))
    props = ply_property_names(0) + [f"f_rest_{i}" for i in range(10) if i != 4]
    with pytest.raises(PlyError, match="missing f_rest_4"):
        read_gaussian_ply(_binary(tmp_path, props=props))


def test_non_finite_named(tmp_path):
    props = ply_property_names(1)
    vals = np.ones((5, len(props)), "<f4")
    vals[1, props.index("scale_1")] = np.nan
    vals[[0, 3], props.index("f_rest_2")] = np.inf
    vals[:, props.index("nx")] = np.nan  # ignored property: not an error
    with pytest.raises(PlyError, match=r"NaN or infinite values in f_rest_2 \(2\), scale_1 \(1\)"):
        read_gaussian_ply(_binary(tmp_path, values=vals, props=props, n=5))
    p = tmp_path / "nan.ply"
    p.write_text(ASCII.replace("0.69314718", "nan"))
    with pytest.raises(PlyError, match=r"scale_1 \(1\)"):
        read_gaussian_ply(p)


def test_truncated(tmp_path):
    with pytest.raises(PlyError, match="truncated"):
        read_gaussian_ply(_binary(tmp_path, n=3, cut=5))
    p = tmp_path / "t.ply"
    p.write_text(ASCII.rsplit("\n", 2)[0] + "\n")
    with pytest.raises(PlyError, match="truncated"):
        read_gaussian_ply(p)


def test_zero_quaternion(tmp_path):
    props = ply_property_names(0)
    vals = np.ones((4, len(props)), "<f4")
    vals[2, props.index("rot_0"):props.index("rot_3") + 1] = 0
    with pytest.raises(PlyError, match="rot_0..rot_3: 1 Gaussians have a zero-norm quaternion"):
        read_gaussian_ply(_binary(tmp_path, values=vals, props=props, n=4))


def test_other_header_errors(tmp_path):
    p = tmp_path / "h.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement face 1\n"
                  b"property list uchar int vertex_indices\nend_header\n")
    with pytest.raises(PlyError, match="no 'vertex' element"):
        read_gaussian_ply(p)
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n")
    with pytest.raises(PlyError, match="end_header"):
        read_gaussian_ply(p)
    p.write_bytes(b"ply\nformat binary_middle_endian 1.0\nend_header\n")
    with pytest.raises(PlyError, match="unknown PLY format"):
        read_gaussian_ply(p)


def test_write_refuses_invalid(tmp_path):
    cloud = _random_cloud(3, 0)
    cloud.means[1, 2] = np.nan
    with pytest.raises(PlyError, match="means holds 1 NaN"):
        write_gaussian_ply(tmp_path / "w.ply", cloud)
    cloud = _random_cloud(3, 0)
    cloud.quats[0] = 0
    with pytest.raises(PlyError, match="zero-norm"):
        write_gaussian_ply(tmp_path / "w.ply", cloud)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(PlyError, match="does not exist"):
        write_gaussian_ply(tmp_path / "no" / "w.ply", _random_cloud(3, 0))
