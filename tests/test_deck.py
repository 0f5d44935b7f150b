"""The deck language (DECK.md §1): every rule broken once, the semantics, and the writer.

Every error is a DeckError whose message reads `<file>:<line>: <command>...`, naming
what was expected and what was found.
"""

from __future__ import annotations

import glob
import os
import re

import jax
import numpy as np
import pytest

import rtjax
from rtjax.deck import MAX_SIDE, Deck, Frame, format_deck, load_deck, parse_deck, save_deck
from rtjax.errors import DeckError, RtjaxError
from rtjax.images import load_image
from rtjax.sunraster import write_sunraster

from deck_checks import assert_same_frames

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(os.path.dirname(HERE), "scenes")
SAMPLE = os.path.join(SCENES, "ex2s3.dat")

SPHERE = "sphe 0 0 0 1\nopaq 1 1 1 0 1\n"  # two lines
CAMERA = "eyep 10 0 0\nrefp 0 0 0\nvang 40 30\nsize 4\n"  # four lines


def fake_texture(path: str) -> np.ndarray:
    """A texture loader for parse_deck: a 2×3 mid-grey image whatever the path."""
    return np.full((2, 3, 3), 128.0, np.float32)


def parse(text: str, **kw) -> Deck:
    kw.setdefault("load_texture", fake_texture)
    return parse_deck(text, "t.dat", **kw)


def deck_error(text: str, **kw) -> DeckError:
    with pytest.raises(DeckError) as info:
        parse(text, **kw)
    return info.value


# ---- every rule broken once -------------------------------------------------------------
# (id, deck text, line of the error, fragments the message must contain after "t.dat:LINE: ")

