"""Derivative images of the silhouette mode for the scenes of `edge_scenes`, and their
comparison with the yardstick (`tests/data/edges_yardstick.npz`, made by
`scripts/edges_yardstick.py`)."""

from __future__ import annotations

import functools
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import rtjax
from edge_scenes import COARSE, DECKS, FINE, parameters, yardstick_key

YARDSTICK = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "edges_yardstick.npz")


#: The stored finite differences' names: the fine ones (the finest first) and the coarse
#: ones, whose steps of 0.3–0.6 px average the derivative where edges crowd.
FINE_KEYS, COARSE_KEYS = (tuple(yardstick_key(*c) for c in cs) for cs in (FINE, COARSE))


@functools.lru_cache(maxsize=None)
def yardsticks(name: str) -> dict[str, np.ndarray]:
    """The stored yardstick of scene `name`: image, names and the finite differences
    named in FINE_KEYS and COARSE_KEYS."""
    with np.load(YARDSTICK) as data:
        return {k.split("/", 1)[1]: data[k] for k in data.files if k.startswith(name + "/")}


def weights(shape) -> np.ndarray:
    """The fixed random weights w of J = Σ w·image."""
    return np.random.default_rng(21).uniform(0, 1, shape)


def scene(name: str) -> rtjax.Scene:
    return rtjax.parse_deck(DECKS[name][0]).frames[0].scene.astype(jnp.float64)


def scene_parameters(name: str, s: rtjax.Scene) -> list[tuple]:
    """`edge_scenes.parameters` of scene `name` as `s` sets it up."""
    p = s.params
    return parameters(name, np.asarray(p.eye), np.asarray(p.refp), float(p.vang[0]), s.structure.width,
                      np.asarray(p.centers))


def varied(name: str, s: rtjax.Scene):
    """A function v ↦ scene with the parameters of `edge_scenes.parameters` moved by v."""
    p = s.params
    params = scene_parameters(name, s)

    def at(v):
        c, r, light, eye = p.centers, p.radii, p.light_dirs, p.eye
        for i, (_, what, index, axis, _) in enumerate(params):
            if what == "center":
                c = c.at[index, axis].add(v[i])
            elif what == "radius":
                r = r.at[index].add(v[i])
            elif what == "light":
                light = light.at[index, axis].add(v[i])
            else:
                eye = eye.at[axis].add(v[i])
        return s.replace(centers=c, radii=r, light_dirs=light, eye=eye)

    return at, len(params)


def derivative_images(name: str, edges: float = 1.0, spp: int = 1, subdivide: int | None = 0):
    """The mode's image (H, W, 3) and its derivative images (P, H, W, 3) by jax.jacfwd
    (`subdivide`: `render(..., subdivide=subdivide)`, halvings of the box in the pixels
    an edge may cross; None: `render`'s default)."""
    s = scene(name)
    at, n = varied(name, s)
    depth = DECKS[name][1]

    @jax.jit
    def f(v):
        image = rtjax.render(at(v), depth=depth, edges=edges, spp=spp, subdivide=subdivide)
        return image, image

    jac, image = jax.jacfwd(f, has_aux=True)(jnp.zeros(n, jnp.float64))
    return np.asarray(image), np.moveaxis(np.asarray(jac), -1, 0)


def own_differences(name: str, step: float, edges: float = 1.0, subdivide: int | None = 0) -> np.ndarray:
    """Central differences (P, H, W, 3) of the mode's own image, each parameter stepped by
    `step` pixels of image motion: what its jacfwd must equal as the step goes to 0,
    wherever no discrete choice (an edge, a hit) changes within the step."""
    s = scene(name)
    at, n = varied(name, s)
    sizes = [q[4] for q in scene_parameters(name, s)]
    f = jax.jit(lambda v: rtjax.render(at(v), depth=DECKS[name][1], edges=edges, subdivide=subdivide))
    out = []
    for i, size in enumerate(sizes):
        e = np.zeros(n)
        e[i] = step * size
        out.append((np.asarray(f(jnp.asarray(e))) - np.asarray(f(jnp.asarray(-e)))) / (2 * e[i]))
    return np.stack(out)


def cosine(a, b) -> float:
    return float(np.sum(a * b) / (np.linalg.norm(a) * np.linalg.norm(b)))


class Comparison(NamedTuple):
    """Derivatives against a yardstick: J's per parameter and per-pixel cosines."""

    names: list
    mine: np.ndarray  # dJ/dθ per parameter
    truth: np.ndarray
    pixel_cosines: np.ndarray  # per parameter

    @property
    def spheres(self) -> np.ndarray:
        """Which parameters are spheres' (the issue's cosine and median are over those)."""
        return np.array([not n.startswith(("light", "eye")) for n in self.names])

    @property
    def cosine(self) -> float:
        return cosine(self.mine[self.spheres], self.truth[self.spheres])

    @property
    def relative(self) -> np.ndarray:
        """Relative error per parameter (all of them)."""
        return np.abs(self.mine - self.truth) / np.abs(self.truth)

    @property
    def median(self) -> float:
        """Median relative error over the spheres' parameters."""
        return float(np.median(self.relative[self.spheres]))

    def summary(self, short: bool = False) -> str:
        rel = self.relative
        worst = np.argsort(-rel)[:3]
        text = (f"cos {self.cosine:.4f}  median rel {self.median * 100:.1f} %  "
                f"min pixel cos {self.pixel_cosines.min():.3f} ({self.names[int(np.argmin(self.pixel_cosines))]})")
        if short:
            return text
        text += "  worst: " + ", ".join(f"{self.names[i]} {self.mine[i]:.4g} vs {self.truth[i]:.4g}" for i in worst)
        text += "\n    pixel cos: " + " ".join(f"{n}:{c:.3f}" for n, c in zip(self.names, self.pixel_cosines))
        text += "\n    rel err %: " + " ".join(f"{n}:{e * 100:.1f}" for n, e in zip(self.names, rel))
        return text


def compare(jac: np.ndarray, fd: np.ndarray, names) -> Comparison:
    """`jac` and `fd`, derivative images (P, H, W, 3), compared."""
    w = weights(fd.shape[1:])
    mine, truth = np.einsum("phwc,hwc->p", jac, w), np.einsum("phwc,hwc->p", fd, w)
    pix = np.array([cosine(a, b) for a, b in zip(jac, fd)])
    return Comparison([str(n) for n in names], mine, truth, pix)
