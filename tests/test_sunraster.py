"""Sun raster codec: Pillow agrees with what we write; hand-built files decode as expected."""

from __future__ import annotations

import os
import re
import struct
import time
import tracemalloc

import numpy as np
import pytest
from PIL import Image

from rtjax.errors import ImageError
from rtjax.sunraster import (
    SUN_EXTENSIONS,
    decode_sunraster,
    encode_sunraster,
    is_sunraster_path,
    read_sunraster,
    write_sunraster,
)

MAGIC = 0x59A66A95


def header(w: int, h: int, depth: int, length: int, rtype: int = 1, maptype: int = 0, maplength: int = 0, magic: int = MAGIC) -> bytes:
    return struct.pack(">8I", magic, w, h, depth, length, rtype, maptype, maplength)


def random_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def scene_like(h: int = 294, w: int = 400) -> np.ndarray:
    """A dark-blue background (the sample deck's `back 0 0 128`) with a yellow disc."""
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = (0, 0, 128)
    yy, xx = np.mgrid[:h, :w]
    img[(yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (h / 4) ** 2] = (230, 220, 10)
    return img


def pil_rgb(path: str) -> np.ndarray:
    # formats=["SUN"]: Pillow's sniffer takes a 1-pixel-wide Sun raster for a GIMP brush
    # (magic, then width 1 reads as brush version 1)
    with Image.open(path, formats=["SUN"]) as im:
        return np.asarray(im.convert("RGB"))


def rle_reference(encoded: bytes) -> bytes:
    """A plain, obviously correct RLE expander to check the vectorised one against."""
    out, i = bytearray(), 0
    while i < len(encoded):
        b = encoded[i]
        if b != 0x80:
            out.append(b)
            i += 1
        elif encoded[i + 1] == 0:
            out.append(0x80)
            i += 2
        else:
            out += bytes([encoded[i + 2]]) * (encoded[i + 1] + 1)
            i += 3
    return bytes(out)


# ---- writing ---------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(3, 5), (294, 400), (1, 1), (2, 7)])
def test_pillow_reads_what_we_write(tmp_path, shape):
    h, w = shape
    img = scene_like(h, w) if shape == (294, 400) else random_image(h, w)
    path = tmp_path / "out.ras"
    write_sunraster(path, img)
    assert np.array_equal(pil_rgb(str(path)), img)
    assert np.array_equal(read_sunraster(path), img)


def test_dark_blue_background_is_blue_for_pillow(tmp_path):
    path = tmp_path / "ex2s3.sunimg"
    write_sunraster(path, scene_like())
    assert tuple(pil_rgb(str(path))[0, 0]) == (0, 0, 128)
    raw = path.read_bytes()
    assert raw[32:35] == bytes([128, 0, 0])  # stored B, G, R


def test_header_fields_odd_width():
    img = random_image(3, 5)
    data = encode_sunraster(img)
    magic, w, h, depth, length, rtype, maptype, maplength = struct.unpack(">8I", data[:32])
    assert (magic, w, h, depth, rtype, maptype, maplength) == (MAGIC, 5, 3, 24, 1, 0, 0)
    assert length == 16 * 3  # 15 bytes per row padded to 16
    assert len(data) == 32 + length
    rows = np.frombuffer(data[32:], np.uint8).reshape(3, 16)
    assert np.all(rows[:, 15] == 0)
    assert np.array_equal(rows[:, :15].reshape(3, 5, 3), img[:, :, ::-1])


def test_header_length_even_width_matches_assignment():
    data = encode_sunraster(np.zeros((294, 400, 3), np.uint8))
    assert struct.unpack(">I", data[16:20])[0] == 3 * 400 * 294
    assert len(data) == 32 + 3 * 400 * 294


def test_assignment_order_bytes():
    img = np.array([[[10, 20, 30]]], np.uint8)
    assert encode_sunraster(img)[32:35] == bytes([30, 20, 10])
    assert encode_sunraster(img, assignment_order=True)[32:35] == bytes([10, 20, 30])


@pytest.mark.parametrize("order", [False, True])
def test_round_trip(order):
    img = random_image(7, 9, seed=3)
    assert np.array_equal(decode_sunraster(encode_sunraster(img, assignment_order=order), assignment_order=order), img)


def test_assignment_file_read_in_standard_order_swaps_red_and_blue(tmp_path):
    img = random_image(4, 5, seed=4)
    write_sunraster(tmp_path / "a.ras", img, assignment_order=True)
    assert np.array_equal(read_sunraster(tmp_path / "a.ras"), img[:, :, ::-1])
    assert np.array_equal(pil_rgb(str(tmp_path / "a.ras")), img[:, :, ::-1])
    assert np.array_equal(read_sunraster(tmp_path / "a.ras", assignment_order=True), img)


@pytest.mark.parametrize("bad", [np.zeros((2, 2, 3), np.float32), np.zeros((2, 2), np.uint8), np.zeros((2, 2, 4), np.uint8), np.zeros((0, 2, 3), np.uint8)])
def test_encode_rejects_bad_arrays(bad):
    with pytest.raises(ImageError):
        encode_sunraster(bad)


# ---- reading hand-built files -----------------------------------------------------------


def test_type1_depth24_odd_width_with_padding():
    # 3x2, rows of 9 bytes padded to 10, pixels B,G,R
    rows = bytes([1, 2, 3, 4, 5, 6, 7, 8, 9, 0xEE, 11, 12, 13, 14, 15, 16, 17, 18, 19, 0xEE])
    got = decode_sunraster(header(3, 2, 24, 20) + rows)
    want = np.array([[[3, 2, 1], [6, 5, 4], [9, 8, 7]], [[13, 12, 11], [16, 15, 14], [19, 18, 17]]], np.uint8)
    assert got.dtype == np.uint8 and np.array_equal(got, want)
    assert np.array_equal(decode_sunraster(header(3, 2, 24, 20) + rows, assignment_order=True), want[:, :, ::-1])


def test_type1_depth32_xbgr():
    rows = bytes([0, 1, 2, 3, 0xFF, 4, 5, 6])  # X B G R, two pixels, 8 bytes (even)
    got = decode_sunraster(header(2, 1, 32, 8) + rows)
    assert np.array_equal(got, [[[3, 2, 1], [6, 5, 4]]])
    assert np.array_equal(decode_sunraster(header(2, 1, 32, 8) + rows, assignment_order=True), [[[1, 2, 3], [4, 5, 6]]])


@pytest.mark.parametrize("order", [False, True])
def test_type3_rgb_and_xrgb(order):
    assert np.array_equal(decode_sunraster(header(1, 1, 24, 4, rtype=3) + bytes([1, 2, 3, 0]), assignment_order=order), [[[1, 2, 3]]])
    assert np.array_equal(decode_sunraster(header(1, 1, 32, 4, rtype=3) + bytes([9, 1, 2, 3]), assignment_order=order), [[[1, 2, 3]]])


def test_type2_rle_escape_and_runs():
    # decoded rows (2x2, 6 bytes each): 80 10 20 07 07 07 | 07 07 07 07 80 80
    encoded = bytes([0x80, 0x00, 0x10, 0x20, 0x80, 0x06, 0x07, 0x80, 0x01, 0x80])
    want = np.array([[[0x20, 0x10, 0x80], [7, 7, 7]], [[7, 7, 7], [0x80, 0x80, 7]]], np.uint8)
    for length in (len(encoded), 0):  # length 0: the rest of the file
        assert np.array_equal(decode_sunraster(header(2, 2, 24, length, rtype=2) + encoded), want)
    assert np.array_equal(decode_sunraster(header(2, 2, 24, 0, rtype=2) + encoded, assignment_order=True), want[:, :, ::-1])


def test_type2_rle_padding_applies_to_decoded_rows():
    # 1x2 image, rows of 3 bytes padded to 4: one run covers row 0 and its pad byte.
    # (DECK.md §5, as netpbm and ImageMagick do; Pillow 13 ignores the padding for RLE.)
    encoded = bytes([0x80, 0x03, 0x40, 0x01, 0x02, 0x03, 0x00])
    data = header(1, 2, 24, len(encoded), rtype=2) + encoded
    want = np.array([[[0x40, 0x40, 0x40]], [[3, 2, 1]]], np.uint8)
    assert np.array_equal(decode_sunraster(data), want)


def test_type2_rle_agrees_with_pillow_on_even_rows(tmp_path):
    encoded = bytes([0x80, 0x00, 0x10, 0x20, 0x80, 0x06, 0x07, 0x80, 0x01, 0x80])
    data = header(2, 2, 24, len(encoded), rtype=2) + encoded
    (tmp_path / "rle.ras").write_bytes(data)
    assert np.array_equal(pil_rgb(str(tmp_path / "rle.ras")), decode_sunraster(data))


def test_type2_rle_matches_reference_on_random_streams():
    rng = np.random.default_rng(7)
    for _ in range(200):
        tokens = []
        for _ in range(rng.integers(1, 40)):
            kind = rng.integers(4)
            if kind == 0:
                tokens.append(bytes([0x80, 0x00]))
            elif kind == 1:
                tokens.append(bytes([0x80, int(rng.integers(1, 256)), int(rng.choice([0x80, 0x00, int(rng.integers(256))]))]))
            else:
                tokens.append(bytes([int(b) for b in rng.integers(0, 256, rng.integers(1, 5)) if b != 0x80]))
        encoded = b"".join(tokens)
        decoded = rle_reference(encoded)
        if len(decoded) % 4 or not decoded:
            continue
        w = len(decoded) // 4  # depth 32, one row of w pixels
        got = decode_sunraster(header(w, 1, 32, len(encoded), rtype=2) + encoded)
        assert np.array_equal(got, np.frombuffer(decoded, np.uint8).reshape(1, w, 4)[:, :, :0:-1])


def rle_encode(raw: bytes) -> bytes:
    """Runs of 3..256 equal bytes become 0x80 n v, a lone 0x80 becomes 0x80 0x00."""

    def token(m: re.Match) -> bytes:
        run = m.group(0)
        return bytes([0x80, len(run) - 1, run[0]]) if len(run) > 1 else b"\x80\x00"

    return re.sub(rb"(.)\1{2,255}|\x80", token, raw, flags=re.DOTALL)


def test_rle_encode_helper_is_right():
    raw = bytes([1, 1, 1, 1, 0x80, 2, 0x80, 0x80, 0x80]) + bytes(600)
    assert rle_reference(rle_encode(raw)) == raw


def test_type2_rle_large_image_is_fast(tmp_path):
    img = scene_like()
    img[200:] = 0  # long runs below, a 0x80 escape in every dark-blue pixel above
    out = rle_encode(encode_sunraster(img)[32:])
    data = header(400, 294, 24, len(out), rtype=2) + bytes(out)
    start = time.perf_counter()
    got = decode_sunraster(data)
    assert time.perf_counter() - start < 0.5
    assert np.array_equal(got, img)
    (tmp_path / "big.ras").write_bytes(data)
    assert np.array_equal(pil_rgb(str(tmp_path / "big.ras")), img)


def test_depth8_with_colour_map():
    cmap = bytes([10, 20, 30]) + bytes([11, 21, 31]) + bytes([12, 22, 32])  # R[3], G[3], B[3]
    rows = bytes([0, 1, 2, 0xAA, 2, 2, 0, 0xAA])  # 3 wide, padded to 4
    got = decode_sunraster(header(3, 2, 8, 8, maptype=1, maplength=9) + cmap + rows)
    want = np.array([[[10, 11, 12], [20, 21, 22], [30, 31, 32]], [[30, 31, 32], [30, 31, 32], [10, 11, 12]]], np.uint8)
    assert np.array_equal(got, want)


def test_depth8_grey_without_map():
    got = decode_sunraster(header(3, 1, 8, 4) + bytes([0, 128, 255, 0]))
    assert np.array_equal(got, [[[0, 0, 0], [128, 128, 128], [255, 255, 255]]])


def test_depth1_monochrome_one_is_black():
    got = decode_sunraster(header(10, 1, 1, 2) + bytes([0b10100000, 0b01000000]))
    bits = [1, 0, 1, 0, 0, 0, 0, 0, 0, 1]
    assert np.array_equal(got[0, :, 0], [0 if b else 255 for b in bits])
    assert got.shape == (1, 10, 3)


@pytest.mark.parametrize("rtype", [0, 1])
def test_length_zero_old_files(rtype):
    got = decode_sunraster(header(2, 1, 24, 0, rtype=rtype) + bytes([1, 2, 3, 4, 5, 6]))
    assert np.array_equal(got, [[[3, 2, 1], [6, 5, 4]]])


def test_colour_map_skipped_for_true_colour():
    got = decode_sunraster(header(1, 1, 24, 4, maptype=1, maplength=6) + bytes(range(6)) + bytes([1, 2, 3, 0]))
    assert np.array_equal(got, [[[3, 2, 1]]])


def test_extensions():
    assert SUN_EXTENSIONS[0] == ".sunimg"
    for name in ("a.sunimg", "A.RAS", "dir/x.Sun", "x.rs", "x.im24", "x.im8", "x.im1", "x.IM32"):
        assert is_sunraster_path(name)
    for name in ("a.png", "a.ras.png", "ras", "a.sunimg.tif"):
        assert not is_sunraster_path(name)


# ---- errors ----------------------------------------------------------------------------


def error(data: bytes, source: str = "x.ras") -> str:
    with pytest.raises(ImageError) as info:
        decode_sunraster(data, source=source)
    message = str(info.value)
    assert message.startswith(source + ": ")
    return message


def test_bad_magic():
    assert "magic" in error(header(1, 1, 24, 4, magic=0x89504E47) + bytes(4))


def test_truncated_header():
    assert "truncated" in error(header(1, 1, 24, 4)[:10])
    assert "truncated" in error(b"")


def test_truncated_pixels_message():
    message = error(header(400, 294, 24, 0) + bytes(1000))
    assert message == "x.ras: truncated: header says 400x294 24-bit pixels (352800 bytes), file holds 1000"


def test_declared_length_larger_than_file():
    assert "truncated" in error(header(2, 1, 24, 600) + bytes(6))


def test_missing_last_pad_byte_is_tolerated():
    assert np.array_equal(decode_sunraster(header(1, 1, 24, 0) + bytes([1, 2, 3])), [[[3, 2, 1]]])
    assert "truncated" in error(header(1, 1, 24, 0) + bytes([1, 2]))


def test_rle_expanding_past_size():
    message = error(header(2, 1, 24, 0, rtype=2) + bytes([0x80, 0xFF, 0x01]))
    assert "past" in message


def test_rle_too_short_and_ending_inside_a_run():
    assert "truncated" in error(header(2, 1, 24, 0, rtype=2) + bytes([1, 2, 3]))
    assert "truncated" in error(header(2, 1, 24, 0, rtype=2) + bytes([1, 2, 3, 4, 5, 0x80, 0x05]))
    assert "truncated" in error(header(2, 1, 24, 0, rtype=2) + bytes([1, 2, 3, 4, 5, 0x80]))


def test_colour_map_errors():
    assert "colour map" in error(header(1, 1, 8, 2, maptype=1, maplength=768) + bytes(30))
    assert "colour map" in error(header(1, 1, 8, 2, maptype=1, maplength=4) + bytes(4) + bytes(2))
    assert "past" in error(header(1, 1, 8, 2, maptype=1, maplength=6) + bytes(6) + bytes([5, 0]))


@pytest.mark.parametrize("fields, word", [((1, 1, 16, 4), "depth"), ((1, 1, 24, 4, 5), "type"), ((1, 1, 24, 4, 1, 2), "map")])
def test_unsupported(fields, word):
    assert word in error(header(*fields) + bytes(64))


@pytest.mark.parametrize("w, h, rtype", [(0, 5, 1), (5, 0, 1), (2**16, 2**16, 1), (0xFFFFFFFF, 0xFFFFFFFF, 2), (2**14, 2**14, 1), (2**14, 2**14, 2)])
def test_huge_claim_with_tiny_file_fails_fast_without_allocating(w, h, rtype):
    data = header(w, h, 32, 0, rtype=rtype) + bytes([0x80, 0xFF, 0x00] * 10)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        error(data)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert time.perf_counter() - start < 0.5
    assert peak < 1 << 20


def test_read_and_write_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.ras"
    with pytest.raises(ImageError, match="nope.ras: cannot read"):
        read_sunraster(missing)
    with pytest.raises(ImageError, match="no/such/dir/x.ras: cannot write"):
        write_sunraster(tmp_path / "no" / "such" / "dir" / "x.ras", random_image(1, 1))
    bad = tmp_path / "bad.ras"
    bad.write_bytes(b"hello")
    with pytest.raises(ImageError, match="^" + re.escape(str(bad)) + ": truncated"):
        read_sunraster(bad)
    assert sorted(os.listdir(tmp_path)) == ["bad.ras"]