ERRORS = [
    # unknown commands
    ("unknown", "foo 1 2\n", 1, ["unknown command 'foo'", "expected one of sphe, opaq"]),
    ("unknown-uppercase", SPHERE + "SPHE 0 0 0 1\n", 3, ["unknown command 'SPHE'"]),
    ("unknown-glued", "sphe0 0 0 1\n", 1, ["unknown command 'sphe0'"]),
    ("unknown-unprintable", "sp\x1bhe 1\n", 1, ["unknown command 'sp\\x1bhe'"]),
    # argument counts, too few and too many, for every command
    ("sphe-3", "sphe 0 0 0\n", 1, ["sphe takes 4 numbers (xc yc zc r), found 3: 0 0 0"]),
    ("sphe-5", "sphe 0 0 0 1 2\n", 1, ["sphe takes 4 numbers (xc yc zc r), found 5"]),
    ("sphe-0", "sphe\n", 1, ["sphe takes 4 numbers (xc yc zc r), found 0"]),
    ("opaq-4", "sphe 0 0 0 1\nopaq 1 1 1 0\n", 2, ["opaq takes 5 numbers (dR dG dB ks beta), found 4"]),
    ("opaq-6", "sphe 0 0 0 1\nopaq 1 1 1 0 1 1\n", 2, ["opaq takes 5 numbers (dR dG dB ks beta), found 6"]),
    ("mirr-1", "sphe 0 0 0 1\nmirr 1\n", 2, ["mirr takes no arguments, found 1: 1"]),
    ("trpa-3", "sphe 0 0 0 1\ntrpa 0.5 1.5 0\n", 2, ["trpa takes 4 numbers (kt n ks beta), found 3"]),
    ("trpa-5", "sphe 0 0 0 1\ntrpa 0.5 1.5 0 1 1\n", 2, ["trpa takes 4 numbers (kt n ks beta), found 5"]),
    ("tmap-0", "sphe 0 0 0 1\ntmap\n", 2, ["tmap takes a file name and optionally 2 numbers (file [ks beta]), found 0"]),
    ("tmap-2", "sphe 0 0 0 1\ntmap t.ras 0.5\n", 2, ["tmap takes a file name and optionally 2 numbers", "found 2 arguments: t.ras 0.5"]),
    ("tmap-4", "sphe 0 0 0 1\ntmap t.ras 0.5 1 1\n", 2, ["tmap takes a file name and optionally 2 numbers", "found 4"]),
    ("plig-5", "plig 1 1 1 255 255\n", 1, ["plig takes 6 numbers (lx ly lz LR LG LB), found 5"]),
    ("plig-7", "plig 1 1 1 255 255 255 1\n", 1, ["plig takes 6 numbers (lx ly lz LR LG LB), found 7"]),
    ("back-2", "back 0 0\n", 1, ["back takes 3 numbers (BR BG BB), found 2"]),
    ("back-4", "back 0 0 0 0\n", 1, ["back takes 3 numbers (BR BG BB), found 4"]),
    ("elig-0", "elig\n", 1, ["elig takes 1 number (ke), found 0"]),
    ("elig-2", "elig 0.1 0.2\n", 1, ["elig takes 1 number (ke), found 2: 0.1 0.2"]),
    ("eyep-2", "eyep 1 2\n", 1, ["eyep takes 3 numbers (xv yv zv), found 2"]),
    ("eyep-4", "eyep 1 2 3 4\n", 1, ["eyep takes 3 numbers (xv yv zv), found 4"]),
    ("refp-2", "refp 1 2\n", 1, ["refp takes 3 numbers (xf yf zf), found 2"]),
    ("refp-4", "refp 1 2 3 4\n", 1, ["refp takes 3 numbers (xf yf zf), found 4"]),
    ("vang-1", "vang 40\n", 1, ["vang takes 2 numbers (ha va), found 1"]),
    ("vang-3", "vang 40 30 20\n", 1, ["vang takes 2 numbers (ha va), found 3"]),
    ("size-0", "size\n", 1, ["size takes 1 number (is), found 0"]),
    ("size-2", "size 4 4\n", 1, ["size takes 1 number (is), found 2"]),
    ("rend-0", CAMERA + "rend\n", 5, ["rend takes 1 file name, found 0"]),
    ("rend-2", CAMERA + "rend a.ras b.ras\n", 5, ["rend takes 1 file name, found 2 arguments: a.ras b.ras"]),
    ("quit-1", "quit now\n", 1, ["quit takes no arguments, found 1: now"]),
    # not numbers
    ("word", "sphe 0 0 zero 1\n", 1, ["sphe: zc must be a number, found zero"]),
    ("comma-decimal", "elig 0,5\n", 1, ["elig: ke must be a number, found 0,5"]),
    ("hex", "size 0x10\n", 1, ["size: is must be a number, found 0x10"]),
    ("bare-exponent", "sphe 0 0 0 1e\n", 1, ["sphe: r must be a number, found 1e"]),
    ("double-sign", "eyep --1 0 0\n", 1, ["eyep: xv must be a number, found --1"]),
    ("underscore", "size 1_000\n", 1, ["size: is must be a number, found 1_000"]),
    ("unicode-digit", "sphe \u0661 0 0 1\n", 1, ["sphe: xc must be a number, found \u0661"]),
    ("fullwidth-digit", "elig \uff10\n", 1, ["elig: ke must be a number, found \uff10"]),
    ("unicode-minus", "eyep \u22121 0 0\n", 1, ["eyep: xv must be a number, found \u22121"]),
    ("nul-in-number", "elig 0\x005\n", 1, ["elig: ke must be a number, found 0\\x005"]),
    # nan and inf, and numbers beyond float32 (the scene's precision)
    ("nan", "sphe nan 0 0 1\n", 1, ["sphe: xc must be a finite number, found nan"]),
    ("NaN-in-material", "sphe 0 0 0 1\nopaq 1 NaN 1 0 1\n", 2, ["opaq: dG must be a finite number, found NaN"]),
    ("inf", "back inf 0 0\n", 1, ["back: BR must be a finite number, found inf"]),
    ("minus-inf", "eyep 0 -inf 0\n", 1, ["eyep: yv must be a finite number, found -inf"]),
    ("infinity", "refp 0 0 Infinity\n", 1, ["refp: zf must be a finite number, found Infinity"]),
    ("overflow-float64", "sphe 1e999 0 0 1\n", 1, ["sphe: xc must be a finite number", "found 1e999"]),
    ("overflow-float32", "sphe 0 0 0 1e39\n", 1, ["sphe: r must be a finite number within float32 range", "found 1e39"]),
    ("size-inf", "size inf\n", 1, ["size: is must be a finite number, found inf"]),
    ("size-1e999", "size 1e999\n", 1, ["size: is must be a finite number, found 1e999"]),
    # ranges: 0 ≤ dR dG dB ks kt ke ≤ 1, beta ≥ 1, n ≥ 1, levels 0..255, r > 0, vang in (0, 180), size
    ("dR<0", "sphe 0 0 0 1\nopaq -0.1 1 1 0 1\n", 2, ["opaq: dR must be in [0, 1], found -0.1"]),
    ("dG>1", "sphe 0 0 0 1\nopaq 1 1.1 1 0 1\n", 2, ["opaq: dG must be in [0, 1], found 1.1"]),
    ("dB>1", "sphe 0 0 0 1\nopaq 1 1 2 0 1\n", 2, ["opaq: dB must be in [0, 1], found 2"]),
    ("opaq-ks<0", "sphe 0 0 0 1\nopaq 1 1 1 -1 1\n", 2, ["opaq: ks must be in [0, 1], found -1"]),
    ("opaq-ks>1", "sphe 0 0 0 1\nopaq 1 1 1 1.0001 1\n", 2, ["opaq: ks must be in [0, 1], found 1.0001"]),
    ("opaq-beta<1", "sphe 0 0 0 1\nopaq 1 1 1 0 0.5\n", 2, ["opaq: beta must be ≥ 1, found 0.5"]),
    ("trpa-kt<0", "sphe 0 0 0 1\ntrpa -0.5 1.5 0 1\n", 2, ["trpa: kt must be in [0, 1], found -0.5"]),
    ("trpa-kt>1", "sphe 0 0 0 1\ntrpa 1.5 1.5 0 1\n", 2, ["trpa: kt must be in [0, 1], found 1.5"]),
    ("trpa-n<1", "sphe 0 0 0 1\ntrpa 0.5 0.9 0 1\n", 2, ["trpa: n must be ≥ 1, found 0.9"]),
    ("trpa-ks>1", "sphe 0 0 0 1\ntrpa 0.5 1.5 3 1\n", 2, ["trpa: ks must be in [0, 1], found 3"]),
    ("trpa-beta<1", "sphe 0 0 0 1\ntrpa 0.5 1.5 0 0\n", 2, ["trpa: beta must be ≥ 1, found 0"]),
    ("tmap-ks>1", "sphe 0 0 0 1\ntmap t.ras 1.5 1\n", 2, ["tmap: ks must be in [0, 1], found 1.5"]),
    ("tmap-ks<0", "sphe 0 0 0 1\ntmap t.ras -0.5 1\n", 2, ["tmap: ks must be in [0, 1], found -0.5"]),
    ("tmap-beta<1", "sphe 0 0 0 1\ntmap t.ras 0 0.99\n", 2, ["tmap: beta must be ≥ 1, found 0.99"]),
    ("tmap-not-number", "sphe 0 0 0 1\ntmap t.ras shiny 1\n", 2, ["tmap: ks must be a number, found shiny"]),
    ("ke<0", "elig -0.1\n", 1, ["elig: ke must be in [0, 1], found -0.1"]),
    ("ke>1", "elig 1.5\n", 1, ["elig: ke must be in [0, 1], found 1.5"]),
    ("LR<0", "plig 1 1 1 -1 0 0\n", 1, ["plig: LR must be in [0, 255], found -1"]),
    ("LG>255", "plig 1 1 1 0 256 0\n", 1, ["plig: LG must be in [0, 255], found 256"]),
    ("LB>255", "plig 1 1 1 0 0 255.5\n", 1, ["plig: LB must be in [0, 255], found 255.5"]),
    ("BR<0", "back -1 0 0\n", 1, ["back: BR must be in [0, 255], found -1"]),
    ("BG>255", "back 0 300 0\n", 1, ["back: BG must be in [0, 255], found 300"]),
    ("BB>255", "back 0 0 1e3\n", 1, ["back: BB must be in [0, 255], found 1e3"]),
    ("r=0", "sphe 0 0 0 0\n", 1, ["sphe: r must be > 0, found 0"]),
    ("r<0", "sphe 0 0 0 -2\n", 1, ["sphe: r must be > 0, found -2"]),
    ("r-rounds-to-0", "sphe 0 0 0 1e-50\n", 1, ["sphe: r must be > 0, found 1e-50 (= 0 in float32)"]),
    ("ha=0", "vang 0 30\n", 1, ["vang: ha must be in (0, 180) degrees, found 0"]),
    ("ha=180", "vang 180 30\n", 1, ["vang: ha must be in (0, 180) degrees, found 180"]),
    ("ha-rounds-to-180", "vang 179.999999999 30\n", 1, ["vang: ha must be in (0, 180)", "found 179.999999999 (= 180 in float32)"]),
    ("va<0", "vang 40 -30\n", 1, ["vang: va must be in (0, 180) degrees, found -30"]),
    ("va>180", "vang 40 200\n", 1, ["vang: va must be in (0, 180) degrees, found 200"]),
    ("size=0", "size 0\n", 1, [f"size: is must be an integer in [1, {MAX_SIDE}], found 0"]),
    ("size<0", "size -3\n", 1, ["size: is must be an integer in [1,", "found -3"]),
    ("size-fraction", "size 2.5\n", 1, ["size: is must be an integer in [1,", "found 2.5"]),
    ("size-huge", "size 1e10\n", 1, ["size: is must be an integer in [1, 2147483647], found 1e10"]),
    ("height-huge", "eyep 1 0 0\nrefp 0 0 0\nvang 1 179\nsize 2000000000\nrend a.ras\n", 5,
     ["rend: size 2000000000 with vang 1 179 makes the image taller than 2147483647 pixels"]),
    # a zero light vector (also when it rounds to zero)
    ("light-zero", "plig 0 0 0 255 255 255\n", 1, ["plig: the light vector (lx ly lz) must not be zero, found 0 0 0"]),
    ("light-signed-zero", "plig -0 0. 0e5 1 1 1\n", 1, ["plig: the light vector (lx ly lz) must not be zero, found -0 0. 0e5"]),
    ("light-rounds-to-zero", "plig 1e-50 0 0 1 1 1\n", 1, ["plig: the light vector", "must not be zero, found 1e-50 (= 0 in float32) 0 0"]),
    # the camera
    ("eye=refp", "eyep 1 2 3\nrefp 1 2 3.0\nvang 40 30\nsize 4\nrend a.ras\n", 5,
     ["rend: eyep (line 1) equals refp (line 2): the view has no direction"]),
    ("eye=refp-float32", "eyep 0 0 0\nvang 40 30\nsize 4\nrefp 1e-50 0 0\nrend a.ras\n", 5, ["rend: eyep (line 1) equals refp (line 4)"]),
    ("eye=refp-later", CAMERA + "rend a.ras\neyep 0 0 0\nrend b.ras\n", 7, ["rend: eyep (line 6) equals refp (line 2)"]),
    ("rend-no-camera", "rend a.ras\n", 1, ["rend: the camera is incomplete: eyep, refp, vang, size must come before rend"]),
    ("rend-no-eyep", "refp 0 0 0\nvang 40 30\nsize 4\nrend a.ras\n", 4, ["rend: the camera is incomplete: eyep must come before rend"]),
    ("rend-no-refp", "eyep 1 0 0\nvang 40 30\nsize 4\nrend a.ras\n", 4, ["rend: the camera is incomplete: refp must come before rend"]),
    ("rend-no-vang", "eyep 1 0 0\nrefp 0 0 0\nsize 4\nrend a.ras\n", 4, ["rend: the camera is incomplete: vang must come before rend"]),
    ("rend-no-size", "eyep 1 0 0\nrefp 0 0 0\nvang 40 30\nrend a.ras\n", 4, ["rend: the camera is incomplete: size must come before rend"]),
    ("rend-no-vang-size", "eyep 1 0 0\nrefp 0 0 0\nrend a.ras\n", 3, ["rend: the camera is incomplete: vang, size must come before rend"]),
    ("rend-camera-after", "eyep 1 0 0\nrefp 0 0 0\nvang 40 30\nrend a.ras\nsize 4\n", 4, ["size must come before rend"]),
    # materials and spheres
    ("opaq-no-sphere", "opaq 1 1 1 0 1\n", 1, ["opaq has no sphere above it (a material line follows a sphe line)"]),
    ("mirr-no-sphere", "# a comment\nmirr\n", 2, ["mirr has no sphere above it"]),
    ("trpa-no-sphere", "trpa 0.5 1.5 0 1\n", 1, ["trpa has no sphere above it"]),
    ("tmap-no-sphere", "tmap missing.ras\n", 1, ["tmap has no sphere above it"]),
    ("second-material", "sphe 0 0 0 1\nopaq 1 1 1 0 1\nmirr\n", 3, ["mirr: the sphere on line 1 already has a material (opaq on line 2)"]),
    ("second-material-same", "sphe 0 0 0 1\nmirr\nmirr\n", 3, ["mirr: the sphere on line 1 already has a material (mirr on line 2)"]),
    ("material-after-rend", SPHERE + CAMERA + "rend a.ras\ntrpa 0.5 1.5 0 1\n", 8, ["trpa: the sphere on line 1 already has a material (opaq on line 2)"]),
    ("sphe-before-sphe", "sphe 0 0 0 1\nsphe 0 0 5 1\nopaq 1 1 1 0 1\n", 1,
     ["sphe has no material line after it (expected opaq, mirr, trpa or tmap before the sphe on line 2)"]),
    ("sphe-before-rend", CAMERA + "sphe 0 0 0 1\nrend a.ras\n", 5, ["sphe has no material line after it", "before the rend on line 6"]),
    ("sphe-at-end", SPHERE + "sphe 0 0 5 1\n\n# nothing more\n", 3, ["sphe has no material line after it", "before the end of the deck"]),
    ("sphe-at-quit", "sphe 0 0 5 1\nquit\nopaq 1 1 1 0 1\n", 1, ["sphe has no material line after it", "before the end of the deck"]),
]


