"""Hard inputs (issue 8): the deck parser and the Sun raster reader under fuzzing, the
command line under malformed input, and outputs that are never half-written.

Properties (hypothesis, a small CI budget; `scripts/fuzz.py` runs the same ones for minutes):
- any text → `parse_deck` returns a Deck or raises DeckError `fuzz.dat:LINE: ...` with a
  line that exists; a Deck's frames hold only valid, finite float32 values and survive
  the writer bit for bit;
- decks generated from the grammar parse to the scene they describe and round-trip;
- any bytes → `decode_sunraster` returns an (H, W, 3) uint8 image or raises ImageError,
  quickly, allocating no more than the file (and, when the file can hold it, the image
  it declares) justifies.
"""

from __future__ import annotations

import os
import re
import select
import signal
import struct
import subprocess
import sys
import time
import tracemalloc

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import InvalidArgument
from hypothesis import strategies as st

from rtjax import cli
from rtjax.deck import COMMANDS, MAX_SIDE, Deck, format_deck, load_deck, parse_deck
from rtjax.errors import DeckError, ImageError
from rtjax.images import load_image, save_image
from rtjax.sunraster import SUN_MAGIC, decode_sunraster, encode_sunraster, read_sunraster, write_sunraster

from deck_checks import assert_same_frames

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = os.path.join(ROOT, "scenes")

CI = settings(
    max_examples=100,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)
def event(name: str) -> None:
    """hypothesis.event inside a property (for --hypothesis-show-statistics), nothing outside."""
    import hypothesis

    try:
        hypothesis.event(name)
    except InvalidArgument:
        pass


LINE_BREAKS = re.compile(r"\r\n|\r|\n")
F32_MAX = float(np.finfo(np.float32).max)


# =========================================================================================
# Decks
# =========================================================================================


def fuzz_texture(path: str) -> np.ndarray:
    """A texture loader for fuzzing: fails for names with `bad` or `oops`, else a small image."""
    name = os.path.basename(path)
    if "bad" in name:
        raise ImageError(f"{path}: truncated: a corrupt texture")
    if "oops" in name:
        raise OSError(5, "Input/output error")
    return np.full((1 + len(name) % 3, 1 + len(name) % 4, 3), 7.0, np.float32)


def check_frame(frame) -> None:
    """What every frame of a deck that parsed must satisfy (DECK.md §1)."""
    s = frame.scene.structure
    p = jax.tree_util.tree_map(np.asarray, frame.scene.params)
    assert 1 <= s.width <= MAX_SIDE and 1 <= s.height <= MAX_SIDE
    assert isinstance(frame.output, str) and frame.output and frame.output.split() == [frame.output]
    for leaf in jax.tree_util.tree_leaves(p):
        assert leaf.dtype == np.float32 and np.all(np.isfinite(leaf))
    assert p.centers.shape == (s.n_spheres, 3) and p.light_dirs.shape == (s.n_lights, 3)
    assert np.all(p.radii > 0)
    assert np.all((0 <= p.diffuse) & (p.diffuse <= 1)) and np.all((0 <= p.ks) & (p.ks <= 1))
    assert np.all((0 <= p.kt) & (p.kt <= 1)) and 0 <= p.ke <= 1
    assert np.all(p.beta >= 1) and np.all(p.ior >= 1)
    assert np.all((0 <= p.light_colors) & (p.light_colors <= 255)) and np.all((0 <= p.background) & (p.background <= 255))
    assert np.all(np.any(p.light_dirs != 0, axis=1))
    assert np.any(p.eye != p.refp)
    assert np.all((0 < p.vang) & (p.vang < 180))
    assert len(p.textures) == s.kinds.count("tmap") == len(s.texture_files)


def check_deck_text(text: str) -> str:
    """The parser's contract on any text: a Deck, or a DeckError at a line that exists."""
    n_lines = len(LINE_BREAKS.split(text))
    try:
        deck = parse_deck(text, "fuzz.dat", folder="/nonexistent", load_texture=fuzz_texture)
    except DeckError as e:
        message = str(e)
        assert e.file == "fuzz.dat" and type(e.line) is int and 1 <= e.line <= n_lines, (e.line, n_lines, message)
        assert message.startswith(f"fuzz.dat:{e.line}: ") and len(message) > len(f"fuzz.dat:{e.line}: ")
        assert "\n" not in message and "\r" not in message
        event("deck error")
        return "error"
    assert isinstance(deck, Deck)
    for frame in deck.frames:
        check_frame(frame)
    if deck.frames:
        written = format_deck(deck.frames)
        again = parse_deck(written, "again.dat", folder="/nonexistent", load_texture=fuzz_texture)
        assert_same_frames(deck, again)
    event(f"deck with {min(len(deck.frames), 2)}+ frames")
    return "deck"


