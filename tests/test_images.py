"""Image I/O by extension: to_uint8 rounding, OpenImageIO round trips, atomic writes, errors."""

from __future__ import annotations

import os
import sys

import numpy as np
import OpenImageIO as oiio
import pytest
from PIL import Image

from rtjax.errors import ImageError
from rtjax.images import load_image, load_image_uint8, save_image, to_uint8
from rtjax.sunraster import encode_sunraster, read_sunraster


def random_image(h: int = 5, w: int = 7, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


# ---- to_uint8 --------------------------------------------------------------------------


def test_to_uint8_rounds_half_up_and_clamps():
    values = np.array([0.49, 0.5, 1.5, 2.5, 127.499, 254.5, 255.4, 300.0, -3.0], np.float32)
    image = np.repeat(values[None, :, None], 3, axis=2)
    got = to_uint8(image)
    assert got.dtype == np.uint8 and got.shape == (1, 9, 3)
    assert got[0, :, 0].tolist() == [0, 1, 2, 3, 127, 255, 255, 255, 0]


def test_to_uint8_passes_uint8_through_and_takes_integers():
    img = random_image()
    assert np.array_equal(to_uint8(img), img)
    assert np.array_equal(to_uint8(img.astype(np.int64)), img)


def test_to_uint8_takes_jax_arrays():
    jnp = pytest.importorskip("jax.numpy")
    assert to_uint8(jnp.full((2, 3, 3), 10.6))[0, 0].tolist() == [11, 11, 11]


def test_to_uint8_rejects_non_finite():
    image = np.zeros((2, 2, 3))
    image[0, 0, 0], image[1, 1, 2] = np.nan, np.inf
    with pytest.raises(ImageError, match="^image has 2 non-finite values$"):
        to_uint8(image)


@pytest.mark.parametrize("shape", [(4, 4), (4, 4, 4), (0, 4, 3), (4, 4, 3, 1)])
def test_to_uint8_rejects_shapes(shape):
    with pytest.raises(ImageError, match="shape"):
        to_uint8(np.zeros(shape))


# ---- round trips -----------------------------------------------------------------------


@pytest.mark.parametrize("ext", [".png", ".tif", ".exr", ".ras", ".sunimg", ".bmp"])
def test_lossless_round_trip(tmp_path, ext):
    img = random_image(5, 7)
    path = tmp_path / ("img" + ext)
    save_image(path, img.astype(np.float32) + 0.3)  # floats round to the same levels
    got = load_image(path)
    assert got.dtype == np.float32 and got.shape == (5, 7, 3)
    assert np.array_equal(got, img)
    assert np.array_equal(load_image_uint8(path), img)
    assert sorted(os.listdir(tmp_path)) == ["img" + ext]


def test_png_agrees_with_pillow(tmp_path):
    img = random_image(3, 5, seed=1)
    save_image(tmp_path / "a.png", img)
    with Image.open(tmp_path / "a.png") as im:
        assert im.mode == "RGB"
        assert np.array_equal(np.asarray(im), img)
    Image.fromarray(img[:, ::-1]).save(tmp_path / "b.png")
    assert np.array_equal(load_image(tmp_path / "b.png"), img[:, ::-1])


def test_exr_stores_levels_over_255(tmp_path):
    img = random_image(2, 3, seed=2)
    save_image(tmp_path / "a.exr", img)
    inp = oiio.ImageInput.open(str(tmp_path / "a.exr"))
    raw = inp.read_image(0, 0, 0, 3, "float")
    inp.close()
    assert np.allclose(raw, img / 255.0, atol=1e-6)


def test_jpeg_is_close(tmp_path):
    img = np.full((8, 8, 3), (200, 40, 90), np.uint8)
    save_image(tmp_path / "a.jpg", img)
    assert np.abs(load_image(tmp_path / "a.jpg") - img).max() <= 6


def test_sun_raster_via_save_image_is_standard_order(tmp_path):
    img = random_image(3, 5, seed=3)
    save_image(tmp_path / "a.ras", img)
    with Image.open(tmp_path / "a.ras") as im:
        assert np.array_equal(np.asarray(im.convert("RGB")), img)
    save_image(tmp_path / "b.ras", img, assignment_order=True)
    assert np.array_equal(load_image(tmp_path / "b.ras"), img[:, :, ::-1])
    assert np.array_equal(load_image(tmp_path / "b.ras", assignment_order=True), img)


def test_sun_raster_found_by_magic_whatever_the_extension(tmp_path):
    img = random_image(2, 2, seed=4)
    (tmp_path / "texture.bin").write_bytes(encode_sunraster(img))
    assert np.array_equal(load_image(tmp_path / "texture.bin"), img)


def test_grey_alpha_and_16_bit(tmp_path):
    grey = (np.arange(12, dtype=np.uint8) * 20).reshape(3, 4)
    Image.fromarray(grey).save(tmp_path / "g.png")
    assert np.array_equal(load_image(tmp_path / "g.png"), np.repeat(grey[:, :, None], 3, axis=2))
    rgba = np.dstack([random_image(3, 4, seed=5), np.full((3, 4), 7, np.uint8)])
    Image.fromarray(rgba).save(tmp_path / "a.png")
    assert np.array_equal(load_image(tmp_path / "a.png"), rgba[:, :, :3])
    deep = (np.arange(36, dtype=np.uint16) * 1800).reshape(3, 4, 3)
    out = oiio.ImageOutput.create(str(tmp_path / "d.png"))
    assert out.open(str(tmp_path / "d.png"), oiio.ImageSpec(4, 3, 3, "uint16")) and out.write_image(deep) and out.close()
    assert np.allclose(load_image(tmp_path / "d.png"), deep / 257.0, atol=1e-4)


def test_hdr_values_are_clamped_to_255(tmp_path):
    out = oiio.ImageOutput.create(str(tmp_path / "h.exr"))
    assert out.open(str(tmp_path / "h.exr"), oiio.ImageSpec(1, 1, 3, "float"))
    assert out.write_image(np.array([[[2.0, 0.5, -1.0]]], np.float32)) and out.close()
    assert load_image(tmp_path / "h.exr").tolist() == [[[255.0, 127.5, 0.0]]]


# ---- errors ----------------------------------------------------------------------------


def test_missing_and_unreadable_files_name_the_path(tmp_path):
    with pytest.raises(ImageError, match=r"nope\.png: cannot read: No such file"):
        load_image(tmp_path / "nope.png")
    (tmp_path / "junk.png").write_bytes(b"hello, not a png")
    with pytest.raises(ImageError, match=r"junk\.png: cannot read: "):
        load_image(tmp_path / "junk.png")
    save_image(tmp_path / "good.png", random_image(20, 20))
    (tmp_path / "cut.png").write_bytes((tmp_path / "good.png").read_bytes()[:80])
    with pytest.raises(ImageError, match=r"cut\.png: cannot read: "):
        load_image(tmp_path / "cut.png")
    (tmp_path / "cut.ras").write_bytes(encode_sunraster(random_image(4, 4))[:50])
    with pytest.raises(ImageError, match=r"cut\.ras: truncated"):
        load_image(tmp_path / "cut.ras")


def test_unknown_extension_writes_nothing(tmp_path):
    with pytest.raises(ImageError, match=r"out\.xyz: cannot write: .*format writer"):
        save_image(tmp_path / "out.xyz", random_image())
    assert os.listdir(tmp_path) == []


def test_missing_folder(tmp_path):
    with pytest.raises(ImageError, match=r"out\.png: cannot write"):
        save_image(tmp_path / "no" / "out.png", random_image())


def fake_oiio(image_output: type) -> object:
    """An OpenImageIO stand-in with its own ImageOutput, the rest the real module's."""
    fake = type(sys)("OpenImageIO")
    fake.ImageOutput = image_output
    fake.__getattr__ = lambda name: getattr(oiio, name)
    return fake


class _FailingOutput:
    """Wraps a real ImageOutput; writes part of the image, then fails."""

    def __init__(self, real, exc: type[BaseException]):
        self.real, self.exc = real, exc

    def open(self, name, spec):
        return self.real.open(name, spec)

    def write_image(self, data):
        self.real.write_scanline(0, 0, np.ascontiguousarray(data[0]))
        raise self.exc("disk on fire")

    def close(self):
        return self.real.close()

    def geterror(self):
        return self.real.geterror()


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_failed_oiio_write_keeps_old_file(tmp_path, monkeypatch, exc):
    path = tmp_path / "render.png"
    old = random_image(4, 4, seed=6)
    save_image(path, old)
    before = path.read_bytes()

    real_create = oiio.ImageOutput.create

    class FakeImageOutput:
        @staticmethod
        def create(name):
            return _FailingOutput(real_create(name), exc)

    monkeypatch.setitem(sys.modules, "OpenImageIO", fake_oiio(FakeImageOutput))
    with pytest.raises(exc):
        save_image(path, random_image(4, 4, seed=7))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["render.png"]


def test_oiio_refusal_is_an_image_error(tmp_path, monkeypatch):
    path = tmp_path / "render.tif"
    real_create = oiio.ImageOutput.create

    class Refusing(_FailingOutput):
        def write_image(self, data):
            return False

        def geterror(self):
            return "no space left\non device"

    class FakeImageOutput:
        @staticmethod
        def create(name):
            return Refusing(real_create(name), RuntimeError)

    monkeypatch.setitem(sys.modules, "OpenImageIO", fake_oiio(FakeImageOutput))
    with pytest.raises(ImageError, match=r"render\.tif: cannot write: no space left; on device$"):
        save_image(path, random_image())
    assert os.listdir(tmp_path) == []


def test_failed_sun_raster_write_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "render.ras"
    old = random_image(4, 4, seed=8)
    save_image(path, old)

    def boom(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(ImageError, match=r"render\.ras: cannot write: No space left on device"):
        save_image(path, random_image(4, 4, seed=9))
    monkeypatch.undo()
    assert np.array_equal(read_sunraster(path), old)
    assert os.listdir(tmp_path) == ["render.ras"]