@pytest.mark.parametrize("text, line, fragments", [e[1:] for e in ERRORS], ids=[e[0] for e in ERRORS])
def test_every_rule_broken_once(text, line, fragments):
    err = deck_error(text)
    message = str(err)
    assert message.startswith(f"t.dat:{line}: "), message
    assert (err.file, err.line) == ("t.dat", line)
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    assert "\n" not in message and "\r" not in message


def test_error_table_covers_every_command_count():
    ids = {e[0] for e in ERRORS}
    for cmd in ("sphe", "opaq", "mirr", "trpa", "tmap", "plig", "back", "elig", "eyep", "refp", "vang", "size", "rend", "quit"):
        assert any(i.startswith(cmd + "-") and i.split("-")[1].isdigit() for i in ids), cmd


def test_error_names_the_deck_file(tmp_path):
    deck = tmp_path / "broken.dat"
    deck.write_text("sphe 0 0 0 1\nopaq 1 1 1 0\n")
    with pytest.raises(DeckError, match=r"^broken\.dat:2: opaq takes 5 numbers \(dR dG dB ks beta\), found 4: 1 1 1 0$"):
        load_deck(deck)


def test_tmap_missing_texture_names_its_path(tmp_path):
    deck = tmp_path / "t.dat"
    deck.write_text("sphe 0 0 0 1\ntmap nope.ras 0.5 2\n")
    with pytest.raises(DeckError) as info:
        load_deck(deck)
    message = str(info.value)
    assert message.startswith("t.dat:2: tmap: cannot read texture 'nope.ras': ")
    assert str(tmp_path / "nope.ras") in message and "No such file" in message