NUMBER_TEXTS = [
    "0", "-0", "1", "-1", "0.5", "1.", ".5", "+2", "255", "255.0001", "256", "-0.0001", "179.99999999", "180",
    "1e308", "-1e308", "1e39", "-1e39", "3.4028235e38", "3.4028236e38", "1e-38", "1e-45", "1e-46", "1e-400",
    "1e999", "-1e999", "2147483647", "2147483648", "4294967296", "1" + "0" * 400,
    "nan", "NaN", "-nan", "inf", "-inf", "+inf", "Infinity", "INF",
    "1e", "e1", "--1", "+-1", "0x10", "1_0", "1,5", "1..2", ".", "-", "٣", "٣.٥", "\u22121", "１", "½", "∞", "1\x00",
]  # fmt: skip
numbers = st.one_of(
    st.sampled_from(NUMBER_TEXTS),
    st.floats().map(repr),
    st.floats(allow_nan=False, allow_infinity=False).map(lambda x: f"{x:.3g}"),
    st.integers(-(10**40), 10**40).map(str),
)
commands = st.sampled_from(list(COMMANDS) + ["SPHE", "sphere", "Quit", "#", "rend#x", "\ufeffsphe"])
file_names = st.sampled_from(["a.ras", "out.png", "bad.ras", "oops.ras", "../x.ras", "/abs.ras", "t.sunimg", "x.xyz", "日本.ras", "a\x00b"])
words = st.text(max_size=6)
separators = st.sampled_from([" ", "\t", "  ", " \t ", "\x0c", "\u3000", "\u2028"])
line_breaks = st.sampled_from(["\n", "\r\n", "\r"])


@st.composite
def deck_line(draw) -> str:
    tokens = [draw(st.one_of(commands, words))] + draw(st.lists(st.one_of(numbers, file_names, words), max_size=8))
    line = draw(separators).join(tokens)
    if draw(st.booleans()):
        line += draw(st.sampled_from(["#", " # ", "#"])) + draw(words)
    return line


@st.composite
def token_stream(draw) -> str:
    lines = draw(st.lists(deck_line(), max_size=8))
    return "".join(line + draw(line_breaks) for line in lines)


def _base_decks() -> list[list[str]]:
    decks = []
    for name in sorted(os.listdir(SCENES)):
        if name.endswith(".dat"):
            with open(os.path.join(SCENES, name), encoding="utf-8") as f:
                decks.append(f.read().splitlines())
    return decks


BASE_DECKS = _base_decks()


@st.composite
def mutated_deck(draw) -> str:
    lines = list(draw(st.sampled_from(BASE_DECKS)))
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            break
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["drop", "duplicate", "swap", "number", "number", "token", "insert", "cut"]))
        if op == "drop":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op in ("number", "token"):
            tokens = lines[i].split(" ")
            k = draw(st.integers(1 if op == "number" and len(tokens) > 1 else 0, len(tokens) - 1))
            tokens[k] = draw(numbers if op == "number" else st.one_of(words, commands, file_names))
            lines[i] = " ".join(tokens)
        elif op == "insert":
            lines.insert(i, draw(deck_line()))
        else:
            lines[i] = lines[i][: draw(st.integers(0, len(lines[i])))]
    return "\n".join(lines) + draw(st.sampled_from(["\n", ""]))


@CI
@given(token_stream())
def test_random_token_streams(text):
    check_deck_text(text)


@CI
@given(mutated_deck())
def test_mutated_decks(text):
    check_deck_text(text)


@CI
@given(st.text(max_size=200))
def test_arbitrary_text(text):
    check_deck_text(text)


def test_unmutated_base_decks_parse():
    assert len(BASE_DECKS) >= 5
    for lines in BASE_DECKS:
        assert check_deck_text("\n".join(lines)) == "deck"


# ---- valid decks from the grammar --------------------------------------------------------


