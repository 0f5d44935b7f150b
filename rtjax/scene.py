"""A scene = static `Structure` (what is compiled) + `Params` (a pytree of arrays).

`jax.jit` caches the renderer by `Structure` (material kinds, counts, image size);
`jax.grad`, `jax.jacfwd` and optimistix act on `Params`, whose leaves are all arrays.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .errors import RtjaxError
from .spheres import CULL_ABOVE

OPAQUE, MIRROR, GLASS, TEXTURE = "opaq", "mirr", "trpa", "tmap"
KINDS = (OPAQUE, MIRROR, GLASS, TEXTURE)

#: Reflection/refraction depth used when a scene has mirrors or glass and none is asked for.
DEFAULT_DEPTH = 10


@dataclasses.dataclass(frozen=True)
class Structure:
    """What the compiled renderer depends on: hashable, never traced.

    `texture_files` (the `tmap` names, for writing the deck back) is excluded from
    equality so that two scenes differing only in file names share one compilation.
    `culling`: whether rays are tested only against the spheres they can meet (the same
    image, faster for many spheres); None (default) culls scenes of more than
    `CULL_ABOVE` spheres.
    """

    kinds: tuple[str, ...]
    n_lights: int
    width: int
    height: int
    texture_shapes: tuple[tuple[int, int], ...] = ()
    texture_files: tuple[str, ...] = dataclasses.field(default=(), compare=False)
    culling: bool | None = None

    def __post_init__(self):
        bad = [k for k in self.kinds if k not in KINDS]
        if bad:
            raise ValueError(f"unknown material kinds {bad}; expected {KINDS}")
        if len(self.texture_shapes) != self.kinds.count(TEXTURE):
            raise ValueError("one texture shape per tmap sphere is required")

    @property
    def n_spheres(self) -> int:
        return len(self.kinds)

    def has(self, kind: str) -> bool:
        return kind in self.kinds

    @property
    def culls(self) -> bool:
        """Whether the renderer culls spheres per group of rays (`culling`)."""
        return self.n_spheres > CULL_ABOVE if self.culling is None else bool(self.culling)

    @property
    def needs_secondary_rays(self) -> bool:
        """Mirrors or glass spawn further rays; otherwise depth 0 is exact."""
        return self.has(MIRROR) or self.has(GLASS)

    @property
    def default_depth(self) -> int:
        return DEFAULT_DEPTH if self.needs_secondary_rays else 0

    def mask(self, *kinds: str) -> np.ndarray:
        """Boolean per sphere: is its material one of `kinds`? (a compile-time constant)"""
        return np.array([k in kinds for k in self.kinds], dtype=bool)

    def texture_index(self) -> np.ndarray:
        """Per sphere, the index of its texture in `Params.textures`, or -1."""
        out, t = [], 0
        for k in self.kinds:
            out.append(t if k == TEXTURE else -1)
            t += k == TEXTURE
        return np.array(out, dtype=np.int32)

    def replace(self, **changes: Any) -> "Structure":
        return dataclasses.replace(self, **changes)


class Params(eqx.Module):
    """Every differentiable number of a scene, in the deck's own units.

    Material arrays hold one entry per sphere; entries a sphere's kind does not use
    (the colour of a mirror, say) are ignored by the renderer and get zero gradient.
    """

    centers: Float[Array, "n 3"]
    radii: Float[Array, " n"]
    diffuse: Float[Array, "n 3"]  # dR dG dB in 0..1 (opaq)
    ks: Float[Array, " n"]  # specular coefficient (opaq, trpa, tmap)
    beta: Float[Array, " n"]  # Phong exponent (opaq, trpa, tmap)
    kt: Float[Array, " n"]  # transmission (trpa)
    ior: Float[Array, " n"]  # index of refraction n (trpa)
    light_dirs: Float[Array, "l 3"]  # toward the light, as written (normalised when used)
    light_colors: Float[Array, "l 3"]  # 0..255
    background: Float[Array, " 3"]  # 0..255
    ke: Float[Array, ""]  # ambient coefficient
    eye: Float[Array, " 3"]
    refp: Float[Array, " 3"]
    vang: Float[Array, " 2"]  # ha, va in degrees
    textures: tuple[Float[Array, "h w 3"], ...] = ()  # texels 0..255, one per tmap sphere
    #: sky occlusion's weight per sphere (`rtjax.occlusion`), not part of the deck language;
    #: None: the assignment's ambient term, no occlusion code
    occlusion: Float[Array, " n"] | None = None
    #: the colour (0..255) glass reflects where a ray meets it from outside, weighted by
    #: Fresnel's reflectance (`shading.fresnel_reflectance`; what passes is weighted by the
    #: rest), not part of the deck language; None: glass reflects only by total internal
    #: reflection, as the deck says, and no such code is compiled
    fresnel: Float[Array, " 3"] | None = None

    def astype(self, dtype) -> "Params":
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), self)


class Scene(eqx.Module):
    """A renderable scene: `structure` is static (part of the pytree's treedef)."""

    structure: Structure = eqx.field(static=True)
    params: Params

    def astype(self, dtype) -> "Scene":
        """The same scene with every parameter cast to `dtype` (e.g. float64 for gradient checks)."""
        return Scene(self.structure, self.params.astype(dtype))

    def replace(self, **params: Any) -> "Scene":
        """A copy with some parameters replaced, e.g. `scene.replace(ke=0.3)`."""
        p = self.params
        new = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
        for k, v in params.items():
            if k not in new:
                raise TypeError(f"unknown scene parameter {k!r}")
            old = new[k] if new[k] is not None else p.radii  # a field not set takes the radii's dtype
            if v is None:
                new[k] = None
            elif k == "textures":
                new[k] = tuple(jnp.asarray(t, jnp.result_type(o)) for t, o in zip(v, old))
            else:
                new[k] = jnp.asarray(v, jnp.result_type(old))
                if getattr(p, k) is not None and new[k].shape != old.shape:
                    raise RtjaxError(f"{k} has shape {new[k].shape}; this scene's is {old.shape} (its structure "
                                     "fixes the number of spheres and lights)")
        return Scene(self.structure, Params(**new))

    def resized(self, width: int, height: int | None = None) -> "Scene":
        """The same scene at another image width; the height follows from `vang` as a
        deck's `size` would give it (DECK.md §2) unless given."""
        from .camera import image_height

        if height is None:
            ha, va = (float(x) for x in np.asarray(self.params.vang))
            height = image_height(int(width), ha, va)
        if int(width) < 1 or int(height) < 1:
            raise RtjaxError(f"an image must be at least 1 pixel a side, not {int(width)}×{int(height)}")
        return Scene(self.structure.replace(width=int(width), height=int(height)), self.params)