@pytest.mark.parametrize(
    "name, content, fragment",
    [
        ("bad.ras", b"\x59\xa6\x6a\x95" + bytes(10), "truncated"),  # a Sun raster header cut short
        ("bad.ras", b"\x59\xa6\x6a\x95" + (3).to_bytes(4, "big") * 2 + (24).to_bytes(4, "big") + bytes(16) + bytes(5), "truncated"),
        ("bad.ras", b"not an image at all " * 3, "not a Sun raster file"),
        ("bad.png", b"\x89PNG\r\n\x1a\n" + bytes(20), "cannot read"),
        ("bad.tif", b"", "cannot read"),
    ],
)
def test_tmap_corrupt_texture(tmp_path, name, content, fragment):
    (tmp_path / name).write_bytes(content)
    (tmp_path / "t.dat").write_text(SPHERE + f"sphe 0 0 3 1\ntmap {name}\n")
    with pytest.raises(DeckError) as info:
        load_deck(tmp_path / "t.dat")
    message = str(info.value)
    assert message.startswith(f"t.dat:4: tmap: cannot read texture '{name}': ") and fragment in message, message
    assert "\n" not in message


def test_tmap_a_folder_or_a_name_with_nul(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "t.dat").write_text("sphe 0 0 0 1\ntmap sub\n")
    with pytest.raises(DeckError, match=r"^t\.dat:2: tmap: cannot read texture 'sub'"):
        load_deck(tmp_path / "t.dat")
    (tmp_path / "t.dat").write_text("sphe 0 0 0 1\ntmap a\x00b\n")
    with pytest.raises(DeckError, match=r"^t\.dat:2: tmap: cannot read texture 'a\\x00b'"):
        load_deck(tmp_path / "t.dat")


