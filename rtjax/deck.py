"""The deck language (DECK.md §1): parser with `file:line:` errors, and the writer.

A deck is read line by line into a running state; every `rend` takes a snapshot of
that state as a `Frame` (a `Scene` and its output name). The writer turns scenes back
into deck text such that parse → write → parse gives the same scenes.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

from .camera import image_height
from .errors import DeckError, RtjaxError
from .scene import GLASS, MIRROR, OPAQUE, TEXTURE, Params, Scene, Structure

# Ordinary float syntax, ASCII digits only (`\d` alone would accept any Unicode digit).
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
# Line breaks as editors and Python's text mode count them; any other character that
# str.splitlines() would break at (form feed, U+2028, ...) is blank space inside a line.
_LINE_BREAK = re.compile(r"\r\n|\r|\n")
_LINE_BREAK_BYTES = re.compile(rb"\r\n|\r|\n")
#: Scenes are float32: a number is rounded to float32 as it is read, and must stay finite.
_F32_MAX = float(np.finfo(np.float32).max)
#: The largest image side a deck may ask for (32-bit indices, the Sun raster header).
MAX_SIDE = 2**31 - 1

#: command → (argument names for messages); `tmap` and `rend` take a file name.
COMMANDS: dict[str, tuple[str, ...]] = {
    "sphe": ("xc", "yc", "zc", "r"),
    "opaq": ("dR", "dG", "dB", "ks", "beta"),
    "mirr": (),
    "trpa": ("kt", "n", "ks", "beta"),
    "tmap": ("file", "[ks beta]"),
    "plig": ("lx", "ly", "lz", "LR", "LG", "LB"),
    "back": ("BR", "BG", "BB"),
    "elig": ("ke",),
    "eyep": ("xv", "yv", "zv"),
    "refp": ("xf", "yf", "zf"),
    "vang": ("ha", "va"),
    "size": ("is",),
    "rend": ("file",),
    "quit": (),
}
MATERIALS = ("opaq", "mirr", "trpa", "tmap")


@dataclasses.dataclass(frozen=True)
class Frame:
    """One `rend`: the scene as it stood and the output name as written."""

    scene: Scene
    output: str
    line: int


@dataclasses.dataclass(frozen=True)
class Deck:
    """A parsed deck: its path and one frame per `rend` line."""

    path: str
    frames: tuple[Frame, ...]


@dataclasses.dataclass
class _Sphere:
    line: int
    center: tuple[float, float, float]
    radius: float
    kind: str | None = None
    material_line: int = 0
    diffuse: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ks: float = 0.0
    beta: float = 1.0
    kt: float = 0.0
    ior: float = 1.0
    texture: str = ""


def _show(text: str) -> str:
    """A token as it reads in a one-line message: as is if printable, else escaped."""
    return text if text.isprintable() else repr(text)[1:-1]


def _to_f32(value: float) -> float:
    """`value` rounded to float32 (inf when out of range), back as a Python float."""
    with np.errstate(over="ignore"):
        return float(np.float32(value))


class _Parser:
    def __init__(self, name: str, folder: str, load_texture: Callable[[str], np.ndarray] | None):
        self.name = name
        self.folder = folder
        self.load_texture = load_texture
        self.spheres: list[_Sphere] = []
        self.lights: list[tuple[tuple[float, ...], tuple[float, ...]]] = []
        self.back = (0.0, 0.0, 0.0)
        self.ke = 0.0
        self.eye: tuple[float, ...] | None = None
        self.refp: tuple[float, ...] | None = None
        self.vang: tuple[float, ...] | None = None
        self.size: int | None = None
        self.set_at: dict[str, int] = {}
        self.textures: dict[str, np.ndarray] = {}
        self.frames: list[Frame] = []
        self.line = 0
        self.cmd = ""
        self.texts: dict[str, str] = {}  # argument name → text, for messages

    # -- errors and argument checking -------------------------------------------------
    def error(self, message: str, line: int | None = None) -> DeckError:
        return DeckError(self.name, self.line if line is None else line, message)

    def numbers(self, args: list[str], names: Sequence[str], f32: bool = True) -> list[float]:
        if len(args) != len(names):
            if not names:
                raise self.error(f"{self.cmd} takes no arguments, found {len(args)}: {' '.join(map(_show, args))}")
            plural = "number" if len(names) == 1 else "numbers"
            raise self.error(
                f"{self.cmd} takes {len(names)} {plural} ({' '.join(names)}), found {len(args)}"
                + (f": {' '.join(map(_show, args))}" if args else "")
            )
        return [self.number(a, n, f32) for a, n in zip(args, names)]

    def number(self, text: str, name: str, f32: bool = True) -> float:
        """A number as the scene stores it: rounded to float32, finite (`f32`), or as written."""
        self.texts[name] = text
        if _NONFINITE.fullmatch(text):
            raise self.error(f"{self.cmd}: {name} must be a finite number, found {_show(text)}")
        if not _NUMBER.fullmatch(text):
            raise self.error(f"{self.cmd}: {name} must be a number, found {_show(text)}")
        value = float(text)
        if not f32:
            if not math.isfinite(value):
                raise self.error(f"{self.cmd}: {name} must be a finite number, found {_show(text)}")
            return value
        if not math.isfinite(_to_f32(value)):
            raise self.error(
                f"{self.cmd}: {name} must be a finite number within float32 range (|x| ≤ {_F32_MAX:.7g}), found {_show(text)}"
            )
        return _to_f32(value)

    def found(self, name: str, value: float) -> str:
        """How a value was written, and what it became when that differs (float32 rounding)."""
        text = self.texts.get(name)
        if text is None:
            return f"{value:g}"
        return _show(text) if float(text) == value else f"{_show(text)} (= {value:g} in float32)"

    def check(self, ok: bool, name: str, value: float, expected: str) -> None:
        if not ok:
            raise self.error(f"{self.cmd}: {name} must be {expected}, found {self.found(name, value)}")

    def unit(self, values, names):
        for v, n in zip(values, names):
            self.check(0 <= v <= 1, n, v, "in [0, 1]")

    def level(self, values, names):
        for v, n in zip(values, names):
            self.check(0 <= v <= 255, n, v, "in [0, 255]")

    # -- commands ---------------------------------------------------------------------
    def pending_sphere(self) -> _Sphere:
        """The sphere a material line applies to (the last one, still without a material)."""
        if not self.spheres:
            raise self.error(f"{self.cmd} has no sphere above it (a material line follows a sphe line)")
        s = self.spheres[-1]
        if s.kind is not None:
            raise self.error(
                f"{self.cmd}: the sphere on line {s.line} already has a material ({s.kind} on line {s.material_line})"
            )
        return s

    def material_target(self) -> _Sphere:
        s = self.pending_sphere()
        s.kind, s.material_line = self.cmd, self.line
        return s

    def require_material(self, before: str) -> None:
        if self.spheres and self.spheres[-1].kind is None:
            s = self.spheres[-1]
            raise self.error(
                f"sphe has no material line after it (expected opaq, mirr, trpa or tmap before {before})", s.line
            )

    def do_sphe(self, a):
        self.require_material(f"the sphe on line {self.line}")
        x, y, z, r = self.numbers(a, COMMANDS["sphe"])
        self.check(r > 0, "r", r, "> 0")
        self.spheres.append(_Sphere(self.line, (x, y, z), r))

    def do_opaq(self, a):
        dr, dg, db, ks, beta = self.numbers(a, COMMANDS["opaq"])
        self.unit((dr, dg, db, ks), ("dR", "dG", "dB", "ks"))
        self.check(beta >= 1, "beta", beta, "≥ 1")
        s = self.material_target()
        s.diffuse, s.ks, s.beta = (dr, dg, db), ks, beta

    def do_mirr(self, a):
        self.numbers(a, ())
        self.material_target()

    def do_trpa(self, a):
        kt, n, ks, beta = self.numbers(a, COMMANDS["trpa"])
        self.unit((kt, ks), ("kt", "ks"))
        self.check(n >= 1, "n", n, "≥ 1")
        self.check(beta >= 1, "beta", beta, "≥ 1")
        s = self.material_target()
        s.kt, s.ior, s.ks, s.beta = kt, n, ks, beta

    def do_tmap(self, a):
        if len(a) not in (1, 3):
            raise self.error(
                f"tmap takes a file name and optionally 2 numbers (file [ks beta]), found {len(a)} arguments"
                + (f": {' '.join(map(_show, a))}" if a else "")
            )
        ks, beta = self.numbers(a[1:], ("ks", "beta")) if len(a) == 3 else (0.0, 1.0)
        self.unit((ks,), ("ks",))
        self.check(beta >= 1, "beta", beta, "≥ 1")
        self.pending_sphere()  # a material line in the wrong place is reported before its file
        name = a[0]
        if name not in self.textures:
            path = os.path.join(self.folder, name)
            if self.load_texture is None:
                raise self.error(f"tmap: textures cannot be loaded here (texture {name!r})")
            try:
                texture = np.asarray(self.load_texture(path))
            except (RtjaxError, OSError, ValueError, MemoryError) as e:
                reason = " ".join(str(e).split()) or type(e).__name__
                raise self.error(f"tmap: cannot read texture {name!r}: {reason}") from None
            if texture.ndim != 3 or texture.shape[2] != 3 or texture.shape[0] < 1 or texture.shape[1] < 1:
                raise self.error(f"tmap: texture {name!r} has shape {texture.shape}, expected (height, width, 3)")
            self.textures[name] = texture
        s = self.material_target()
        s.ks, s.beta, s.texture = ks, beta, name

    def do_plig(self, a):
        v = self.numbers(a, COMMANDS["plig"])
        if v[0] == v[1] == v[2] == 0:
            found = " ".join(self.found(n, x) for n, x in zip(COMMANDS["plig"][:3], v[:3]))
            raise self.error(f"plig: the light vector (lx ly lz) must not be zero, found {found}")
        self.level(v[3:], COMMANDS["plig"][3:])
        self.lights.append((tuple(v[:3]), tuple(v[3:])))

    def do_back(self, a):
        v = self.numbers(a, COMMANDS["back"])
        self.level(v, COMMANDS["back"])
        self.back = tuple(v)

    def do_elig(self, a):
        (ke,) = self.numbers(a, COMMANDS["elig"])
        self.unit((ke,), ("ke",))
        self.ke = ke

    def do_eyep(self, a):
        self.eye = tuple(self.numbers(a, COMMANDS["eyep"]))
        self.set_at["eyep"] = self.line

    def do_refp(self, a):
        self.refp = tuple(self.numbers(a, COMMANDS["refp"]))
        self.set_at["refp"] = self.line

    def do_vang(self, a):
        v = self.numbers(a, COMMANDS["vang"])
        for x, n in zip(v, COMMANDS["vang"]):
            self.check(0 < x < 180, n, x, "in (0, 180) degrees")
        self.vang = tuple(v)

    def do_size(self, a):
        (n,) = self.numbers(a, COMMANDS["size"], f32=False)  # a count, not a float32 parameter
        self.check(n >= 1 and n == int(n) and n <= MAX_SIDE, "is", n, f"an integer in [1, {MAX_SIDE}]")
        self.size = int(n)

    def do_rend(self, a):
        if len(a) != 1:
            raise self.error(
                f"rend takes 1 file name, found {len(a)} arguments" + (f": {' '.join(map(_show, a))}" if a else "")
            )
        self.require_material(f"the rend on line {self.line}")
        missing = [c for c, v in (("eyep", self.eye), ("refp", self.refp), ("vang", self.vang), ("size", self.size)) if v is None]
        if missing:
            raise self.error(f"rend: the camera is incomplete: {', '.join(missing)} must come before rend")
        if self.eye == self.refp:  # compared as stored (float32), where the view direction is computed
            raise self.error(
                f"rend: eyep (line {self.set_at['eyep']}) equals refp (line {self.set_at['refp']}): the view has no direction"
            )
        ha, va = self.vang
        try:
            height = image_height(self.size, ha, va)
        except OverflowError:
            height = MAX_SIDE + 1
        if height > MAX_SIDE:
            raise self.error(
                f"rend: size {self.size} with vang {ha:g} {va:g} makes the image taller than {MAX_SIDE} pixels"
            )
        self.frames.append(Frame(self.snapshot(), a[0], self.line))

    def snapshot(self) -> Scene:
        sp = self.spheres
        kinds = tuple(s.kind for s in sp)
        tex_names = tuple(s.texture for s in sp if s.kind == TEXTURE)
        textures = tuple(self.textures[t] for t in tex_names)
        ha, va = self.vang
        structure = Structure(
            kinds=kinds,
            n_lights=len(self.lights),
            width=self.size,
            height=image_height(self.size, ha, va),
            texture_shapes=tuple(t.shape[:2] for t in textures),
            texture_files=tex_names,
        )

        def arr(values, shape):
            return np.asarray(values, np.float32).reshape(shape)

        n, nl = len(sp), len(self.lights)
        params = Params(
            centers=arr([s.center for s in sp], (n, 3)),
            radii=arr([s.radius for s in sp], (n,)),
            diffuse=arr([s.diffuse for s in sp], (n, 3)),
            ks=arr([s.ks for s in sp], (n,)),
            beta=arr([s.beta for s in sp], (n,)),
            kt=arr([s.kt for s in sp], (n,)),
            ior=arr([s.ior for s in sp], (n,)),
            light_dirs=arr([l[0] for l in self.lights], (nl, 3)),
            light_colors=arr([l[1] for l in self.lights], (nl, 3)),
            background=arr(self.back, (3,)),
            ke=arr(self.ke, ()),
            eye=arr(self.eye, (3,)),
            refp=arr(self.refp, (3,)),
            vang=arr(self.vang, (2,)),
            textures=tuple(np.asarray(t, np.float32) for t in textures),
        )
        params = params.astype(jnp.float32)
        return Scene(structure, params)

    # -- the loop -----------------------------------------------------------------------
    def parse(self, text: str) -> tuple[Frame, ...]:
        for self.line, raw in enumerate(_LINE_BREAK.split(text), start=1):
            tokens = raw.split("#", 1)[0].split()
            if not tokens:
                continue
            self.cmd, args = tokens[0], tokens[1:]
            self.texts = {}
            if self.cmd == "quit":
                if args:
                    raise self.error(f"quit takes no arguments, found {len(args)}: {' '.join(map(_show, args))}")
                break
            handler = getattr(self, "do_" + self.cmd, None) if self.cmd in COMMANDS else None
            if handler is None:
                raise self.error(f"unknown command {self.cmd!r} (expected one of {', '.join(COMMANDS)})")
            handler(args)
        self.cmd = "end of deck"
        self.require_material("the end of the deck")
        return tuple(self.frames)


def parse_deck(
    text: str,
    name: str = "<deck>",
    folder: str = ".",
    load_texture: Callable[[str], np.ndarray] | None = None,
) -> Deck:
    """Parse deck text; `name` appears in error messages, `folder` resolves `tmap` files."""
    return Deck(name, _Parser(name, folder, load_texture).parse(text.lstrip("\ufeff")))


def load_deck(path: str | os.PathLike) -> Deck:
    """Read and parse a deck file. Raises `DeckError` (`file:line: ...`) on bad input."""
    from .images import load_image  # images imports nothing from here; keep start-up light

    path = os.fspath(path)
    name = os.path.basename(path) or path
    try:
        with open(path, "rb") as f:
            data = f.read()
    except (OSError, ValueError) as e:
        raise DeckError(name, None, f"cannot read the deck: {getattr(e, 'strerror', None) or e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = len(_LINE_BREAK_BYTES.findall(data, 0, e.start)) + 1
        raise DeckError(name, line, f"the deck is not UTF-8 text (byte 0x{data[e.start]:02x})") from None
    return parse_deck(text, name, os.path.dirname(os.path.abspath(path)), load_image)


# -- writing ---------------------------------------------------------------------------------
def _fmt(x) -> str:
    """The shortest text that reads back to the same float32/float64 value."""
    x = np.asarray(x)[()]  # a NumPy scalar keeps its precision (0-d arrays print as float64)
    if not np.isfinite(x):
        raise RtjaxError(f"cannot write {x} into a deck: numbers in a deck are finite")
    # "-0" stays "-0": parse → write → parse keeps every parameter bit for bit.
    return np.format_float_positional(x, unique=True, trim="-") if abs(float(x)) < 1e16 else np.format_float_scientific(x, unique=True, trim="-")


def _name(name: str, what: str) -> str:
    """A file name as one deck token (exactly what the parser reads as one): not empty,
    no blank space or line break, no `#`."""
    if not isinstance(name, str) or not name or name.split() != [name] or "#" in name:
        raise RtjaxError(f"cannot write the {what} name {name!r} into a deck: it must be one word without blanks or '#'")
    return name


def _line(cmd: str, *values) -> str:
    return " ".join([cmd, *(v if isinstance(v, str) else _fmt(v) for v in values)])


def _scene_parts(scene: Scene) -> tuple[list[str], list[str], list[str]]:
    """Deck lines of a scene in three parts: per sphere (sphe + material), per light, state."""
    s, p = scene.structure, jax_to_numpy(scene.params)
    spheres, t = [], 0
    for i, kind in enumerate(s.kinds):
        if kind == OPAQUE:
            material = _line("opaq", *p.diffuse[i], p.ks[i], p.beta[i])
        elif kind == MIRROR:
            material = "mirr"
        elif kind == GLASS:
            material = _line("trpa", p.kt[i], p.ior[i], p.ks[i], p.beta[i])
        else:
            material = _line("tmap", _name(s.texture_files[t], "tmap texture"), p.ks[i], p.beta[i])
            t += 1
        spheres.append(_line("sphe", *p.centers[i], p.radii[i]) + "\n" + material)
    lights = [_line("plig", *d, *c) for d, c in zip(p.light_dirs, p.light_colors)]
    state = [
        _line("back", *p.background),
        _line("elig", p.ke),
        _line("eyep", *p.eye),
        _line("refp", *p.refp),
        _line("vang", *p.vang),
        _line("size", str(s.width)),
    ]
    return spheres, lights, state


def format_deck(frames: Sequence[Frame] | Scene, output: str | None = None, header: str | None = None) -> str:
    """Deck text for one scene or several frames (parse → write → parse is the identity).

    The language only adds spheres and lights, so a later frame must keep the earlier
    frames' spheres and lights unchanged (it may add more); state lines are restated.
    """
    if isinstance(frames, Scene):
        frames = [Frame(frames, "out.sunimg" if output is None else output, 0)]
    out = [f"# {h}" if h else "#" for h in (header or "").splitlines()]
    done_spheres: list[str] = []
    done_lights: list[str] = []
    for fr in frames:
        spheres, lights, state = _scene_parts(fr.scene)
        if spheres[: len(done_spheres)] != done_spheres or lights[: len(done_lights)] != done_lights:
            raise RtjaxError("a later frame must keep the earlier frames' spheres and lights: decks cannot remove or change them")
        out += spheres[len(done_spheres) :] + lights[len(done_lights) :] + state + [_line("rend", _name(fr.output, "rend output"))]
        done_spheres, done_lights = spheres, lights
    out.append("quit")
    return "\n".join(out) + "\n"


def save_deck(path: str | os.PathLike, frames: Sequence[Frame] | Scene, output: str | None = None, header: str | None = None) -> None:
    """Write deck text atomically."""
    from .atomic import atomic_write

    atomic_write(path, format_deck(frames, output, header).encode("utf-8"))


def jax_to_numpy(params: Params) -> Params:
    import jax

    return jax.tree_util.tree_map(np.asarray, params)
