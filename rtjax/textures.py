"""Texture mapping (DECK.md §4): longitude/colatitude with z up, bilinear, u wraps.

For a hit with outward unit normal p = (P − C)/r:

    u = atan2(p_y, p_x)/(2π) + ½     (wraps; the seam u = 0 ≡ 1 is the −x axis)
    v = acos(p_z)/π                  (v = 0 at the north pole +z: the texture's top row)

The texel there, sampled bilinearly with texel centres at ((x + ½)/w, (y + ½)/h),
columns wrapping and rows clamped, divided by 255, is the diffuse colour d.

Derivatives (DECK.md §6: never NaN):
- v is computed as atan2(ρ, p_z) with ρ = |(p_x, p_y)|, which equals acos(p_z) for
  a unit p (and for any length of p) but has no infinite slope at p_z = ±1.
- At a pole (ρ² ≤ tiny) longitude is undefined: u is taken as ½ (as atan2(0, 0) = 0
  gives) with a zero derivative, and ρ has a zero derivative (`numerics.norm`); the
  colour there is the top (bottom) row interpolated at u = ½. The exact slope of v at
  a pole depends on the direction one leaves it in; 0 is the choice made here. Near a
  pole, u's slope grows like 1/ρ (the map's own singularity), large but finite.
- On the seam atan2 jumps from π to −π, but its derivative is continuous there and
  the sampled colour is the same on both sides (columns wrap), so the colour and its
  derivative are continuous across the seam.
- p = 0 (a ray that met nothing; its colour is discarded) is treated as the north
  pole, so even discarded lanes carry no NaN into forward-mode tangents.

The colour is linear in the texels, so a texture can be a fitted parameter.

Speed: in float32, angles come from `fast_atan2`, a branch-free polynomial (Abramowitz &
Stegun 4.4.49) accurate to about 3e-7 rad, about float32 rounding (u is off by at most
~5e-8, far below a texel): XLA's CPU atan2 is a scalar library call. float64 (gradient
checks, comparisons with the reference) uses the exact atan2. `textured_diffuse` runs
its stages under `lax.cond`s, which materialise each stage once (and skip it when no ray
of a segment hits a textured sphere) where XLA's CPU fusion would recompute them per
colour channel and per light.

Several textures of different sizes are sampled in one pass: their texels are laid
end to end in one (3, Σ h·w) array and each ray looks up its own texture's width,
height and offset, so the cost of a segment does not grow with the number of textures.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .numerics import tiny


#: atan(a) ≈ a·Σ c_k·a^(2k) on [0, 1], |error| ≤ 2e-8 (Abramowitz & Stegun 4.4.49).
_ATAN_COEFFS = (
    1.0,
    -0.3333314528,
    0.1999355085,
    -0.1420889944,
    0.1065626393,
    -0.0752896400,
    0.0429096138,
    -0.0161657367,
    0.0028662257,
)


@jax.custom_jvp
def fast_atan2(y, x):
    """atan2(y, x) from a polynomial, elementwise ops only (vectorises on a CPU).

    Octant reduction to a = min/max of |x|, |y| in [0, 1], then a·poly(a²). Accuracy
    about 1e-7 rad in float32, 2e-8 rad in float64. atan2(0, 0) = 0.
    The derivative is the exact one, (x·dy − y·dx)/(x² + y²), computed on inputs scaled
    by max(|x|, |y|) so that it stays finite for tiny arguments; 0 at (0, 0).
    """
    ax, ay = jnp.abs(x), jnp.abs(y)
    swap = ay > ax
    num = jnp.where(swap, ax, ay)
    den = jnp.where(swap, ay, ax)
    a = num / jnp.where(den > 0, den, 1)
    s = a * a
    poly = jnp.asarray(_ATAN_COEFFS[-1], a.dtype)
    for c in _ATAN_COEFFS[-2::-1]:
        poly = poly * s + c
    r = a * poly
    r = jnp.where(swap, jnp.pi / 2 - r, r)
    r = jnp.where(x < 0, jnp.pi - r, r)
    return jnp.where(y < 0, -r, r)


@fast_atan2.defjvp
def _fast_atan2_jvp(primals, tangents):
    y, x = primals
    dy, dx = tangents
    m = jnp.maximum(jnp.abs(x), jnp.abs(y))
    ok = m > 0
    m = jnp.where(ok, m, 1)
    xs, ys = x / m, y / m
    den = jnp.where(ok, (xs * xs + ys * ys) * m, 1)  # xs² + ys² ∈ [1, 2] where ok
    return fast_atan2(y, x), jnp.where(ok, (xs * dy - ys * dx) / den, 0)


def sphere_uv(p: Float[Array, "3 p"]) -> tuple[Float[Array, " p"], Float[Array, " p"]]:
    """(u, v) in [0, 1]² for outward normals p (unit, or any nonzero length).

    float64: exact atan2; float32: `fast_atan2` (see the module's note on speed)."""
    atan2 = jnp.arctan2 if p.dtype == jnp.float64 else fast_atan2
    t = tiny(p.dtype)
    rho2 = p[0] * p[0] + p[1] * p[1]
    pole = rho2 <= t
    px = jnp.where(pole, 1, p[0])
    py = jnp.where(pole, 0, p[1])
    rho = jnp.where(pole, 0, jnp.sqrt(jnp.where(pole, 1, rho2)))
    pz = jnp.where(pole & (p[2] * p[2] <= t), 1, p[2])
    u = atan2(py, px) / (2 * jnp.pi) + 0.5
    v = atan2(rho, pz) / jnp.pi
    return u, v


def _sample(flat, u, v, w, h, offset):
    """Bilinear lookup in a (3, N) texel array; w, h, offset per ray (or scalars).

    x = u·w − ½ and y = v·h − ½ place texel centres at integers; columns wrap (mod w),
    rows clamp to [0, h − 1]. Returns (3, P).
    """
    dtype = u.dtype
    x = u * jnp.asarray(w, dtype) - 0.5
    y = v * jnp.asarray(h, dtype) - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0  # floor has a zero derivative: d fx = d x
    fy = y - y0
    ix0 = jnp.mod(x0.astype(jnp.int32), w)
    ix1 = jnp.mod(ix0 + 1, w)
    iy = y0.astype(jnp.int32)
    iy0 = jnp.clip(iy, 0, h - 1)
    iy1 = jnp.clip(iy + 1, 0, h - 1)
    row0, row1 = offset + iy0 * w, offset + iy1 * w
    top = flat[:, row0 + ix0] * (1 - fx) + flat[:, row0 + ix1] * fx
    bottom = flat[:, row1 + ix0] * (1 - fx) + flat[:, row1 + ix1] * fx
    return top * (1 - fy) + bottom * fy


def bilinear(texels: Float[Array, "h w 3"], u: Float[Array, " p"], v: Float[Array, " p"]) -> Float[Array, "p 3"]:
    """Bilinear sample of one texture at (u, v): (P, 3) texel values (0..255)."""
    h, w = texels.shape[:2]
    flat = texels.reshape(h * w, 3).T
    return _sample(flat, u, v, w, h, 0).T


def texture_colour(texels: Float[Array, "h w 3"], p: Float[Array, "3 p"]) -> Float[Array, "3 p"]:
    """The diffuse colour d in 0..1 that a texture gives the unit-sphere point p."""
    u, v = sphere_uv(p)
    return bilinear(texels, u, v).T / 255


def textured_diffuse(
    textures: Sequence[Float[Array, "h w 3"]],
    texture_of: Int[Array, " p"],
    p: Float[Array, "3 p"],
    d: Float[Array, "3 p"],
) -> Float[Array, "3 p"]:
    """Per ray, the texture's colour where `texture_of` ≥ 0 (an index into `textures`),
    else `d` unchanged. One (u, v) and one bilinear lookup per ray, whatever the count
    and sizes of the textures.

    The work runs under `lax.cond`s on "some ray hits a textured sphere": skipped when
    none does, and each stage's result is materialised once (XLA's CPU fusion would
    otherwise inline the (u, v) polynomial and index arithmetic into every consumer).
    Both modes of differentiation go through `lax.cond`.
    """
    if not textures:
        return d
    shapes = [t.shape[:2] for t in textures]
    if len(textures) == 1:
        ((h, w),) = shapes
        sel = (h, w, 0)
        flat = textures[0].reshape(h * w, 3).T
    else:
        sizes = [h * w for h, w in shapes]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
        k = jnp.maximum(texture_of, 0)
        hs = jnp.asarray(np.array([h for h, _ in shapes], np.int32))[k]
        ws = jnp.asarray(np.array([w for _, w in shapes], np.int32))[k]
        sel = (hs, ws, jnp.asarray(offsets)[k])
        flat = jnp.concatenate([t.reshape(-1, 3) for t in textures], axis=0).T
    flat = flat.astype(p.dtype)
    textured = texture_of >= 0
    some = jnp.any(textured)

    def lookup(args):
        flat, p, d = args
        uv = jax.lax.cond(some, lambda q: jnp.stack(sphere_uv(q)), lambda q: jnp.zeros_like(q[:2]), p)
        h, w, offset = sel
        colour = _sample(flat, uv[0], uv[1], w, h, offset) / 255
        return jnp.where(textured, colour, d)

    return jax.lax.cond(some, lookup, lambda args: args[2], (flat, p, d))