def test_tmap_without_a_loader():
    with pytest.raises(DeckError, match=r"^t\.dat:2: tmap: textures cannot be loaded here"):
        parse_deck("sphe 0 0 0 1\ntmap a.ras\n", "t.dat")


def test_tmap_loader_returning_a_bad_shape():
    with pytest.raises(DeckError, match=r"^t\.dat:2: tmap: texture 'a.ras' has shape \(2, 2\)"):
        parse_deck("sphe 0 0 0 1\ntmap a.ras\n", "t.dat", load_texture=lambda p: np.zeros((2, 2)))


@pytest.mark.parametrize(
    "data, line, byte",
    [
        (b"sphe 0 0 0 1\nopaq 1 1 1 0 1\n# caf\xe9\n", 3, "0xe9"),
        (b"\xff\xfesphe\n", 1, "0xff"),
        (b"# ok\r\n# ok\r\nrend \xc3(\n", 3, "0xc3"),
        (b"# ok\r# ok\rrend \x80\n", 3, "0x80"),  # old Mac line breaks count too
    ],
)
def test_non_utf8_deck(tmp_path, data, line, byte):
    (tmp_path / "latin1.dat").write_bytes(data)
    with pytest.raises(DeckError) as info:
        load_deck(tmp_path / "latin1.dat")
    assert str(info.value) == f"latin1.dat:{line}: the deck is not UTF-8 text (byte {byte})"


def test_unreadable_deck(tmp_path):
    with pytest.raises(DeckError, match=r"^missing\.dat: cannot read the deck: No such file"):
        load_deck(tmp_path / "missing.dat")
    with pytest.raises(DeckError, match=r"cannot read the deck"):
        load_deck(tmp_path)


# ---- semantics ---------------------------------------------------------------------------


def params(deck: Deck, frame: int = 0):
    return jax.tree_util.tree_map(np.asarray, deck.frames[frame].scene.params)


def test_comments_blank_lines_and_tabs():
    text = (
        "##### a header #####\n"
        "\n"
        "   \t  \n"
        "sphe\t1.\t2  3\t 4  # a sphere, tab separated\n"
        "\topaq 1 0.5 0.25 0.1 10#glued comment\n"
        "# eyep 0 0 0   (commented out)\n"
        "eyep 10 0 0\nrefp 0 0 0\nvang 40 30\nsize 4\n"
        "rend a.ras  # the output\n"
        "elig 2\n"  # line 12: the line count survives comments and blank lines
    )
    err = deck_error(text)
    assert err.line == 12
    deck = parse(text.rsplit("elig", 1)[0])
    p = params(deck)
    assert np.array_equal(p.centers, [[1, 2, 3]]) and np.array_equal(p.radii, [4])
    assert np.array_equal(p.diffuse, [[1, 0.5, 0.25]]) and p.ks[0] == np.float32(0.1) and p.beta[0] == 10
    assert np.array_equal(p.eye, [10, 0, 0])
    assert deck.frames[0].output == "a.ras" and deck.frames[0].line == 11


def test_line_endings_and_byte_order_mark():
    for sep in ("\r\n", "\r", "\n"):
        text = "\ufeff" + sep.join(["# x", "", "sphe 0 0 0 1", "opaq 1 1 1 0 1 9"]) + sep
        assert deck_error(text).line == 4
    # A form feed or U+2028 is blank space inside a line, not a line break.
    assert deck_error("sphe 0\x0c0 0 1\nopaq 1 1 1 0\n").line == 2
    assert len(parse(SPHERE + "eyep\u20281 0 0\nrefp 0 0 0\nvang 40 30\nsize 4\nrend a.ras\n").frames) == 1


