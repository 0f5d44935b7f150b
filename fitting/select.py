"""Which parameters are free, and the unconstrained coordinates the solvers move.

A `Selection` picks parameter families (centres, colours, ke, …) for all spheres or a
subset; everything else stays fixed (a constant of the residual function, never
differentiated). Bounded parameters live on the real line through a
reparameterisation (colours in [0, 1] through a logistic, radii > 0 through exp,
n ≥ 1 through 1 + exp, …), so no solver step can leave the valid range, and
`Selection.params(y)` maps the solver's coordinates back to the deck's own units.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .errors import FitError


@dataclasses.dataclass(frozen=True)
class Transform:
    """x = lo + (hi − lo)·σ(u) (bounded), lo + e^u (bounded below), or x = x0 + scale·u."""

    kind: str  # "interval", "lower" or "affine"
    lo: float = 0.0
    hi: float = 1.0
    scale: float = 1.0

    def to_free(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        if self.kind == "interval":
            eps = 1e-6
            z = np.clip((x - self.lo) / (self.hi - self.lo), eps, 1 - eps)  # a value on the bound starts just inside
            return np.log(z) - np.log1p(-z)
        if self.kind == "lower":
            return np.log(np.maximum(x - self.lo, 1e-6 * max(1.0, abs(self.lo))))
        return np.zeros_like(x)  # affine: u measures the change from the start, in units of `scale`

    def from_free(self, u, x0):
        if self.kind == "interval":
            return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(u)
        if self.kind == "lower":
            return self.lo + jnp.exp(u)
        return x0 + self.scale * u


@dataclasses.dataclass(frozen=True)
class Family:
    """A parameter family: its field in `rtjax.Params`, whether it is per sphere (and for
    which material kinds), and its transform (`None`: built from the scene's scale)."""

    field: str
    per_sphere: bool
    kinds: tuple[str, ...] = ()
    transform: Transform | None = None
    label: str = ""


_UNIT = Transform("interval", 0.0, 1.0)
_LEVEL = Transform("interval", 0.0, 255.0)

FAMILIES: dict[str, Family] = {
    "centers": Family("centers", True, ("opaq", "mirr", "trpa", "tmap"), None, "centre"),
    "radii": Family("radii", True, ("opaq", "mirr", "trpa", "tmap"), Transform("lower", 0.0), "radius"),
    "colors": Family("diffuse", True, ("opaq",), _UNIT, "colour"),
    "ks": Family("ks", True, ("opaq", "trpa", "tmap"), _UNIT, "ks"),
    "beta": Family("beta", True, ("opaq", "trpa", "tmap"), Transform("lower", 1.0), "beta"),
    "kt": Family("kt", True, ("trpa",), _UNIT, "kt"),
    "n": Family("ior", True, ("trpa",), Transform("lower", 1.0), "n"),
    "ke": Family("ke", False, (), _UNIT, "ke"),
    "light": Family("light_dirs", False, (), Transform("affine"), "light direction"),
    "light_colors": Family("light_colors", False, (), _LEVEL, "light intensity"),
    "background": Family("background", False, (), _LEVEL, "background"),
    "eye": Family("eye", False, (), None, "eye"),
    "refp": Family("refp", False, (), None, "refp"),
    "vang": Family("vang", False, (), Transform("interval", 0.0, 180.0), "vang"),
    "textures": Family("textures", False, (), _LEVEL, "texels"),
}
ALIASES = {"center": "centers", "centres": "centers", "colours": "colors", "diffuse": "colors", "ior": "n",
           "radius": "radii", "lights": "light", "light_dirs": "light", "camera": "eye,refp,vang"}


def parse_free(text: str | Iterable[str]) -> tuple[str, ...]:
    """'centers,colors,ke' → ('centers', 'colors', 'ke'); aliases allowed; unknown names are errors."""
    names = text.split(",") if isinstance(text, str) else list(text)
    out: list[str] = []
    for raw in names:
        name = raw.strip().lower()
        if not name:
            continue
        for n in ALIASES.get(name, name).split(","):
            if n not in FAMILIES:
                raise FitError(f"unknown parameter family {raw.strip()!r}; choose from {', '.join(FAMILIES)}")
            if n not in out:
                out.append(n)
    if not out:
        raise FitError("no free parameters chosen")
    return tuple(out)


class Selection:
    """Free parameters of one scene and the map y ↦ Params.

    `y` (what the solver moves) is a dict, family → unconstrained array; `params(y)`
    writes the transformed values into a copy of the start parameters.
    """

    def __init__(self, scene: rtjax.Scene, free: str | Sequence[str], spheres: Sequence[int] | None = None):
        self.scene = scene
        self.families = parse_free(free)
        s, p = scene.structure, scene.params
        n = s.n_spheres
        chosen = list(range(n)) if spheres is None else [int(i) for i in spheres]
        bad = [i for i in chosen if not 0 <= i < n]
        if bad:
            raise FitError(f"sphere index {bad[0]} is out of range: the scene has {n} spheres (0..{n - 1})")
        radii = np.asarray(p.radii, np.float64)
        length = float(np.median(radii)) if n else 1.0
        self.index: dict[str, np.ndarray] = {}
        self.transform: dict[str, Transform] = {}
        for name in self.families:
            fam = FAMILIES[name]
            if fam.per_sphere:
                idx = np.array([i for i in chosen if s.kinds[i] in fam.kinds], dtype=np.int32)
                if idx.size == 0:
                    which = "the chosen spheres" if spheres is not None else "the scene's spheres"
                    raise FitError(f"{name}: none of {which} has it (it belongs to {', '.join(fam.kinds)} spheres)")
                self.index[name] = idx
            elif name == "light" and s.n_lights == 0 or name == "light_colors" and s.n_lights == 0:
                raise FitError(f"{name}: the scene has no lights")
            elif name == "textures" and not p.textures:
                raise FitError("textures: the scene has no textured spheres")
            self.transform[name] = fam.transform or Transform("affine", scale=length)
        self.start = self.values(p)

    def values(self, p: rtjax.Params) -> dict[str, np.ndarray]:
        """The free values (deck units) of `p`, family → array."""
        out = {}
        for name in self.families:
            a = getattr(p, FAMILIES[name].field)
            if name == "textures":
                out[name] = tuple(np.asarray(t, np.float64) for t in a)
            else:
                a = np.asarray(a, np.float64)
                out[name] = a[self.index[name]] if name in self.index else a
        return out

    def y0(self) -> dict:
        """Unconstrained start: each family's transform applied to the start values."""
        y = {}
        for name, v in self.start.items():
            t = self.transform[name]
            y[name] = tuple(t.to_free(a) for a in v) if name == "textures" else t.to_free(v)
        # The solver's own coordinates: float64 whenever JAX allows it (optimistix's damped
        # systems are built in the default float type; the render keeps the scene's dtype).
        dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), y)

    def params(self, y: dict) -> rtjax.Params:
        """The scene's parameters with the free ones set from `y` (differentiable in y)."""
        p = self.scene.params
        new = {}
        for name in self.families:
            fam, t = FAMILIES[name], self.transform[name]
            old = getattr(p, fam.field)
            if name == "textures":
                new[fam.field] = tuple(t.from_free(u, None).astype(o.dtype) for u, o in zip(y[name], old))
                continue
            x0 = jnp.asarray(self.start[name], old.dtype)
            value = t.from_free(y[name], x0).astype(old.dtype)
            new[fam.field] = old.at[self.index[name]].set(value) if name in self.index else value
        return dataclasses.replace(p, **new)

    def at(self, params: rtjax.Params, start: dict) -> "Selection":
        """This selection from other start parameters and free values (the same families,
        spheres and transforms): `Objective.at`'s part."""
        out = copy.copy(self)
        out.scene, out.start = rtjax.Scene(self.scene.structure, params), start
        return out

    def scene_at(self, y: dict) -> rtjax.Scene:
        return rtjax.Scene(self.scene.structure, self.params(y))

    def size(self) -> int:
        return sum(int(np.size(a)) for a in jax.tree_util.tree_leaves(self.start))

    def table(self, y: dict) -> list[tuple[str, object, object]]:
        """Rows (name, start, fitted) in deck units, one per sphere and family (textures summarised)."""
        fitted = self.values(self.params(y))
        rows = []
        for name in self.families:
            if name == "textures":
                for k, (a, b) in enumerate(zip(self.start[name], fitted[name])):
                    rows.append((f"texture {k} (mean level)", float(np.mean(a)), float(np.mean(b))))
                continue
            label = FAMILIES[name].label
            if name in self.index:
                for j, i in enumerate(self.index[name]):
                    rows.append((f"sphere {i} {label}", _plain(self.start[name][j]), _plain(fitted[name][j])))
            elif name in ("light", "light_colors"):
                for j in range(len(self.start[name])):
                    rows.append((f"light {j} {label.split()[-1]}", _plain(self.start[name][j]), _plain(fitted[name][j])))
            else:
                rows.append((label, _plain(self.start[name]), _plain(fitted[name])))
        return rows


def _plain(a):
    a = np.asarray(a, np.float64)
    return float(a) if a.ndim == 0 else [float(x) for x in a.ravel()]
