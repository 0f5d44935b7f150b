"""Residuals: render(parameters) − target, per pixel and channel.

The model image is the silhouette-aware render (so residuals have derivatives through
edges), optionally passed through nuisance parameters (exposure gain, gamma) that a
photo-like target may need; residuals can be masked and made robust to outliers
(Huber or Cauchy, as √(2ρ(r)) so least-squares solvers minimise Σρ). A pyramid of
area-averaged targets gives the coarse-to-fine schedule.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .errors import FitError
from .select import Selection

NUISANCE = ("gain", "gamma")
LOSSES = ("l2", "huber", "cauchy")


def load_target(target, *, assignment_order: bool = False) -> np.ndarray:
    """A target image as float (H, W, 3) in 0..255: a path (Sun raster or anything
    OpenImageIO reads) or an array."""
    if isinstance(target, (str, bytes)) or hasattr(target, "__fspath__"):
        return np.asarray(rtjax.load_image(target, assignment_order=assignment_order), np.float64)
    a = np.asarray(target, np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise FitError(f"target image has shape {a.shape}; expected (height, width, 3)")
    return a


def match_size(scene: rtjax.Scene, target: np.ndarray) -> rtjax.Scene:
    """The scene at the target's size: the deck's image size follows the target when
    the aspect ratio agrees (the height the deck's `vang` gives for the target's width);
    otherwise a clear error."""
    h, w = target.shape[:2]
    s = scene.structure
    if (h, w) == (s.height, s.width):
        return scene
    ha, va = (float(x) for x in np.asarray(scene.params.vang))
    expect = rtjax.image_height(w, ha, va)
    if abs(expect - h) > 1:
        raise FitError(
            f"the target is {w}×{h} (aspect {w / h:.3f}) but the deck's view (vang {ha:g} {va:g}) is "
            f"{s.width}×{s.height} (aspect {s.width / s.height:.3f}): the aspect ratios differ"
        )
    return scene.resized(w, h)


def area_matrix(n_out: int, n_in: int) -> np.ndarray:
    """(n_out, n_in) weights averaging each output cell's footprint on the input grid."""
    edges = np.linspace(0, n_in, n_out + 1)
    m = np.zeros((n_out, n_in))
    for i in range(n_out):
        lo, hi = edges[i], edges[i + 1]
        for j in range(int(np.floor(lo)), min(n_in, int(np.ceil(hi)))):
            m[i, j] = min(hi, j + 1) - max(lo, j)
        m[i] /= m[i].sum()
    return m


def downsample(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-average an (H, W, C) image to (height, width, C)."""
    a = area_matrix(height, image.shape[0])
    b = area_matrix(width, image.shape[1])
    return np.einsum("ih,hwc,jw->ijc", a, image, b)


def schedule_widths(width: int, levels: int | Sequence[int] | None) -> list[int]:
    """Image widths from coarse to fine, ending at the full width.

    An int k gives k levels halving the width (none below 48 pixels); a sequence is
    taken as given (sorted, capped at the full width)."""
    if levels is None or isinstance(levels, int):
        k = 3 if levels is None else int(levels)
        out = [width]
        while len(out) < k and out[0] // 2 >= 48:
            out.insert(0, out[0] // 2)
        return out
    out = sorted({min(int(w), width) for w in levels if int(w) >= 1})
    if not out or out[-1] != width:
        out.append(width)
    return out


def robust(r, loss: str, scale: float):
    """Residuals r' with Σr'² = 2Σρ(r): plain (l2), Huber or Cauchy with scale `scale`."""
    if loss == "l2":
        return r
    a = jnp.abs(r)
    if loss == "huber":
        rho = jnp.where(a <= scale, 0.5 * r * r, scale * (a - 0.5 * scale))
    elif loss == "cauchy":
        rho = 0.5 * scale**2 * jnp.log1p((r / scale) ** 2)
    else:
        raise FitError(f"unknown loss {loss!r}; choose from {', '.join(LOSSES)}")
    ok = rho > 0
    return jnp.where(ok, jnp.sign(r) * jnp.sqrt(jnp.where(ok, 2 * rho, 1)), 0)


def apply_nuisance(image, nuisance: dict):
    """A camera's response: 255·(gain·I/255)^γ, with the gain and γ fitted jointly."""
    if not nuisance:
        return image
    x = image / 255
    if "gain" in nuisance:
        x = x * jnp.exp(nuisance["gain"])
    if "gamma" in nuisance:
        pos = x > 1e-6
        xs = jnp.where(pos, x, 1)
        x = jnp.where(pos, jnp.exp(jnp.exp(nuisance["gamma"]) * jnp.log(xs)), 0)
    return 255 * jnp.clip(x, 0, 1)


@dataclasses.dataclass
class Objective:
    """The residual function of one pyramid level."""

    selection: Selection
    scene: rtjax.Scene  # at this level's size
    target: jnp.ndarray
    weight: jnp.ndarray  # (H, W, 1): the mask
    edges: float
    depth: int | None
    loss: str
    loss_scale: float
    nuisance: tuple[str, ...]

    def model(self, y: dict):
        p = self.selection.params(y["scene"])
        image = rtjax.render(rtjax.Scene(self.scene.structure, p), depth=self.depth, edges=self.edges)
        return apply_nuisance(image, y.get("nuisance", {}))

    def residuals(self, y: dict, args=None):
        r = (self.model(y) - self.target) * self.weight / 255
        return robust(r, self.loss, self.loss_scale / 255)

    def loss_value(self, y: dict) -> float:
        r = self.residuals(y)
        return float(0.5 * jnp.mean(r * r))


def nuisance_y0(names: Sequence[str], dtype) -> dict:
    bad = [n for n in names if n not in NUISANCE]
    if bad:
        raise FitError(f"unknown nuisance parameter {bad[0]!r}; choose from {', '.join(NUISANCE)}")
    return {n: jnp.zeros((), dtype) for n in names}


def prepare_mask(mask, height: int, width: int) -> np.ndarray:
    """A mask (H, W) or (H, W, 1/3) of weights in [0, 1] (True: counted), or all ones."""
    if mask is None:
        return np.ones((height, width, 1))
    m = np.asarray(rtjax.load_image(mask) / 255 if isinstance(mask, str) else mask, np.float64)
    if m.ndim == 3:
        m = m.mean(axis=2)
    if m.shape != (height, width):
        raise FitError(f"the mask is {m.shape[1]}×{m.shape[0]}, the target {width}×{height}")
    return m[..., None]