def test_number_syntax():
    deck = parse("sphe 0. -20 1e-3 .5\nopaq +1 1E0 0.0 1e-1 2.5e1\n" + CAMERA + "rend a.ras\n")
    p = params(deck)
    assert np.array_equal(p.centers, np.array([[0, -20, 1e-3]], np.float32))
    assert p.radii[0] == 0.5 and p.beta[0] == 25 and p.ks[0] == np.float32(0.1)
    assert p.centers.dtype == np.float32


def test_size_accepts_integral_floats():
    deck = parse(CAMERA.replace("size 4", "size 4e1") + "rend a.ras\nsize 40.0\nrend b.ras\n")
    assert [f.scene.structure.width for f in deck.frames] == [40, 40]
    assert deck.frames[0].scene.structure.height == 29  # round(40·tan 15°/tan 20°) = round(29.44)


def test_boundary_values_are_accepted():
    text = (
        "sphe 0 0 0 1e-30\nopaq 0 0 1 1 1\n"
        "sphe 0 0 5 3e38\ntrpa 0 1 0 1\n"
        "sphe 0 0 9 1\ntrpa 1 1000 1 5000\n"
        "plig 0 0 -1e-30 0 0 255\nback 255 0 255\nelig 1\n"
        "eyep 10 0 0\nrefp 0 0 0\nvang 0.001 179.99\nsize 1\nrend a.ras\n"
    )
    p = params(parse(text))
    assert np.array_equal(p.radii, np.array([1e-30, 3e38, 1], np.float32))
    assert np.array_equal(p.ior, [1, 1, 1000]) and np.array_equal(p.kt, [0, 0, 1])
    assert np.array_equal(p.light_dirs, np.array([[0, 0, -1e-30]], np.float32))
    assert p.ke == 1 and np.array_equal(p.background, [255, 0, 255])


def test_state_is_replaced_by_later_lines():
    text = (
        SPHERE
        + "back 1 2 3\nelig 0.1\n"
        + CAMERA
        + "back 10 20 30\nelig 0.5\neyep 0 10 0\nvang 60 45\nsize 8\n"
        + "rend a.ras\n"
    )
    deck = parse(text)
    p, s = params(deck), deck.frames[0].scene.structure
    assert np.array_equal(p.background, [10, 20, 30]) and p.ke == np.float32(0.5)
    assert np.array_equal(p.eye, [0, 10, 0]) and np.array_equal(p.vang, [60, 45])
    assert (s.width, s.height) == (8, 6)  # round(8·tan 22.5°/tan 30°) = round(5.74)


