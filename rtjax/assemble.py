"""Scenes from parsed decks: the `tmap` textures a deck names, and the `Scene` of each `rend`.

The parser (`rtjax.deck`) describes each frame by the deck lines in effect at its `rend`
(`Snapshot`), each line's values keyed by the scene field they give (`Line`); this
module reads the textures those lines name and builds `Structure` and `Params`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping

import jax.numpy as jnp
import numpy as np

from .camera import image_height
from .errors import RtjaxError
from .scene import TEXTURE, Params, Scene, Structure

#: A value as a deck line gives it: a float32-exact number, a count, a file name, or a
#: vector of numbers (the arguments that give one field together, e.g. xc yc zc).
Value = float | int | str | tuple[float, ...]

#: The per-sphere material fields and the value a sphere whose material leaves them out
#: gets (the colour of a mirror, say): the renderer ignores such entries.
SPHERE_DEFAULTS: Mapping[str, Value] = {"diffuse": (0.0, 0.0, 0.0), "ks": 0.0, "beta": 1.0, "kt": 0.0, "ior": 1.0}


@dataclasses.dataclass(frozen=True)
class Line:
    """One deck line as read.

    Attributes:
        command: its command (`sphe`, `opaq`, ...).
        number: its line number in the deck (0 for the defaults no line gave).
        values: its values by the field they give: a `Params` field (`centers`, `radii`,
            `ks`, ...), `texture` (a `tmap` file name), `width` (`size`) or `output`
            (the `rend` file name).
    """

    command: str
    number: int
    values: Mapping[str, Value]


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """The deck lines in effect at one `rend`: what its frame shows.

    Attributes:
        spheres: each sphere's `sphe` line and its material line, in deck order.
        lights: the `plig` lines so far, in deck order.
        state: the latest line of each state command (`back`, `elig`, `eyep`, `refp`,
            `vang`, `size`), by command.
        rend: the `rend` line itself.
    """

    spheres: tuple[tuple[Line, Line], ...]
    lights: tuple[Line, ...]
    state: Mapping[str, Line]
    rend: Line


class Textures:
    """The textures a deck's `tmap` lines name, each file read once.

    Arguments:
        folder: the deck's folder; texture names are relative to it.
        load: reads an image file into a (height, width, 3) array of texels 0..255;
            None where textures cannot be loaded.
    """

    def __init__(self, folder: str, load: Callable[[str], np.ndarray] | None):
        self.folder = folder
        self.load = load
        self.arrays: dict[str, np.ndarray] = {}

    def read(self, name: str) -> None:
        """Read texture `name` into `arrays` unless it is there already.

        Raises `RtjaxError` (one line, naming the texture and the reason) when it cannot
        be read or is not a colour image.
        """
        if name in self.arrays:
            return
        if self.load is None:
            raise RtjaxError(f"textures cannot be loaded here (texture {name!r})")
        try:
            texture = np.asarray(self.load(os.path.join(self.folder, name)))
        except (RtjaxError, OSError, ValueError, MemoryError) as e:
            reason = " ".join(str(e).split()) or type(e).__name__
            raise RtjaxError(f"cannot read texture {name!r}: {reason}") from None
        if texture.ndim != 3 or texture.shape[2] != 3 or texture.shape[0] < 1 or texture.shape[1] < 1:
            raise RtjaxError(f"texture {name!r} has shape {texture.shape}, expected (height, width, 3)")
        self.arrays[name] = texture


def assemble(snapshot: Snapshot, textures: Mapping[str, np.ndarray]) -> Scene:
    """The scene of one `rend`.

    Arguments:
        snapshot: the deck lines in effect at the `rend`.
        textures: texture arrays by file name, holding every name the snapshot's `tmap`
            lines give (`Textures.arrays`).

    Returns:
        The `Scene`, its parameters float32 arrays exactly as the deck's numbers were
        rounded on reading.
    """
    spheres = [{**SPHERE_DEFAULTS, **sphe.values, **material.values} for sphe, material in snapshot.spheres]
    kinds = tuple(material.command for _, material in snapshot.spheres)
    names = tuple(s["texture"] for s, kind in zip(spheres, kinds) if kind == TEXTURE)
    maps = tuple(textures[name] for name in names)
    state = {field: value for line in snapshot.state.values() for field, value in line.values.items()}
    ha, va = state["vang"]
    structure = Structure(
        kinds=kinds,
        n_lights=len(snapshot.lights),
        width=state["width"],
        height=image_height(state["width"], ha, va),
        texture_shapes=tuple(t.shape[:2] for t in maps),
        texture_files=names,
    )

    def array(values, shape: tuple[int, ...]) -> np.ndarray:
        return np.asarray(values, np.float32).reshape(shape)

    def per_sphere(field: str, shape: tuple[int, ...] = ()) -> np.ndarray:
        return array([s[field] for s in spheres], (len(spheres), *shape))

    def per_light(field: str) -> np.ndarray:
        return array([light.values[field] for light in snapshot.lights], (len(snapshot.lights), 3))

    params = Params(
        centers=per_sphere("centers", (3,)),
        radii=per_sphere("radii"),
        diffuse=per_sphere("diffuse", (3,)),
        ks=per_sphere("ks"),
        beta=per_sphere("beta"),
        kt=per_sphere("kt"),
        ior=per_sphere("ior"),
        light_dirs=per_light("light_dirs"),
        light_colors=per_light("light_colors"),
        background=array(state["background"], (3,)),
        ke=array(state["ke"], ()),
        eye=array(state["eye"], (3,)),
        refp=array(state["refp"], (3,)),
        vang=array(state["vang"], (2,)),
        textures=tuple(np.asarray(t, np.float32) for t in maps),
    )
    return Scene(structure, params.astype(jnp.float32))
