"""Texture mapping (DECK.md §4): longitude/colatitude with z up, bilinear, u wraps.

For a hit with outward unit normal p = (P − C)/r: u = atan2(p_y, p_x)/(2π) + ½,
v = acos(p_z)/π (v = 0 at the north pole, the texture's top row). Both angles are
taken through `atan2` on safe inputs so the poles and the seam have finite derivatives
(acos has an infinite slope at ±1; atan2(0, 0) has a 0/0 slope).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .numerics import norm, tiny


def sphere_uv(p: Float[Array, "3 p"]):
    """(u, v) in [0, 1]² for unit vectors p; u wraps at the −x axis (the seam)."""
    rho = norm(p[:2])
    pole = rho * rho <= tiny(p.dtype)
    px = jnp.where(pole, 1, p[0])
    py = jnp.where(pole, 0, p[1])
    u = jnp.arctan2(py, px) / (2 * jnp.pi) + 0.5
    v = jnp.arctan2(rho, p[2]) / jnp.pi
    return u, v


def bilinear(texels: Float[Array, "h w 3"], u: Float[Array, " p"], v: Float[Array, " p"]):
    """Bilinear sample at (u, v), texel centres at ((x + ½)/w, (y + ½)/h).

    Columns wrap (longitude is periodic); rows clamp at the poles. Differentiable in
    (u, v) and, linearly, in the texels.
    """
    h, w = texels.shape[:2]
    x = u * w - 0.5
    y = v * h - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = (x - x0)[:, None]  # texels[...] below are (P, 3)
    fy = (y - y0)[:, None]
    ix0 = jnp.mod(x0.astype(jnp.int32), w)
    ix1 = jnp.mod(ix0 + 1, w)
    iy0 = jnp.clip(y0.astype(jnp.int32), 0, h - 1)
    iy1 = jnp.clip(y0.astype(jnp.int32) + 1, 0, h - 1)
    top = texels[iy0, ix0] * (1 - fx) + texels[iy0, ix1] * fx
    bottom = texels[iy1, ix0] * (1 - fx) + texels[iy1, ix1] * fx
    return top * (1 - fy) + bottom * fy


def texture_colour(texels: Float[Array, "h w 3"], p: Float[Array, "3 p"]) -> Float[Array, "3 p"]:
    """The diffuse colour d in 0..1 that a texture gives the unit-sphere point p."""
    u, v = sphere_uv(p)
    return bilinear(texels, u, v).T / 255
