"""Texture recovery: the schedule of a texel fit and which texels the views determine.

A texture's colour is linear in its texels (bilinear weights, before the render's
clamping), and with the geometry fixed no edge moves: the model of a texel fit is the
plain render at pixel centres, which is how `rtjax render` makes a target, so the
residual at the truth is the target's rounding alone. Texels are detail at the image's
own scale, so the fit is one full-size level of every pixel (`plain_level`), not a
coarse-to-fine pyramid (an area-averaged level blurs what it would have to recover),
first with a wide robust loss, then the fit's own (`texel_levels`).

A texel is *seen* when its **coverage**, the summed weight it carries in the rendered
pixels, Σ over pixels (and views) of ∂colour/∂texel (per channel, averaged over the three),
is at least `SEEN_ABOVE`: the texel's share of the pixels it is sampled in, times the
shading there (1 for a fully lit, unshadowed pixel that samples that texel alone). A
texel of coverage 0 is in no pixel: its gradient is zero and the fit leaves it exactly
as it started. Between 0 and `SEEN_ABOVE` a texel is in some pixels but shares them with
its neighbours (an image with fewer pixels on a sphere than its texture has texels) or is
seen dimly, at a grazing angle: the fit moves it, but it is not determined on its own.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .objective import Samples, level_grid, prepare_mask

#: The families a fit takes `plain_level` for when textures are free: they change
#: colours, never an edge (with the geometry fixed).
APPEARANCE = ("textures", "colors", "ks", "beta", "ke", "light_colors", "background")
#: A texel fit starts with the robust loss this many times wider (`texel_levels`): from a
#: flat start, residuals of a hundred levels are what is to be fitted, not outliers, and
#: a Cauchy loss of the fit's scale would take them in slowly.
WIDE_SCALE = 10.0
#: A texel counts as seen at or above this coverage (pixels' worth of weight; see the
#: module's docstring): as much as one fully lit pixel that samples it alone.
SEEN_ABOVE = 1.0


def appearance_only(families: Sequence[str]) -> bool:
    """Whether a fit of `families` is a texture fit with fixed geometry (`APPEARANCE`)."""
    return "textures" in families and set(families) <= set(APPEARANCE)


def plain_level(target: np.ndarray, weight: np.ndarray, dtype, scale: float = 1.0) -> Samples:
    """Every pixel of the full-size image at its centre, matched by the plain render;
    `scale`: the robust loss's scale as a factor of the fit's."""
    height, width = target.shape[:2]
    _, xy, step = level_grid(width, height, width)
    arrays = (jnp.asarray(a, dtype) for a in (xy, step, target.reshape(-1, 3), weight.reshape(-1, 1), 0.0))
    return Samples(*arrays, exact=False, scale=jnp.asarray(scale, dtype), whole=False, plain=True)


def texel_levels(target: np.ndarray, weight: np.ndarray, dtype) -> list[Samples]:
    """A texel fit's schedule: `plain_level` at `WIDE_SCALE` times the robust loss's
    scale, then at the fit's own (`solve.level_budget` hands over once the RMS residual
    is below `objective.NARROW_BELOW` of the fit's scale)."""
    return [plain_level(target, weight, dtype, WIDE_SCALE), plain_level(target, weight, dtype)]


def texel_weights(scene: rtjax.Scene, samples: Samples, depth: int | None = None) -> tuple[np.ndarray, ...]:
    """Per texture of `scene`, (h, w): each texel's summed weight in the plain render's
    colours at `samples` (times their mask weight): Σ ∂colour/∂texel per channel, averaged
    over the channels. One reverse-mode pass (the render is linear in the texels)."""
    structure, params = scene.structure, scene.params
    weight = jnp.asarray(samples.weight, params.textures[0].dtype)

    def colours(textures):
        at = rtjax.Scene(structure, dataclasses.replace(params, textures=textures))
        return rtjax.render_samples(at, samples.xy, step=samples.step, depth=depth) * weight

    out, pullback = jax.vjp(colours, tuple(params.textures))
    (grads,) = pullback(jnp.ones_like(out))
    return tuple(np.asarray(g, np.float64).sum(-1) / 3 for g in grads)


