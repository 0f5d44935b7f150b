"""The deck language (DECK.md §1): its commands, the parser with `file:line:` errors, and the writer.

Every command is declared once, in `COMMANDS`: its arguments (name, kind, range, the scene
field each gives) and its meaning. The parser reads a deck line by line against that
table and describes each `rend` by the lines in effect there (`rtjax.assemble.Snapshot`);
`rtjax.assemble` reads the textures they name and builds each frame's `Scene`. The writer
turns scenes back into deck lines from the same table, such that parse → write → parse
gives the same scenes.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

from .assemble import SPHERE_DEFAULTS, Line, Snapshot, Textures, Value, assemble
from .camera import image_height
from .errors import DeckError, RtjaxError, shown, writing
from .scene import TEXTURE, Scene

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


def _to_f32(value: float) -> float:
    """`value` rounded to float32 (inf when out of range), back as a Python float."""
    with np.errstate(over="ignore"):
        return float(np.float32(value))


# -- the commands ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Range:
    """Where a number argument must lie.

    Attributes:
        test: whether a value lies there (the value as stored: rounded to float32 for a
            number, as written for a count).
        expected: the range as a message says it: "<name> must be <expected>, found ...".
    """

    test: Callable[[float], bool]
    expected: str


UNIT = Range(lambda x: 0 <= x <= 1, "in [0, 1]")
LEVEL = Range(lambda x: 0 <= x <= 255, "in [0, 255]")
POSITIVE = Range(lambda x: x > 0, "> 0")
AT_LEAST_ONE = Range(lambda x: x >= 1, "≥ 1")
ANGLE = Range(lambda x: 0 < x < 180, "in (0, 180) degrees")
SIDE = Range(lambda x: 1 <= x <= MAX_SIDE and x == int(x), f"an integer in [1, {MAX_SIDE}]")

#: Argument kinds: a number (rounded to float32, as scenes store it), a count (an
#: integer, read as written), a file name (one word).
NUMBER, COUNT, FILE = "number", "count", "file name"


@dataclasses.dataclass(frozen=True)
class Arg:
    """One argument of a command.

    Attributes:
        name: its name in messages (`xc`, `dR`, `file`).
        field: the scene field it gives (see `rtjax.assemble.Line`); consecutive
            arguments of one field give it together, as a vector (xc yc zc → `centers`).
        range: where its value must lie; None: any finite number, or any file name.
        kind: `NUMBER`, `COUNT` or `FILE`.
        default: its value when left out. Arguments with a default are optional; they
            end the line and are given all or none (tmap's `[ks beta]`).
    """

    name: str
    field: str
    range: Range | None = None
    kind: str = NUMBER
    default: float | None = None


#: What a command's line does: adds a sphere, completes the sphere above it, adds a
#: light, replaces a setting, renders a frame, stops reading.
SPHERE, MATERIAL, LIGHT, STATE, REND, QUIT = "sphere", "material", "light", "state", "rend", "quit"


@dataclasses.dataclass(frozen=True)
class Command:
    """One deck command.

    Attributes:
        name: its keyword.
        role: what a line of it does (`SPHERE`, `MATERIAL`, `LIGHT`, `STATE`, `REND`, `QUIT`).
        meaning: what it says, in a short phrase.
        args: its arguments, in order.
        initial: for a setting, its argument values before any line gives them; None: a
            `rend` needs a line of it first.
    """

    name: str
    role: str
    meaning: str
    args: tuple[Arg, ...] = ()
    initial: tuple[float, ...] | None = None

    @property
    def counts(self) -> tuple[int, int]:
        """The argument counts a line may have: without its optional arguments, with them."""
        return sum(a.default is None for a in self.args), len(self.args)

    @property
    def ranged(self) -> list[Arg]:
        """The arguments with a range, in the order they are checked: range by range, in
        the order the arguments first use them (trpa: kt and ks in [0, 1], then n and beta ≥ 1)."""
        ranged = [a for a in self.args if a.range is not None]
        ranges = [a.range for a in ranged]
        return sorted(ranged, key=lambda a: ranges.index(a.range))

    def miscount(self, args: Sequence[str]) -> str:
        """The message for a line of this command with the wrong number of arguments `args`.

        The table has three shapes: numbers ("takes 4 numbers (xc yc zc r)"), one file
        name, and a file name with an optional group of numbers (tmap).
        """
        found = f"found {len(args)}"
        listed = f": {' '.join(map(shown, args))}" if args else ""
        if not self.args:
            return f"{self.name} takes no arguments, {found}{listed}"
        names = " ".join(a.name for a in self.args if a.default is None)
        optional = [a.name for a in self.args if a.default is not None]
        if optional:
            names += f" [{' '.join(optional)}]"
        if all(a.kind != FILE for a in self.args):
            plural = "number" if len(self.args) == 1 else "numbers"
            return f"{self.name} takes {len(self.args)} {plural} ({names}), {found}{listed}"
        takes = f"a file name and optionally {len(optional)} numbers ({names})" if optional else "1 file name"
        return f"{self.name} takes {takes}, {found} arguments{listed}"


def _numbers(names: str, field: str, range: Range | None = None) -> tuple[Arg, ...]:
    """Number arguments (`names`, blank-separated) that give `field` together."""
    return tuple(Arg(name, field, range) for name in names.split())


#: The deck language: every command by keyword, in the order messages list them.
COMMANDS: dict[str, Command] = {c.name: c for c in (
    Command("sphe", SPHERE, "a sphere", (*_numbers("xc yc zc", "centers"), Arg("r", "radii", POSITIVE))),
    Command("opaq", MATERIAL, "its material: opaque Phong",
            (*_numbers("dR dG dB", "diffuse", UNIT), Arg("ks", "ks", UNIT), Arg("beta", "beta", AT_LEAST_ONE))),
    Command("mirr", MATERIAL, "its material: perfect mirror"),
    Command("trpa", MATERIAL, "its material: transparent, refracting",
            (Arg("kt", "kt", UNIT), Arg("n", "ior", AT_LEAST_ONE), Arg("ks", "ks", UNIT), Arg("beta", "beta", AT_LEAST_ONE))),
    Command("tmap", MATERIAL, "its material: opaque with a texture as diffuse colour",
            (Arg("file", "texture", kind=FILE),
             Arg("ks", "ks", UNIT, default=0.0), Arg("beta", "beta", AT_LEAST_ONE, default=1.0))),
    Command("plig", LIGHT, "adds a parallel light; (lx, ly, lz) points toward the light",
            (*_numbers("lx ly lz", "light_dirs"), *_numbers("LR LG LB", "light_colors", LEVEL))),
    Command("back", STATE, "background colour", _numbers("BR BG BB", "background", LEVEL), initial=(0.0, 0.0, 0.0)),
    Command("elig", STATE, "ambient coefficient", _numbers("ke", "ke", UNIT), initial=(0.0,)),
    Command("eyep", STATE, "the eye", _numbers("xv yv zv", "eye")),
    Command("refp", STATE, "the point the eye looks at", _numbers("xf yf zf", "refp")),
    Command("vang", STATE, "horizontal and vertical view angles (degrees)", _numbers("ha va", "vang", ANGLE)),
    Command("size", STATE, "image width in pixels", (Arg("is", "width", SIDE, kind=COUNT),)),
    Command("rend", REND, "render the scene as it stands into `file`", (Arg("file", "output", kind=FILE),)),
    Command("quit", QUIT, "stop reading"),
)}  # fmt: skip

_MATERIALS = tuple(c.name for c in COMMANDS.values() if c.role == MATERIAL)


def _fields(command: Command, values: Sequence[Value]) -> dict[str, Value]:
    """A line's argument values (in order) by the field they give: alone, or as a tuple."""
    pairs = zip(command.args, values)
    grouped = {field: [v for _, v in group] for field, group in itertools.groupby(pairs, key=lambda p: p[0].field)}
    return {field: v[0] if len(v) == 1 else tuple(v) for field, v in grouped.items()}


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


# -- reading -----------------------------------------------------------------------------------
class _Parser:
    """Reads a deck's lines against `COMMANDS` into the `Snapshot` of each `rend`.

    Arguments:
        name: the deck's name, for messages.
        read_texture: called with each `tmap` file name once its line passed every other
            check; an `RtjaxError` it raises is reported at that line.
    """

    def __init__(self, name: str, read_texture: Callable[[str], None]):
        self.name = name
        self.read_texture = read_texture
        self.spheres: list[tuple[Line, Line]] = []  # complete: sphe line, material line
        self.pending: Line | None = None  # a sphe line still without its material line
        self.lights: list[Line] = []
        self.state = {c.name: Line(c.name, 0, _fields(c, c.initial)) for c in COMMANDS.values() if c.initial is not None}
        self.snapshots: list[Snapshot] = []
        self.line = 0
        self.command = ""
        self.texts: dict[str, str] = {}  # argument name → its text on this line, for messages

    def parse(self, text: str) -> list[Snapshot]:
        """The snapshot of every `rend` in `text`; a `DeckError` at the first bad line."""
        for self.line, raw in enumerate(_LINE_BREAK.split(text), start=1):
            tokens = raw.split("#", 1)[0].split()
            if not tokens:
                continue
            command = COMMANDS.get(tokens[0])
            if command is None:
                raise self.error(f"unknown command {tokens[0]!r} (expected one of {', '.join(COMMANDS)})")
            if command.role == QUIT:
                self.read(command, tokens[1:])
                break
            self.step(command, tokens[1:])
        self.close_sphere("the end of the deck")
        return self.snapshots

    def step(self, command: Command, args: list[str]) -> None:
        """One line: its arguments read, then what its command does with them."""
        if command.role == SPHERE:
            self.close_sphere(f"the sphe on line {self.line}")  # before this line's own arguments
        line = self.read(command, args)
        if command.role == SPHERE:
            self.pending = line
        elif command.role == MATERIAL:
            sphere = self.pending_sphere()
            if "texture" in line.values:
                try:
                    self.read_texture(line.values["texture"])
                except RtjaxError as e:
                    raise self.error(f"{command.name}: {e}") from None
            self.spheres.append((sphere, line))
            self.pending = None
        elif command.role == LIGHT:
            self.lights.append(line)
        elif command.role == STATE:
            self.state[command.name] = line
        elif command.role == REND:
            self.close_sphere(f"the rend on line {self.line}")
            self.check_camera()
            self.snapshots.append(Snapshot(tuple(self.spheres), tuple(self.lights), dict(self.state), line))

    # -- arguments: count, syntax, ranges ---------------------------------------------------------
    def read(self, command: Command, args: list[str]) -> Line:
        """A line of `command` with arguments `args`, checked against its table entry.

        Checked in turn: the count, each number's syntax, the light vector (plig), the ranges.
        """
        self.command, self.texts = command.name, {}
        if len(args) not in command.counts:
            raise self.error(command.miscount(args))
        values = {a.name: a.default for a in command.args}
        for arg, text in zip(command.args, args):
            values[arg.name] = text if arg.kind == FILE else self.number(arg, text)
        if command.role == LIGHT:
            self.light_not_zero(command, values)
        for arg in command.ranged:
            value = values[arg.name]
            if not arg.range.test(value):
                raise self.error(f"{command.name}: {arg.name} must be {arg.range.expected}, found {self.found(arg.name, value)}")
        ordered = [int(values[a.name]) if a.kind == COUNT else values[a.name] for a in command.args]
        return Line(command.name, self.line, _fields(command, ordered))

    def number(self, arg: Arg, text: str) -> float:
        """`text` as the value of `arg`: finite, and rounded to float32 unless a count."""
        self.texts[arg.name] = text
        where = f"{self.command}: {arg.name}"
        if _NONFINITE.fullmatch(text):
            raise self.error(f"{where} must be a finite number, found {shown(text)}")
        if not _NUMBER.fullmatch(text):
            raise self.error(f"{where} must be a number, found {shown(text)}")
        value = float(text)
        if arg.kind == COUNT:
            if not math.isfinite(value):
                raise self.error(f"{where} must be a finite number, found {shown(text)}")
            return value
        if not math.isfinite(_to_f32(value)):
            raise self.error(
                f"{where} must be a finite number within float32 range (|x| ≤ {_F32_MAX:.7g}), found {shown(text)}"
            )
        return _to_f32(value)

    def found(self, name: str, value: float) -> str:
        """How a value was written, and what it became when that differs (float32 rounding)."""
        text = self.texts.get(name)
        if text is None:
            return f"{value:g}"
        return shown(text) if float(text) == value else f"{shown(text)} (= {value:g} in float32)"

    def error(self, message: str, line: int | None = None) -> DeckError:
        return DeckError(self.name, self.line if line is None else line, message)

    # -- the rules that are not ranges ------------------------------------------------------------
    def light_not_zero(self, command: Command, values: Mapping[str, float]) -> None:
        """A light's vector must not be zero (as stored); checked before its colour's ranges."""
        names = [a.name for a in command.args if a.field == "light_dirs"]
        if all(values[n] == 0 for n in names):
            found = " ".join(self.found(n, values[n]) for n in names)
            raise self.error(f"{command.name}: the light vector ({' '.join(names)}) must not be zero, found {found}")

    def pending_sphere(self) -> Line:
        """The sphe line a material line completes: the last one, still without a material."""
        if self.pending is not None:
            return self.pending
        if not self.spheres:
            raise self.error(f"{self.command} has no sphere above it (a material line follows a sphe line)")
        sphere, material = self.spheres[-1]
        raise self.error(
            f"{self.command}: the sphere on line {sphere.number} already has a material"
            f" ({material.command} on line {material.number})"
        )

    def close_sphere(self, before: str) -> None:
        """A sphe line must have its material line before `before` (a sphe, a rend, the end)."""
        if self.pending is not None:
            expected = f"{', '.join(_MATERIALS[:-1])} or {_MATERIALS[-1]}"
            message = f"sphe has no material line after it (expected {expected} before {before})"
            raise self.error(message, self.pending.number)

    def check_camera(self) -> None:
        """A rend needs every setting without a default, eyep ≠ refp, and an image within MAX_SIDE."""
        missing = [c.name for c in COMMANDS.values() if c.role == STATE and c.name not in self.state]
        if missing:
            raise self.error(f"rend: the camera is incomplete: {', '.join(missing)} must come before rend")
        eyep, refp = self.state["eyep"], self.state["refp"]
        if eyep.values["eye"] == refp.values["refp"]:  # compared as stored (float32), where the view direction is computed
            raise self.error(f"rend: eyep (line {eyep.number}) equals refp (line {refp.number}): the view has no direction")
        (ha, va), size = self.state["vang"].values["vang"], self.state["size"].values["width"]
        try:
            height = image_height(size, ha, va)
        except OverflowError:
            height = MAX_SIDE + 1
        if height > MAX_SIDE:
            raise self.error(f"rend: size {size} with vang {ha:g} {va:g} makes the image taller than {MAX_SIDE} pixels")


def parse_deck(
    text: str,
    name: str = "<deck>",
    folder: str = ".",
    load_texture: Callable[[str], np.ndarray] | None = None,
) -> Deck:
    """Parse deck text.

    Arguments:
        text: the deck (a leading byte order mark is skipped).
        name: the deck's name in error messages.
        folder: the folder `tmap` file names are relative to.
        load_texture: reads an image file into a (height, width, 3) array (e.g.
            `rtjax.load_image`); None: a `tmap` line is an error.

    Returns:
        The `Deck`, one `Frame` per `rend` line. Raises `DeckError` (`name:line: ...`)
        on bad input.
    """
    textures = Textures(folder, load_texture)
    snapshots = _Parser(name, textures.read).parse(text.lstrip("\ufeff"))
    frames = (Frame(assemble(s, textures.arrays), s.rend.values["output"], s.rend.number) for s in snapshots)
    return Deck(name, tuple(frames))


def load_deck(path: str | os.PathLike) -> Deck:
    """Read and parse a deck file; its `tmap` names are relative to its folder.

    Raises `DeckError` (`file:line: ...`) on bad input.
    """
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


# -- writing -----------------------------------------------------------------------------------
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


def _write(command: str, values: Mapping[str, Any]) -> str:
    """The deck line of `command` whose arguments give `values` (by field, as the parser's
    `Line.values`): numbers as `_fmt` writes them, counts as integers, file names as one word."""
    words = [command]
    for field, group in itertools.groupby(COMMANDS[command].args, key=lambda a: a.field):
        kind, value = next(group).kind, values[field]
        if kind == FILE:
            words.append(_name(value, f"{command} {field}"))
        elif kind == COUNT:
            words.append(str(value))
        else:
            words += [_fmt(x) for x in np.ravel(value)]
    return " ".join(words)


def _scene_parts(scene: Scene) -> tuple[list[str], list[str], list[str]]:
    """Deck lines of a scene in three parts: per sphere (sphe + material), per light, state."""
    s, p = scene.structure, jax.tree_util.tree_map(np.asarray, scene.params)
    whole = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)} | {"width": s.width}
    texture = s.texture_index()
    spheres = []
    for i, kind in enumerate(s.kinds):
        sphere = {field: whole[field][i] for field in ("centers", "radii", *SPHERE_DEFAULTS)}
        if kind == TEXTURE:
            sphere["texture"] = s.texture_files[texture[i]]
        material = _write(kind, sphere)
        spheres.append(_write("sphe", sphere) + "\n" + material)
    lights = [_write("plig", {"light_dirs": d, "light_colors": c}) for d, c in zip(p.light_dirs, p.light_colors)]
    state = [_write(c.name, whole) for c in COMMANDS.values() if c.role == STATE]
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
        out += spheres[len(done_spheres) :] + lights[len(done_lights) :] + state + [_write("rend", {"output": fr.output})]
        done_spheres, done_lights = spheres, lights
    out.append("quit")
    return "\n".join(out) + "\n"


def save_deck(path: str | os.PathLike, frames: Sequence[Frame] | Scene, output: str | None = None, header: str | None = None) -> None:
    """Write deck text atomically."""
    from .atomic import atomic_write

    text = format_deck(frames, output, header)
    with writing(path):
        atomic_write(path, text.encode("utf-8"))