@st.composite
def number_text(draw, lo: float, hi: float) -> str:
    """A number in [lo, hi] written in one of the ordinary syntaxes (7+ significant digits)."""
    x = draw(st.floats(lo, hi, allow_nan=False, allow_infinity=False))
    style = draw(st.sampled_from(["repr", "g9", "e7", "int"]))
    if style == "int" and float(round(x)) == x and abs(x) < 1e15:
        return draw(st.sampled_from([str(int(x)), f"{int(x)}.", f"+{int(x)}" if x >= 0 else str(int(x)), f"{x:e}"]))
    text = repr(x) if style in ("repr", "int") else f"{x:.9g}" if style == "g9" else f"{x:.7e}"
    return "0" if text == "-0.0" and lo >= 0 else text


def f32(text: str) -> np.float32:
    return np.float32(float(text))


@st.composite
def valid_deck(draw):
    """(text, expected frames): a deck obeying every rule, and what each rend must hold."""
    lines: list[str] = []
    model = {"spheres": [], "lights": [], "back": ["0", "0", "0"], "ke": "0"}

    def vec(lo, hi, n=3):
        return [draw(number_text(lo, hi)) for _ in range(n)]

    def camera(item):
        if item == "eyep":
            model["eye"] = [draw(number_text(100, 1e4))] + vec(-1e4, 1e4, 2)  # x > 100: never refp
            lines.append("eyep " + " ".join(model["eye"]))
        elif item == "refp":
            model["refp"] = [draw(number_text(-50, 50))] + vec(-1e4, 1e4, 2)
            lines.append("refp " + " ".join(model["refp"]))
        elif item == "vang":
            model["vang"] = vec(0.5, 179, 2)
            lines.append("vang " + " ".join(model["vang"]))
        else:
            model["size"] = draw(st.integers(1, 64))
            lines.append("size " + draw(st.sampled_from([str(model["size"]), f"{model['size']}.0", f"{model['size']}e0"])))

    for item in draw(st.permutations(["eyep", "refp", "vang", "size"])):
        camera(item)
    frames = []
    items = draw(st.lists(st.sampled_from(["sphe", "sphe", "plig", "back", "elig", "eyep", "refp", "vang", "size", "rend", "#", ""]), max_size=14))
    for item in items + ["rend"]:
        if item == "sphe":
            centre, r = vec(-1e4, 1e4), draw(number_text(1e-3, 1e4))
            lines.append("sphe " + " ".join(centre + [r]))
            kind = draw(st.sampled_from(["opaq", "mirr", "trpa", "tmap"]))
            if kind == "opaq":
                lines.append("opaq " + " ".join(vec(0, 1, 4) + [draw(number_text(1, 1000))]))
            elif kind == "mirr":
                lines.append("mirr")
            elif kind == "trpa":
                lines.append("trpa " + " ".join([draw(number_text(0, 1)), draw(number_text(1, 5)), draw(number_text(0, 1)), draw(number_text(1, 1000))]))
            else:
                name = draw(st.from_regex(r"[c-np-z][c-np-z0-9_]{0,6}\.(ras|png)", fullmatch=True))  # never bad/oops
                extra = [draw(number_text(0, 1)), draw(number_text(1, 100))] if draw(st.booleans()) else []
                lines.append(" ".join(["tmap", name, *extra]))
            model["spheres"].append((kind, centre, r))
        elif item == "plig":
            direction = vec(-10, 10)
            k = draw(st.integers(0, 2))
            direction[k] = draw(st.sampled_from(["", "-"])) + draw(number_text(0.5, 10)).lstrip("+")  # never zero
            colour = vec(0, 255)
            lines.append("plig " + " ".join(direction + colour))
            model["lights"].append((direction, colour))
        elif item == "back":
            model["back"] = vec(0, 255)
            lines.append("back " + " ".join(model["back"]))
        elif item == "elig":
            model["ke"] = draw(number_text(0, 1))
            lines.append("elig " + model["ke"])
        elif item in ("eyep", "refp", "vang", "size"):
            camera(item)
        elif item == "rend":
            output = draw(st.from_regex(r"[a-z0-9_]{1,8}\.(sunimg|ras|png)", fullmatch=True))
            lines.append(f"rend {output}" + draw(st.sampled_from(["", "  # a frame"])))
            frames.append({**{k: (list(v) if isinstance(v, list) else v) for k, v in model.items()}, "output": output, "line": len(lines)})
        elif item == "#":
            lines.append("# " + draw(st.text(max_size=10)).replace("\n", " ").replace("\r", " "))
        else:
            lines.append(draw(st.sampled_from(["", "   ", "\t"])))
    if draw(st.booleans()):
        lines += ["quit", draw(st.sampled_from(["garbage after quit", "sphe nan", "\x00"]))]
    text = draw(line_breaks).join(lines) + "\n"
    return text, frames