def test_lights_add_up():
    deck = parse("plig 1 0 0 10 20 30\nplig 0 1 0 40 50 60\n" + CAMERA + "rend a.ras\nplig 0 0 1 1 1 1\nrend b.ras\n")
    assert [f.scene.structure.n_lights for f in deck.frames] == [2, 3]
    p = params(deck, 1)
    assert np.array_equal(p.light_dirs, [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert np.array_equal(p.light_colors, [[10, 20, 30], [40, 50, 60], [1, 1, 1]])


def test_defaults():
    deck = parse(CAMERA + "rend a.ras\n")
    s, p = deck.frames[0].scene.structure, params(deck)
    assert s.kinds == () and s.n_lights == 0
    assert np.array_equal(p.background, [0, 0, 0]) and p.ke == 0
    assert p.light_dirs.shape == (0, 3) and p.centers.shape == (0, 3)


def test_several_rend_lines_snapshot_the_scene_as_it_stood():
    text = (
        "sphe 0 0 0 1\nopaq 1 0 0 0 1\n" + CAMERA + "back 0 0 1\nrend one.ras\n"
        "sphe 0 0 3 1\nmirr\neyep 0 10 0\nback 0 0 2\nrend two.ras\n"
        "sphe 0 0 6 1\ntrpa 0.5 1.5 0.1 3\nsize 6\nrend three.ras\n"
    )
    deck = parse(text)
    assert [f.output for f in deck.frames] == ["one.ras", "two.ras", "three.ras"]
    assert [f.line for f in deck.frames] == [8, 13, 17]
    assert [f.scene.structure.kinds for f in deck.frames] == [("opaq",), ("opaq", "mirr"), ("opaq", "mirr", "trpa")]
    assert [f.scene.structure.width for f in deck.frames] == [4, 4, 6]
    first, second, third = (params(deck, i) for i in range(3))
    assert first.centers.shape == (1, 3) and np.array_equal(first.eye, [10, 0, 0]) and first.background[2] == 1
    assert second.centers.shape == (2, 3) and np.array_equal(second.eye, [0, 10, 0]) and second.background[2] == 2
    assert np.array_equal(third.centers, [[0, 0, 0], [0, 0, 3], [0, 0, 6]])
    assert third.kt[2] == np.float32(0.5) and third.ior[2] == 1.5


def test_quit_stops_reading():
    deck = parse(SPHERE + CAMERA + "rend a.ras\nquit\nthis is not a deck\nsphe nan\n\xff garbage 1 2 3\nrend b.ras\n")
    assert [f.output for f in deck.frames] == ["a.ras"]
    assert parse("quit\nrend a.ras\n").frames == ()
    assert parse("quit # done\n").frames == ()


def test_empty_deck_and_deck_without_rend():
    assert parse("").frames == ()
    assert parse("# only comments\n\n").frames == ()
    assert parse(SPHERE + CAMERA).frames == ()


def test_tmap_defaults_and_loading(tmp_path, monkeypatch):
    (tmp_path / "tex").mkdir()
    texture = np.random.default_rng(0).integers(0, 256, (3, 5, 3), dtype=np.uint8)
    write_sunraster(tmp_path / "tex" / "checker.ras", texture)
    (tmp_path / "t.dat").write_text(
        "sphe 0 0 0 1\ntmap tex/checker.ras\nsphe 0 0 3 1\ntmap tex/checker.ras 0.5 7\n" + CAMERA + "rend a.ras\n"
    )
    monkeypatch.chdir(tmp_path / "tex")  # names are relative to the deck's folder, not the cwd
    deck = load_deck(tmp_path / "t.dat")
    s, p = deck.frames[0].scene.structure, params(deck)
    assert s.kinds == ("tmap", "tmap") and s.texture_shapes == ((3, 5), (3, 5))
    assert s.texture_files == ("tex/checker.ras", "tex/checker.ras")
    assert np.array_equal(p.ks, [0, 0.5]) and np.array_equal(p.beta, [1, 7])
    assert all(np.array_equal(t, texture.astype(np.float32)) for t in p.textures)


def test_tmap_texture_is_loaded_once():
    calls = []

    def loader(path):
        calls.append(path)
        return fake_texture(path)

    parse_deck("sphe 0 0 0 1\ntmap a.ras\nsphe 0 0 3 1\ntmap a.ras 0 2\n" + CAMERA + "rend x.ras\n", folder="/decks", load_texture=loader)
    assert calls == [os.path.join("/decks", "a.ras")]


def test_sample_deck():
    deck = load_deck(SAMPLE)
    assert deck.path == "ex2s3.dat" and len(deck.frames) == 1
    frame = deck.frames[0]
    s, p = frame.scene.structure, params(deck)
    assert frame.output == "ex2s3.sunimg" and frame.line == 25
    assert s.kinds == ("opaq", "opaq", "opaq", "mirr", "trpa", "trpa", "trpa", "mirr")
    assert (s.width, s.height, s.n_lights) == (400, 294, 1)
    assert np.array_equal(p.centers[2], [30, -20, 30]) and p.radii[2] == 30
    assert np.array_equal(p.diffuse[1], np.array([1, 0.2, 0.5], np.float32)) and p.ks[1] == np.float32(0.4) and p.beta[1] == 20
    assert np.array_equal(p.ior[4:7], np.array([1.5, 2.42, 1.7], np.float32))
    assert np.array_equal(p.kt[4:7], np.array([0.8, 0.8, 0.9], np.float32))
    assert np.array_equal(p.background, [0, 0, 128]) and p.ke == np.float32(0.2)
    assert np.array_equal(p.light_dirs, [[0.5, 0.5, 2]]) and np.array_equal(p.light_colors, [[255, 255, 255]])
    assert np.array_equal(p.eye, [100, 150, 80]) and np.array_equal(p.refp, [0, 0, 0]) and np.array_equal(p.vang, [40, 30])
    assert all(leaf.dtype == np.float32 for leaf in jax.tree_util.tree_leaves(p))


def test_top_level_api():
    assert rtjax.load_deck is load_deck and rtjax.parse_deck is parse_deck
    assert rtjax.format_deck is format_deck and rtjax.save_deck is save_deck
    assert rtjax.Deck is Deck and rtjax.Frame is Frame


# ---- the writer ----------------------------------------------------------------------------


NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)


def assert_valid_deck_text(text: str) -> None:
    """One command per line with its argument count, numbers in plain syntax; ends with quit."""
    counts = {"sphe": 4, "opaq": 5, "mirr": 0, "trpa": 4, "tmap": 3, "plig": 6, "back": 3, "elig": 1,
              "eyep": 3, "refp": 3, "vang": 2, "size": 1, "rend": 1, "quit": 0}  # fmt: skip
    assert text.endswith("quit\n")
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        cmd, *args = line.split(" ")
        assert len(args) == counts[cmd], line
        numbers = args[1:] if cmd == "tmap" else [] if cmd == "rend" else args
        assert all(NUMBER.fullmatch(a) for a in numbers), line


def round_trip(deck: Deck, folder: str = ".", **kw) -> Deck:
    text = format_deck(deck.frames, **kw)
    assert_valid_deck_text(text)
    again = parse_deck(text, "written.dat", folder=folder, load_texture=load_image)
    assert deck.frames
    assert_same_frames(deck, again)
    assert format_deck(again.frames, **kw) == text  # writing is a fixed point
    return again


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(SCENES, "*.dat"))), ids=os.path.basename)
def test_writer_round_trips_scene_decks(path):
    round_trip(load_deck(path), folder=os.path.dirname(path))


