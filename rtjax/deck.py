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

_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")

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

    # -- errors and argument checking -------------------------------------------------
    def error(self, message: str, line: int | None = None) -> DeckError:
        return DeckError(self.name, self.line if line is None else line, message)

    def numbers(self, args: list[str], names: Sequence[str]) -> list[float]:
        if len(args) != len(names):
            plural = "number" if len(names) == 1 else "numbers"
            raise self.error(
                f"{self.cmd} takes {len(names)} {plural} ({' '.join(names)}), found {len(args)}"
                + (f": {' '.join(args)}" if args else "")
            )
        return [self.number(a, n) for a, n in zip(args, names)]

    def number(self, text: str, name: str) -> float:
        if not _NUMBER.fullmatch(text):
            raise self.error(f"{self.cmd}: {name} must be a number, found {text!r}")
        value = float(text)
        if not math.isfinite(value):
            raise self.error(f"{self.cmd}: {name} must be a finite number, found {text!r}")
        return value

    def check(self, ok: bool, name: str, value: float, expected: str) -> None:
        if not ok:
            raise self.error(f"{self.cmd}: {name} must be {expected}, found {value:g}")

    def unit(self, values, names):
        for v, n in zip(values, names):
            self.check(0 <= v <= 1, n, v, "in [0, 1]")

    def level(self, values, names):
        for v, n in zip(values, names):
            self.check(0 <= v <= 255, n, v, "in [0, 255]")

    # -- commands ---------------------------------------------------------------------
    def material_target(self) -> _Sphere:
        if not self.spheres:
            raise self.error(f"{self.cmd} has no sphere above it (a material line follows a sphe line)")
        s = self.spheres[-1]
        if s.kind is not None:
            raise self.error(
                f"{self.cmd}: the sphere on line {s.line} already has a material ({s.kind} on line {s.material_line})"
            )
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
            raise self.error(f"tmap takes a file name and optionally 2 numbers (file [ks beta]), found {len(a)} arguments")
        ks, beta = self.numbers(a[1:], ("ks", "beta")) if len(a) == 3 else (0.0, 1.0)
        self.unit((ks,), ("ks",))
        self.check(beta >= 1, "beta", beta, "≥ 1")
        name = a[0]
        if name not in self.textures:
            path = os.path.join(self.folder, name)
            if self.load_texture is None:
                raise self.error("tmap: textures cannot be loaded here")
            try:
                self.textures[name] = self.load_texture(path)
            except (RtjaxError, OSError) as e:
                raise self.error(f"tmap: cannot read texture {name!r}: {e}") from None
        s = self.material_target()
        s.ks, s.beta, s.texture = ks, beta, name

    def do_plig(self, a):
        v = self.numbers(a, COMMANDS["plig"])
        if v[0] == v[1] == v[2] == 0:
            raise self.error("plig: the light vector (lx ly lz) must not be zero, found 0 0 0")
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
        (n,) = self.numbers(a, COMMANDS["size"])
        self.check(n >= 1 and n == int(n), "is", n, "an integer ≥ 1")
        self.size = int(n)

    def do_rend(self, a):
        if len(a) != 1:
            raise self.error(f"rend takes 1 file name, found {len(a)} arguments")
        self.require_material(f"the rend on line {self.line}")
        missing = [c for c, v in (("eyep", self.eye), ("refp", self.refp), ("vang", self.vang), ("size", self.size)) if v is None]
        if missing:
            raise self.error(f"rend: the camera is incomplete: {', '.join(missing)} must come before rend")
        if self.eye == self.refp:
            raise self.error(
                f"rend: eyep (line {self.set_at['eyep']}) equals refp (line {self.set_at['refp']}): the view has no direction"
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
        for self.line, raw in enumerate(text.splitlines(), start=1):
            tokens = raw.split("#", 1)[0].split()
            if not tokens:
                continue
            self.cmd, args = tokens[0], tokens[1:]
            if self.cmd == "quit":
                if args:
                    raise self.error(f"quit takes no arguments, found {len(args)}")
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
    except OSError as e:
        raise DeckError(name, None, f"cannot read the deck: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise DeckError(name, line, f"the deck is not UTF-8 text (byte 0x{data[e.start]:02x})") from None
    return parse_deck(text, name, os.path.dirname(os.path.abspath(path)), load_image)


# -- writing ---------------------------------------------------------------------------------
def _fmt(x) -> str:
    """The shortest text that reads back to the same float32/float64 value."""
    x = np.asarray(x)[()]  # a NumPy scalar keeps its precision (0-d arrays print as float64)
    s = np.format_float_positional(x, unique=True, trim="-") if abs(float(x)) < 1e16 else np.format_float_scientific(x, unique=True, trim="-")
    return "0" if s in ("-0", "+0") else s


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
            material = _line("tmap", s.texture_files[t], p.ks[i], p.beta[i])
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
        frames = [Frame(frames, output or "out.sunimg", 0)]
    out = [f"# {h}" if h else "#" for h in (header or "").splitlines()]
    done_spheres: list[str] = []
    done_lights: list[str] = []
    for fr in frames:
        spheres, lights, state = _scene_parts(fr.scene)
        if spheres[: len(done_spheres)] != done_spheres or lights[: len(done_lights)] != done_lights:
            raise RtjaxError("a later frame must keep the earlier frames' spheres and lights: decks cannot remove or change them")
        out += spheres[len(done_spheres) :] + lights[len(done_lights) :] + state + [_line("rend", fr.output)]
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