@CI
@given(valid_deck())
def test_valid_decks_parse_to_what_they_say_and_round_trip(case):
    text, frames = case
    deck = parse_deck(text, "gen.dat", load_texture=fuzz_texture)
    assert len(deck.frames) == len(frames)
    for frame, want in zip(deck.frames, frames):
        check_frame(frame)
        s = frame.scene.structure
        p = jax.tree_util.tree_map(np.asarray, frame.scene.params)
        assert frame.output == want["output"] and frame.line == want["line"]
        assert s.kinds == tuple(k for k, _, _ in want["spheres"]) and s.n_lights == len(want["lights"])
        assert s.width == want["size"]
        assert np.array_equal(p.centers, np.array([[f32(t) for t in c] for _, c, _ in want["spheres"]], np.float32).reshape(-1, 3))
        assert np.array_equal(p.radii, np.array([f32(r) for _, _, r in want["spheres"]], np.float32))
        assert np.array_equal(p.light_dirs, np.array([[f32(t) for t in d] for d, _ in want["lights"]], np.float32).reshape(-1, 3))
        assert np.array_equal(p.light_colors, np.array([[f32(t) for t in c] for _, c in want["lights"]], np.float32).reshape(-1, 3))
        assert np.array_equal(p.background, [f32(t) for t in want["back"]]) and p.ke == f32(want["ke"])
        assert np.array_equal(p.eye, [f32(t) for t in want["eye"]]) and np.array_equal(p.refp, [f32(t) for t in want["refp"]])
        assert np.array_equal(p.vang, [f32(t) for t in want["vang"]])
    written = format_deck(deck.frames)
    again = parse_deck(written, "again.dat", load_texture=fuzz_texture)
    assert_same_frames(deck, again)
    assert format_deck(again.frames) == written


# =========================================================================================
# Sun raster files
# =========================================================================================


def header(w, h, depth, length, rtype=1, maptype=0, maplength=0, magic=SUN_MAGIC) -> bytes:
    return struct.pack(">8I", magic, w, h, depth, length, rtype, maptype, maplength)


def row_bytes(w: int, depth: int) -> int:
    raw = (w * depth + 7) // 8
    return raw + (raw & 1)


def rle_encode(raw: bytes) -> bytes:
    """Runs of 3..256 equal bytes become 0x80 n v, a lone 0x80 becomes 0x80 0x00."""

    def token(m: re.Match) -> bytes:
        run = m.group(0)
        return bytes([0x80, len(run) - 1, run[0]]) if len(run) > 1 else b"\x80\x00"

    return re.sub(rb"(.)\1{2,255}|\x80", token, raw, flags=re.DOTALL)


@st.composite
def raster_file(draw) -> bytes:
    """A well-formed Sun raster file: depth 1/8/24/32, types 0-3, with or without a colour map."""
    h, w = draw(st.integers(1, 6)), draw(st.integers(1, 7))
    depth = draw(st.sampled_from([1, 8, 24, 32]))
    rtype = draw(st.sampled_from([0, 1, 2, 3]))
    cmap = b""
    if depth <= 8 and draw(st.booleans()):
        n = draw(st.integers(1, 256 if depth == 8 else 2))
        cmap = draw(st.binary(min_size=3 * n, max_size=3 * n))
    raw = draw(st.binary(min_size=row_bytes(w, depth) * h, max_size=row_bytes(w, depth) * h))
    if depth == 8 and cmap:
        raw = bytes(b % (len(cmap) // 3) for b in raw)
    elif depth == 1 and cmap:
        raw = raw if len(cmap) == 6 else bytes(len(raw))
    if draw(st.booleans()):  # runs, to give RLE something to do
        raw = bytes(len(raw)) if depth != 8 or not cmap else raw
    body = rle_encode(raw) if rtype == 2 else raw
    length = draw(st.sampled_from([len(body), 0]))
    return header(w, h, depth, length, rtype, 1 if cmap else 0, len(cmap)) + cmap + body


EXTREMES = [0, 1, 2, 3, 7, 8, 15, 16, 24, 31, 32, 33, 255, 256, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 2**24, 2**28, 2**31 - 1, 2**31, 2**32 - 1]


@st.composite
def mutated_raster(draw) -> bytes:
    data = bytearray(draw(raster_file()))
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["field", "field", "field", "truncate", "append", "byte", "rle_bomb", "short_map"]))
        if op == "field" and len(data) >= 32:
            i = draw(st.integers(1, 7))  # width height depth length type maptype maplength
            struct.pack_into(">I", data, 4 * i, draw(st.one_of(st.sampled_from(EXTREMES), st.integers(0, 2**32 - 1))))
        elif op == "truncate":
            del data[draw(st.integers(0, len(data))) :]
        elif op == "append":
            data += draw(st.binary(max_size=64))
        elif op == "byte" and data:
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        elif op == "rle_bomb" and len(data) >= 32:
            struct.pack_into(">I", data, 20, 2)
            data += draw(st.sampled_from([b"\x80\xff\x00", b"\x80\xff\x80", b"\x80\x00", b"\x80"])) * draw(st.integers(1, 400))
        elif op == "short_map" and len(data) >= 32:
            struct.pack_into(">II", data, 24, 1, draw(st.sampled_from([1, 2, 3, 4, 6, 765, 768, 771, 10**6])))
    return bytes(data)