def test_writer_round_trips_the_sample_deck_with_a_header():
    deck = load_deck(SAMPLE)
    text = format_deck(deck.frames, header="fitted by rtjax\nsecond line")
    assert text.startswith("# fitted by rtjax\n# second line\nsphe 0 0 0 20\nopaq 1 1 0 0.2 10\n")
    assert "\nrend ex2s3.sunimg\nquit\n" in text
    round_trip(deck, header="fitted by rtjax\nsecond line")


def test_writer_multi_frame_adds_only_new_spheres_and_lights():
    text = (
        "sphe 0 0 0 1\nopaq 1 0 0 0 1\nplig 1 0 0 9 9 9\n" + CAMERA + "rend one.ras\n"
        "sphe 0 0 3 1\nmirr\nplig 0 1 0 8 8 8\neyep 0 10 0\nrend two.ras\n"
        "size 6\nrend three.ras\n"
    )
    deck = parse(text)
    written = format_deck(deck.frames)
    assert written.count("sphe ") == 2 and written.count("plig ") == 2 and written.count("rend ") == 3
    round_trip(deck)


def test_writer_keeps_every_bit():
    values = ["-0", "0.1", "0.30000001", "1.1754944e-38", "1e-45", "3.4028235e38", "-123456.79", "16777217", "1e16", "9.999999e15"]
    for v in values:
        text = f"sphe {v} {v} {v} 1\nmirr\neyep 10 0 0\nrefp 0 0 0\nvang 40 30\nsize 4\nrend a.ras\n"
        round_trip(parse(text))
    deck = parse("sphe -0. 0 0 1\nmirr\n" + CAMERA + "rend a.ras\n")
    assert format_deck(deck.frames).startswith("sphe -0 0 0 1\n")
    assert np.signbit(params(round_trip(deck)).centers[0, 0])


def test_writer_round_trips_textures(tmp_path):
    write_sunraster(tmp_path / "t.ras", np.random.default_rng(1).integers(0, 256, (1, 1, 3), dtype=np.uint8))
    (tmp_path / "t.dat").write_text("sphe 0 0 0 1\ntmap t.ras\nsphe 0 0 3 1\ntmap t.ras 0.25 3\n" + CAMERA + "rend a.ras\n")
    deck = load_deck(tmp_path / "t.dat")
    assert "tmap t.ras 0 1\n" in format_deck(deck.frames)
    save_deck(tmp_path / "copy.dat", deck.frames)
    assert deck.frames
    assert_same_frames(deck, load_deck(tmp_path / "copy.dat"))
    assert sorted(os.listdir(tmp_path)) == ["copy.dat", "t.dat", "t.ras"]  # no temporary file left


def test_writer_into_a_folder_that_cannot_be_written_is_one_error(tmp_path):
    """A deck written below a file: an RtjaxError naming the path (it was an OSError
    naming the temporary file), nothing left behind."""
    deck = parse("sphe 0 0 0 1\nmirr\n" + CAMERA + "rend a.ras\n")
    (tmp_path / "file").write_text("keep me")
    with pytest.raises(rtjax.RtjaxError, match=f"^{tmp_path / 'file' / 'd.dat'}: cannot write: "):
        save_deck(tmp_path / "file" / "d.dat", deck.frames)
    assert sorted(os.listdir(tmp_path)) == ["file"] and (tmp_path / "file").read_text() == "keep me"


def test_writer_single_scene_and_fitted_values():
    scene = load_deck(SAMPLE).frames[0].scene
    fitted = scene.replace(ke=np.float32(0.123456789), radii=scene.params.radii * np.float32(1.1))
    text = format_deck(fitted, output="fit.sunimg")
    assert "\nelig 0.12345679\n" in text and "\nrend fit.sunimg\n" in text
    again = parse_deck(text).frames[0].scene
    assert np.asarray(again.params.radii).tobytes() == np.asarray(fitted.params.radii).tobytes()
    assert format_deck(scene).rstrip().endswith("rend out.sunimg\nquit")


def test_writer_refuses_what_a_deck_cannot_say():
    deck = parse("sphe 0 0 0 1\nopaq 1 0 0 0 1\n" + CAMERA + "rend one.ras\nsphe 0 0 3 1\nmirr\nrend two.ras\n")
    with pytest.raises(RtjaxError, match="cannot remove or change"):
        format_deck([deck.frames[1], deck.frames[0]])  # the later frame drops a sphere
    moved = deck.frames[1].scene.replace(centers=np.array([[0, 0, 1], [0, 0, 3]], np.float32))
    with pytest.raises(RtjaxError, match="cannot remove or change"):
        format_deck([deck.frames[0], Frame(moved, "two.ras", 0)])
    for name in ("two words.ras", "", "a#b.ras", "tab\t.ras", "nl\n.ras"):
        with pytest.raises(RtjaxError, match="rend output name"):
            format_deck(deck.frames[0].scene, output=name)
    with pytest.raises(RtjaxError, match="finite"):
        format_deck(deck.frames[0].scene.replace(ke=np.float32(np.nan)))