@dataclasses.dataclass
class TexelCoverage:
    """Which texels a fit's views determine (module docstring).

    - `weights`: per texture, (h, w) coverage summed over the views.
    - `files`: per texture, its `tmap` file name as the deck gave it.
    - `smoothed`: whether the fit had a smoothness prior, which fills the texels not seen.
    """

    weights: tuple[np.ndarray, ...]
    files: tuple[str, ...] = ()
    smoothed: bool = False  # a smoothness prior (`Smoothed`) filled the texels not seen

    def seen(self, k: int) -> np.ndarray:
        """Texture k's seen texels, (h, w) booleans."""
        return self.weights[k] >= SEEN_ABOVE

    def summary(self) -> list[dict]:
        """Per texture: its size, and the count and share of texels seen, weakly seen
        (0 < coverage < `SEEN_ABOVE`: moved, not determined alone) and not seen
        (coverage 0: left as they started, unless `smoothed`)."""
        out = []
        for k, w in enumerate(self.weights):
            n = int(w.size)
            seen, unseen = int(np.sum(w >= SEEN_ABOVE)), int(np.sum(w <= 0))
            out.append({"texture": k, "file": self.files[k] if k < len(self.files) else None,
                        "width": int(w.shape[1]), "height": int(w.shape[0]), "texels": n,
                        "seen": seen, "seen_share": seen / n, "weak": n - seen - unseen, "not_seen": unseen,
                        "not_seen_share": unseen / n, "seen_above": SEEN_ABOVE, "smoothed": self.smoothed})
        return out

    def lines(self) -> list[str]:
        """The summary as text, one line per texture."""
        fate = "filled from their neighbours" if self.smoothed else "left as they started"
        return [f"texture {s['texture']} ({s['width']}×{s['height']}): {s['seen']} of {s['texels']} texels seen "
                f"({100 * s['seen_share']:.1f} %), {s['weak']} weakly, {s['not_seen']} not seen "
                f"({100 * s['not_seen_share']:.1f} %, {fate})" for s in self.summary()]


def coverage(scenes: Sequence[rtjax.Scene], mask=None, depth: int | None = None, smoothed: bool = False) -> TexelCoverage:
    """`TexelCoverage` of the views `scenes` (each at its full size, every pixel at its
    centre; `mask`: as `FitOptions.mask`, for each view)."""
    total = None
    for scene in scenes:
        s = scene.structure
        dtype = jnp.result_type(scene.params.centers)
        level = plain_level(np.zeros((s.height, s.width, 3)), prepare_mask(mask, s.height, s.width), dtype)
        w = texel_weights(scene, level, depth)
        total = w if total is None else tuple(a + b for a, b in zip(total, w))
    return TexelCoverage(total, tuple(scenes[0].structure.texture_files), smoothed)


def texel_differences(textures: Sequence) -> jnp.ndarray:
    """Every pair of neighbouring texels' difference, (M, 3) in levels: along rows
    (columns wrap, as the sphere's longitude does) and down columns."""
    out = []
    for t in textures:
        out.append((jnp.roll(t, -1, axis=1) - t).reshape(-1, 3))
        out.append((t[1:] - t[:-1]).reshape(-1, 3))
    return jnp.concatenate(out)


@dataclasses.dataclass
class Smoothed:
    """A residual function with a smoothness prior on the texels (Tikhonov on their
    differences) appended: √`weight`·(neighbour − texel)/255 for every pair of
    neighbouring texels, so a difference of d levels costs as much as `weight` pixels
    off by d. It decides the texels the views do not determine by themselves (weakly
    seen: shared pixels, grazing views) from their neighbours, and fills texels no view
    sees from theirs (they no longer stay as they started); it also softens sharp
    steps in the texture, so it is off unless asked for (`FitOptions.smooth`)."""

    objective: object
    selection: object
    weight: float

    def start(self):
        """The smoothed objective's `start`."""
        return self.objective.start()

    def at(self, start) -> "Smoothed":
        return dataclasses.replace(self, objective=self.objective.at(start))

    def residuals(self, y: dict, samples):
        r = self.objective.residuals(y, samples)
        textures = self.selection.params(y["scene"]).textures
        prior = jnp.sqrt(jnp.asarray(self.weight, r.dtype)) * texel_differences(textures).astype(r.dtype) / 255
        return jnp.concatenate([r, prior])