def check_raster(data: bytes) -> object:
    """decode_sunraster's contract on any bytes: an image or an ImageError, fast and small."""
    fields = struct.unpack(">8I", data[:32]) if len(data) >= 32 else None
    started = tracemalloc.is_tracing()
    if not started:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    t0 = time.perf_counter()
    try:
        outcome = decode_sunraster(data, source="fuzz.ras")
    except ImageError as e:
        outcome = e
    finally:
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] - base
        if not started:
            tracemalloc.stop()
    assert elapsed < 2.0, elapsed
    event("image" if isinstance(outcome, np.ndarray) else "ImageError")
    if isinstance(outcome, ImageError):
        message = str(outcome)
        assert message.startswith("fuzz.ras: ") and "\n" not in message
    else:
        assert fields is not None and fields[0] == SUN_MAGIC
        w, h = fields[1], fields[2]
        assert isinstance(outcome, np.ndarray) and outcome.dtype == np.uint8 and outcome.shape == (h, w, 3)
    # Memory: proportional to the file, plus the declared image only when the file can
    # hold it (RLE expands 3 bytes to at most 256); never what a header merely claims.
    budget = (1 << 20) + 64 * len(data)
    if fields is not None:
        w, h, depth = fields[1:4]
        need = row_bytes(w, max(depth, 1)) * h if w * h <= 2**28 and depth <= 32 else 1 << 62
        if need <= 86 * len(data) + 256:
            budget += 32 * (3 * w * h) + 16 * need
    assert peak <= budget, (peak, budget, fields, len(data))
    return outcome


@CI
@given(raster_file())
def test_well_formed_rasters_decode(data):
    image = check_raster(data)
    assert isinstance(image, np.ndarray), image


@settings(CI, max_examples=150)
@given(mutated_raster())
def test_mutated_rasters(data):
    check_raster(data)


@CI
@given(st.binary(max_size=300))
def test_random_bytes_as_rasters(data):
    check_raster(data)
    check_raster(header(3, 2, 24, 0) + data)
    check_raster(header(3, 2, 24, 0, rtype=2) + data)


@pytest.mark.parametrize(
    "data",
    [
        header(2**16, 2**15, 32, 0, rtype=2) + b"\x80\xff\x00" * 30000,  # 90 kB cannot hold 8 GB
        header(300, 300, 24, 0, rtype=2) + b"\x80\xff\x01" * 3000,  # expands past the declared size
        header(3, 3, 8, 0, rtype=2) + b"\x80\x00" * 150000,  # 300 kB of escapes, far past 12 bytes
        header(2**31 - 1, 2**31 - 1, 1, 0xFFFFFFFF, 1, 1, 0xFFFFFFFF),
        header(1, 1, 8, 2, maptype=1, maplength=0xFFFFFFFF) + bytes(100),
        header(4, 4, 8, 16, maptype=1, maplength=3) + bytes([1, 2, 3]) + bytes([0, 5] * 8),  # index past the map
    ],
    ids=["huge-claim", "rle-past-size", "rle-escapes", "max-fields", "huge-map", "short-map"],
)
def test_hostile_rasters(data):
    assert isinstance(check_raster(data), ImageError)


