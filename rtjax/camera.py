"""Camera and image geometry (DECK.md §2): z up, square pixels, row 0 at the top."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .numerics import normalize as _normalize
from .numerics import spread


def normalize(v):
    return _normalize(v, axis=-1) if v.ndim == 1 else _normalize(v, axis=0)


def image_height(width: int, ha_deg: float, va_deg: float) -> int:
    """H = round(is · tan(va/2) / tan(ha/2)), rounding halves up; at least 1."""
    ratio = math.tan(math.radians(va_deg) / 2) / math.tan(math.radians(ha_deg) / 2)
    return max(1, int(math.floor(width * ratio + 0.5)))


def basis(eye: Float[Array, " 3"], refp: Float[Array, " 3"]):
    """Forward w, right u, up v. u = w × ẑ normalised; ŷ stands in for ẑ when w ∥ ẑ."""
    w = normalize(refp - eye)
    z = jnp.array([0.0, 0.0, 1.0], w.dtype)
    y = jnp.array([0.0, 1.0, 0.0], w.dtype)
    # w ∥ ẑ (to rounding): the cross product vanishes relative to |w| = 1.
    parallel = jnp.sum(jnp.cross(w, z) ** 2) < (1e-10 if w.dtype == jnp.float32 else 1e-20)
    up = jnp.where(parallel, y, z)
    u = normalize(jnp.cross(w, up))
    v = jnp.cross(u, w)
    return w, u, v


def subpixel_offsets(spp: int, dtype=jnp.float32) -> Float[Array, "k 2"]:
    """The k×k sample positions inside a pixel, in [0, 1)², a regular grid (k = spp)."""
    g = (np.arange(spp) + 0.5) / spp
    sx, sy = np.meshgrid(g, g, indexing="xy")
    return jnp.asarray(np.stack([sx.ravel(), sy.ravel()], -1), dtype)


def rays_through(
    eye: Float[Array, " 3"],
    refp: Float[Array, " 3"],
    vang: Float[Array, " 2"],
    width: int,
    height: int,
    xy: Float[Array, "2 k"],
):
    """Origins and unit directions (3, K) of rays through image positions `xy`.

    xy is in pixels, x across from the left edge, y down from the top edge, so pixel
    (i, j)'s centre is (i + ½, j + ½): it samples the screen point
    (x/W·2 − 1, 1 − y/H·2) in units of the half extents R·tan(ha/2), R·tan(va/2).
    The direction does not depend on R, so R never appears.
    """
    w, u, v = basis(eye, refp)
    half = jnp.tan(jnp.deg2rad(vang) / 2)
    sx = (xy[0] / width * 2 - 1) * half[0]
    sy = (1 - xy[1] / height * 2) * half[1]
    d = normalize(w[:, None] + spread(sx) * u[:, None] + spread(sy) * v[:, None])
    return jnp.broadcast_to(eye[:, None], d.shape), d


def pixel_grid(width: int, height: int, offset: Float[Array, " 2"]) -> Float[Array, "2 p"]:
    """Image positions of every pixel at sub-pixel `offset`, row-major (P = H·W)."""
    i = jnp.arange(width, dtype=offset.dtype) + offset[0]
    j = jnp.arange(height, dtype=offset.dtype) + offset[1]
    return jnp.stack([jnp.broadcast_to(i[None, :], (height, width)), jnp.broadcast_to(j[:, None], (height, width))]).reshape(2, -1)


def primary_rays(
    eye: Float[Array, " 3"],
    refp: Float[Array, " 3"],
    vang: Float[Array, " 2"],
    width: int,
    height: int,
    offset: Float[Array, " 2"],
):
    """Origins and unit directions (3, P) of one ray per pixel at sub-pixel `offset`,
    row-major (P = H·W): pixel (i, j) samples (i + ox, j + oy) (see `rays_through`)."""
    return rays_through(eye, refp, vang, width, height, pixel_grid(width, height, offset))


def pixel_angle(vang: Float[Array, "2"], width: int) -> Float[Array, ""]:
    """The width of one pixel on the screen, per unit of distance from the eye (at the centre)."""
    return 2 * jnp.tan(jnp.deg2rad(vang[0]) / 2) / width
