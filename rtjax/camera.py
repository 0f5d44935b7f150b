"""Camera and image geometry (DECK.md §2): z up, square pixels, row 0 at the top."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .numerics import normalize as _normalize


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


def primary_rays(
    eye: Float[Array, "3"],
    refp: Float[Array, "3"],
    vang: Float[Array, "2"],
    width: int,
    height: int,
    offset: Float[Array, "2"],
):
    """Origins and unit directions (3, P) of one ray per pixel, row-major (P = H·W).

    Pixel (i, j) at sub-pixel `offset` samples the screen point
    ((i + ox)/W·2 − 1, 1 − (j + oy)/H·2) in units of the half extents R·tan(ha/2),
    R·tan(va/2). The direction does not depend on R, so R never appears.
    """
    dtype = eye.dtype
    w, u, v = basis(eye, refp)
    half = jnp.tan(jnp.deg2rad(vang) / 2)
    i = jnp.arange(width, dtype=dtype)
    j = jnp.arange(height, dtype=dtype)
    x = (i + offset[0]) / width * 2 - 1
    y = 1 - (j + offset[1]) / height * 2
    sx = u[:, None, None] * (x * half[0])[None, None, :]
    sy = v[:, None, None] * (y * half[1])[None, :, None]
    d = normalize(w[:, None, None] + sx + sy).reshape(3, -1)
    o = jnp.broadcast_to(eye[:, None], d.shape)
    return o, d


def pixel_angle(vang: Float[Array, "2"], width: int) -> Float[Array, ""]:
    """The width of one pixel on the screen, per unit of distance from the eye (at the centre)."""
    return 2 * jnp.tan(jnp.deg2rad(vang[0]) / 2) / width