@CI
@given(st.integers(1, 9), st.integers(1, 9), st.booleans(), st.integers(0, 2**32 - 1))
def test_small_and_odd_sizes_round_trip(h, w, order, seed):
    image = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    data = encode_sunraster(image, assignment_order=order)
    assert len(data) == 32 + row_bytes(w, 24) * h
    assert np.array_equal(decode_sunraster(data, assignment_order=order), image)
    assert np.array_equal(decode_sunraster(header(w, h, 24, 0, rtype=2) + rle_encode(data[32:]), assignment_order=order), image)


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (5, 3), (7, 1)])
def test_textures_of_one_pixel_and_odd_sizes(tmp_path, shape):
    texture = np.random.default_rng(shape[0]).integers(0, 256, (*shape, 3), dtype=np.uint8)
    write_sunraster(tmp_path / "tex.ras", texture)
    save_image(tmp_path / "tex.png", texture)
    assert np.array_equal(load_image(tmp_path / "tex.ras"), texture.astype(np.float32))
    assert np.array_equal(load_image(tmp_path / "tex.png"), texture.astype(np.float32))
    (tmp_path / "t.dat").write_text(
        "sphe 0 0 0 1\ntmap tex.ras\nsphe 0 0 3 1\ntmap tex.png 0.5 4\neyep 9 0 1\nrefp 0 0 1\nvang 40 30\nsize 8\nrend a.ras\n"
    )
    deck = load_deck(tmp_path / "t.dat")
    assert deck.frames[0].scene.structure.texture_shapes == (shape, shape)
    for t in deck.frames[0].scene.params.textures:
        assert np.array_equal(np.asarray(t), texture.astype(np.float32))


def test_render_with_a_one_pixel_texture(tmp_path, capsys):
    write_sunraster(tmp_path / "one.ras", np.array([[[200, 10, 20]]], np.uint8))
    (tmp_path / "t.dat").write_text(
        "sphe 0 0 0 1\ntmap one.ras\nplig 1 0 1 255 255 255\nelig 1\neyep 9 0 0\nrefp 0 0 0\nvang 40 30\nsize 9\nrend a.ras\n"
    )
    assert cli.main(["render", str(tmp_path / "t.dat"), "-o", str(tmp_path / "out")]) == 0
    image = read_sunraster(tmp_path / "out" / "a.ras")
    assert image.shape == (7, 9, 3)
    # ke = 1, ks = 0: I = ke·d·L = the texel's colour, wherever the sphere is seen.
    assert tuple(image[3, 4]) == (200, 10, 20) and tuple(image[0, 0]) == (0, 0, 0)


# =========================================================================================
# The command line under malformed input (subprocesses, run side by side)
# =========================================================================================


