"""Image I/O through OpenImageIO, atomic writes (docs/design.md section 10)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from nehad.runtime import images
from nehad.runtime.images import ImageError, atomic_path, read_image, write_image


def _img(h=13, w=17, c=3, seed=0):
    return np.random.default_rng(seed).uniform(size=(h, w, c)).astype(np.float32)


@pytest.mark.parametrize("bits,c", [(8, 3), (8, 4), (16, 3), (16, 1)])
def test_png_roundtrip(tmp_path, bits, c):
    img = _img(c=c)
    if c == 4:  # associated alpha in memory (OpenImageIO's convention): colour <= alpha
        img[..., 3] = np.maximum(img[..., 3], 0.2)
        img[..., :3] *= img[..., 3:]
    p = write_image(tmp_path / "a.png", img, bit_depth=bits)
    back = read_image(p)
    assert back.shape == img.shape and back.dtype == np.float32
    q = 255.0 if bits == 8 else 65535.0
    if c == 4:  # stored straight (colour / alpha), premultiplied again on reading
        a = img[..., 3:]
        assert np.abs(back - img)[..., 3].max() <= 0.5 / q + 1e-7
        assert (np.abs(back - img)[..., :3] <= 0.5 / q * a + 0.5 / q + 1e-6).all()
        return
    assert np.abs(back - img).max() <= 0.5 / q + 1e-7
    np.testing.assert_allclose(back * q, np.round(img * q), atol=1e-3)  # exactly the quantised values


def test_straight_alpha_png_reads_premultiplied(tmp_path):
    import OpenImageIO as oiio

    # a straight-alpha RGBA PNG as Blender/D-NeRF write it
    p = str(tmp_path / "s.png")
    px = np.array([[[153, 102, 51, 128], [255, 255, 255, 0]]], np.uint8)
    out = oiio.ImageOutput.create(p)
    spec = oiio.ImageSpec(2, 1, 4, "uint8")
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out.open(p, spec)
    out.write_image(px)
    out.close()
    back = read_image(p)
    a = 128 / 255  # premultiplied in float, not rounded again to 8 bits
    np.testing.assert_allclose(back[0, 0], [0.6 * a, 0.4 * a, 0.2 * a, a], atol=1e-6)
    np.testing.assert_allclose(back[0, 1], [0, 0, 0, 0], atol=1e-7)


def test_png_clips_and_handles_nan(tmp_path):
    img = np.array([[[-1.0, 2.0, np.nan]]], np.float32)
    back = read_image(write_image(tmp_path / "c.png", img))
    np.testing.assert_array_equal(back, [[[0.0, 1.0, 0.0]]])


def test_grayscale_2d_input(tmp_path):
    img = _img(c=1)[:, :, 0]
    back = read_image(write_image(tmp_path / "g.png", img))
    assert back.shape == (13, 17, 1)


def test_exr_float_exact(tmp_path):
    img = _img(c=3) * 100 - 20  # outside [0, 1], negative: linear values / depth as stored
    img[0, 0, 0] = 1e-20
    back = read_image(write_image(tmp_path / "d.exr", img))
    np.testing.assert_array_equal(back, img)
    depth = _img(c=1)[:, :, 0] * 5
    np.testing.assert_array_equal(read_image(write_image(tmp_path / "z.exr", depth))[:, :, 0], depth)


def test_jpeg(tmp_path):
    img = np.full((16, 16, 3), 0.5, np.float32)
    back = read_image(write_image(tmp_path / "j.jpg", img))
    assert back.shape == (16, 16, 3) and np.abs(back - 0.5).max() < 0.02
    with pytest.raises(ImageError, match="bit depth 16"):
        write_image(tmp_path / "j16.jpg", img, bit_depth=16)


def test_permissions_follow_umask(tmp_path):
    p = write_image(tmp_path / "p.png", _img())
    mask = os.umask(0o022)
    os.umask(mask)
    assert os.stat(p).st_mode & 0o777 == 0o666 & ~mask


def test_missing_folder_names_path(tmp_path):
    target = tmp_path / "nope" / "x.png"
    with pytest.raises(ImageError, match=str(target)):
        write_image(target, _img())
    with pytest.raises(ImageError, match="no such image file"):
        read_image(tmp_path / "absent.png")


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    class Boom(Exception):
        pass

    real_create = oiio.ImageOutput.create

    class Failing:
        def __init__(self, out):
            self.out = out

        def __getattr__(self, name):
            return getattr(self.out, name)

        def write_image(self, data):
            raise Boom("crash in the middle of a write")

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda p: Failing(real_create(p))))
    with pytest.raises(Boom):
        write_image(tmp_path / "f.png", _img())
    assert list(tmp_path.iterdir()) == []
    # an existing file is left untouched by a failed overwrite
    monkeypatch.undo()
    good = write_image(tmp_path / "f.png", _img(seed=1))
    before = good.read_bytes()
    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda p: Failing(real_create(p))))
    with pytest.raises(Boom):
        write_image(good, _img(seed=2))
    assert good.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["f.png"]


def test_unknown_format_and_bad_shape(tmp_path):
    with pytest.raises(ImageError, match="no writer"):
        write_image(tmp_path / "x.unknownfmt", _img())
    with pytest.raises(ImageError, match="shape"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 2, 2)))
    with pytest.raises(ImageError, match="5 channels"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 5)))
    assert list(tmp_path.iterdir()) == []


def test_corrupt_file(tmp_path):
    p = tmp_path / "bad.png"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ImageError, match="bad.png"):
        read_image(p)


def test_atomic_path_helper(tmp_path):
    target = tmp_path / "out.bin"
    with atomic_path(target) as tmp:
        assert os.path.dirname(tmp) == str(tmp_path) and tmp.endswith(".bin")
        with open(tmp, "wb") as f:
            f.write(b"abc")
        assert not target.exists()
    assert target.read_bytes() == b"abc"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            with open(tmp, "wb") as f:
                f.write(b"half")
            raise RuntimeError("crash")
    assert target.read_bytes() == b"abc" and [p.name for p in tmp_path.iterdir()] == ["out.bin"]
    assert images._UMASK == (lambda m: (os.umask(m), m)[1])(os.umask(0o022))