def popen_cli(*args: str, cwd=None) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.Popen([sys.executable, "-m", "rtjax", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=cwd, env=env)


def all_files(folder) -> list[str]:
    out = []
    for root, _, files in os.walk(folder):
        out += [os.path.relpath(os.path.join(root, f), folder) for f in files]
    return sorted(out)


def test_cli_malformed_decks_and_rasters(tmp_path, capsys):
    camera = "eyep 9 0 0\nrefp 0 0 0\nvang 40 30\nsize 8\n"
    cases = {  # deck file → (bytes, line, fragment)
        "corrupt_texture.dat": (f"sphe 0 0 0 1\ntmap corrupt.ras\n{camera}rend a.ras\n".encode(), 2, "tmap: cannot read texture 'corrupt.ras': "),
        "binary.dat": (b"sphe 0 0 0 1\nmirr\n\x00\x01\xfe\xff\n", 3, "the deck is not UTF-8 text (byte 0xfe)"),
        "rle_texture.dat": (f"sphe 0 0 0 1\ntmap rle.ras 0 1\n{camera}rend a.ras\n".encode(), 2, "expands to"),
    }
    (tmp_path / "corrupt.ras").write_bytes(header(5, 4, 24, 60) + bytes(17))  # truncated
    (tmp_path / "rle.ras").write_bytes(header(2, 2, 24, 0, rtype=2) + b"\x80\xff\x07" * 4)  # expands past 2×2
    for name, (content, _, _) in cases.items():
        (tmp_path / name).write_bytes(content)
        (tmp_path / ("out_" + name)).mkdir()
    # Two as real processes, side by side; the third in-process (the same code path).
    procs = {name: popen_cli("render", name, "-o", "out_" + name, cwd=tmp_path) for name in list(cases)[:2]}
    results = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        results[name] = (proc.returncode, stdout.decode(), stderr.decode())
    name = "rle_texture.dat"
    code = cli.main(["render", str(tmp_path / name), "-o", str(tmp_path / ("out_" + name))])
    captured = capsys.readouterr()
    results[name] = (code, captured.out, captured.err)
    for name, (code, out, err) in results.items():
        _, line, fragment = cases[name]
        assert code == 2 and out == "", (name, err)
        assert "Traceback" not in err and len(err.splitlines()) == 1, err
        assert err.startswith(f"{name}:{line}: ") and fragment in err, err
        assert all_files(tmp_path / ("out_" + name)) == []


# =========================================================================================
# Outputs: atomic, deterministic
# =========================================================================================

OLD = encode_sunraster(np.full((2, 3, 3), 9, np.uint8))


def test_interrupted_sun_raster_write_keeps_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "a.ras"
    target.write_bytes(OLD)
    seen = []

    def interrupt(fd):  # the temporary file holds the new bytes; the rename has not happened
        seen.append(os.fstat(fd).st_size)
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", interrupt)
    with pytest.raises(KeyboardInterrupt):
        save_image(target, np.zeros((40, 50, 3), np.uint8))
    assert seen == [32 + 150 * 40]
    assert all_files(tmp_path) == ["a.ras"] and target.read_bytes() == OLD
    monkeypatch.undo()
    save_image(target, np.zeros((40, 50, 3), np.uint8))  # and a complete write replaces it
    assert read_sunraster(target).shape == (40, 50, 3) and all_files(tmp_path) == ["a.ras"]


def test_failed_sun_raster_write_is_an_image_error(tmp_path, monkeypatch):
    (tmp_path / "a.ras").write_bytes(OLD)

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(ImageError, match=r"a\.ras: cannot write: No space left on device"):
        save_image(tmp_path / "a.ras", np.zeros((4, 5, 3), np.uint8))
    assert all_files(tmp_path) == ["a.ras"] and (tmp_path / "a.ras").read_bytes() == OLD


def test_interrupted_oiio_write_keeps_the_old_file(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    old_png = tmp_path / "old.png"
    save_image(old_png, np.full((2, 3, 3), 9, np.uint8))
    old = old_png.read_bytes()
    target = tmp_path / "a.png"
    target.write_bytes(old)
    real_create = oiio.ImageOutput.create
    temporary = []

    class HalfWriter:
        """Writes the first half of the rows, then Ctrl-C."""

        def __init__(self, out):
            self.out = out

        def open(self, name, spec):
            temporary.append(name)
            return self.out.open(name, spec)

        def write_image(self, pixels):
            half = pixels.shape[0] // 2
            self.out.write_scanlines(0, half, 0, pixels[:half])
            assert os.path.exists(temporary[0])
            raise KeyboardInterrupt

        def close(self):
            return self.out.close()

        def geterror(self):
            return self.out.geterror()

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda name: HalfWriter(real_create(name))))
    with pytest.raises(KeyboardInterrupt):
        save_image(target, np.zeros((40, 50, 3), np.uint8))
    assert temporary and os.path.dirname(temporary[0]) == str(tmp_path)
    assert all_files(tmp_path) == ["a.png", "old.png"] and target.read_bytes() == old


def test_cli_interrupt_in_process(tmp_path, capsys, monkeypatch):
    deck = tmp_path / "d.dat"
    deck.write_text("sphe 0 0 0 1\nopaq 1 0.2 0 0.5 10\nplig 1 1 2 255 255 255\neyep 8 6 4\nrefp 0 0 0\nvang 40 30\nsize 16\nrend a.ras\n")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "a.ras").write_bytes(OLD)
    def interrupt(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", interrupt)
    assert cli.main(["render", str(deck), "-o", str(tmp_path / "out"), "--png"]) == 130
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == "interrupted: no partial file was written\n"
    assert all_files(tmp_path / "out") == ["a.ras"] and (tmp_path / "out" / "a.ras").read_bytes() == OLD


def test_same_deck_same_bytes(tmp_path, capsys):
    deck = tmp_path / "d.dat"
    deck.write_text(
        "sphe 0 0 0 1\nopaq 1 0.2 0 0.5 10\nplig 1 1 2 255 255 255\nback 0 0 128\neyep 8 6 4\nrefp 0 0 0\nvang 40 30\nsize 16\n"
        "rend a.ras\nrend b.png\n"
    )
    for out in ("one", "two"):
        assert cli.main(["render", str(deck), "-o", str(tmp_path / out)]) == 0
    capsys.readouterr()
    for name in ("a.ras", "b.png"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


# ---- killing a real `rtjax render` ------------------------------------------------------------

SLOW_FSYNC = """
import os, sys, time
real_fsync = os.fsync
def slow_fsync(fd):  # the temporary file is complete, the rename is still to come
    print("WRITING", flush=True)
    time.sleep(120)
    real_fsync(fd)
os.fsync = slow_fsync
from rtjax.cli import main
sys.exit(main(sys.argv[1:]))
"""


def read_until(proc: subprocess.Popen, marker: bytes, timeout: float) -> bytes:
    """Read the child's stdout until `marker` appears (or fail after `timeout` seconds)."""
    seen, fd, end = b"", proc.stdout.fileno(), time.monotonic() + timeout
    while marker not in seen:
        left = end - time.monotonic()
        assert left > 0 and proc.poll() is None, (seen, proc.poll())
        ready, _, _ = select.select([fd], [], [], min(left, 1.0))
        if ready:
            seen += os.read(fd, 4096)
    return seen


@pytest.mark.skipif(not hasattr(signal, "SIGTERM") or os.name != "posix", reason="POSIX signals")
def test_signal_mid_write_keeps_the_previous_file(tmp_path):
    deck = tmp_path / "d.dat"
    deck.write_text("sphe 0 0 0 1\nopaq 1 0.2 0 0.5 10\nplig 1 1 2 255 255 255\neyep 8 6 4\nrefp 0 0 0\nvang 40 30\nsize 16\nrend a.ras\n")
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    procs = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        out = tmp_path / f"out{int(sig)}"
        out.mkdir()
        (out / "a.ras").write_bytes(OLD)
        procs[sig] = subprocess.Popen(
            [sys.executable, "-c", SLOW_FSYNC, "render", str(deck), "-o", str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
        )  # fmt: skip
    for sig, proc in procs.items():
        try:
            read_until(proc, b"WRITING", 240)
            out = tmp_path / f"out{int(sig)}"
            assert len(all_files(out)) == 2  # a.ras and the complete temporary file beside it
            proc.send_signal(sig)
            _, stderr = proc.communicate(timeout=60)
        finally:
            proc.kill()
        assert proc.returncode == 128 + int(sig), stderr
        assert stderr.decode() == "interrupted: no partial file was written\n"
        assert all_files(out) == ["a.ras"] and (out / "a.ras").read_bytes() == OLD


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_ctrl_c_during_a_render_leaves_only_complete_files(tmp_path):
    """Three frames of different sizes (each compiles and renders anew); Ctrl-C once the
    first is written: what is there is complete, no temporary file is left."""
    scene = "sphe 0 0 0 1\nopaq 1 0.2 0 0.5 10\nsphe 0 0 2.5 1\nmirr\nplig 1 1 2 255 255 255\neyep 8 6 4\nrefp 0 0 1\nvang 40 30\n"
    deck = tmp_path / "d.dat"
    deck.write_text(scene + "size 30\nrend a.ras\nsize 31\nrend b.ras\nsize 32\nrend c.ras\n")
    out = tmp_path / "out"
    proc = popen_cli("render", str(deck), "-o", str(out))
    try:
        first = read_until(proc, b"a.ras  30x", 240)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    err = stderr.decode()
    assert "Traceback" not in err
    files = all_files(out)
    assert "a.ras" in files and all(not f.startswith(".") for f in files), files
    sizes = {"a.ras": (22, 30), "b.ras": (23, 31), "c.ras": (24, 32)}
    for name in files:
        assert read_sunraster(out / name).shape == (*sizes[name], 3)  # complete, decodes
    if proc.returncode == 130:
        assert err == "interrupted: no partial file was written\n"
    else:  # it finished before the signal landed
        assert proc.returncode == 0 and files == ["a.ras", "b.ras", "c.ras"], (proc.returncode, err)
    printed = len((first + stdout).decode().splitlines())  # a frame's line follows its file
    assert printed in (len(files), len(files) - 1)
