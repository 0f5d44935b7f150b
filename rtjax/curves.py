"""Intersection curves of spheres that cut into one another, as edges of the silhouette
mode's box filter.

Where sphere E cuts into the sphere H a ray meets, the nearest hit switches from H to E
along the curve t_E = t_H (near roots), which is not an outline: the silhouette search
(`edges.EdgeWatch`) does not see it. Across it the colour jumps like across a silhouette,
so it is box-filtered the same way: its signed distance δ = (t_E − t_H)/|∇(t_E − t_H)|
in sample steps (positive on H's side), the rate from the ray differentials, the sides
traced with H removed (E's side) and with E removed (H's side).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import spheres
from .numerics import dot, safe_div, safe_sqrt, tiny


def entry(o, d, c, r):
    """Distance t to the near root of rays (o, d) (unit d) on spheres (c, r), and the
    outward normal there; broadcasts over (3, ...) and (...)."""
    f, b, l = spheres.offsets(o, d, c)
    dtype = jnp.result_type(o)
    disc = r**2 - dot(l, l)
    sq = safe_sqrt(disc, jnp.asarray(tiny(dtype), dtype))
    t = -b - sq
    return t, (l - sq * d) / r


def entry_rate(normal, t, d, do, dd):
    """∂t per sample step of a ray's hit at distance t with outward `normal`, the ray
    moving by (∂o, ∂d): −N·(∂o + t·∂d)/(N·d)."""
    return -safe_div(dot(normal, do + t * dd), dot(normal, d))


def curve_terms(o, d, diff, ce, re, ch, rh):
    """Signed distance δ (sample steps, > 0 on H's side) from rays to the curve where
    sphere E (ce, re) cuts into H (ch, rh), and the curve's normal (nx, ny) in the image.
    δ and the normal are differentiable in the scene, the rate included: off the curve
    (δ ≠ 0, within the box) δ moves with it."""
    te, ne = entry(o, d, ce, re)
    th, nh = entry(o, d, ch, rh)
    ox, dx, oy, dy = diff
    gx = entry_rate(ne, te, d, ox, dx) - entry_rate(nh, th, d, ox, dx)
    gy = entry_rate(ne, te, d, oy, dy) - entry_rate(nh, th, d, oy, dy)
    floor = jnp.asarray(tiny(jnp.result_type(o)), jnp.result_type(o))
    norm_ = safe_sqrt(gx**2 + gy**2, floor)
    return safe_div(te - th, norm_), safe_div(gx, norm_), safe_div(gy, norm_)


def nearest_curve(o, d, diff, live, hit: spheres.Hit, tab: spheres.Table, centers, radii,
                  width) -> tuple[Float[Array, " p"], Int[Array, " p"]]:
    """Per ray that enters a sphere H (its hit, from outside): among the spheres E that
    cut into H and that the ray enters next, the one whose curve with H is nearest, within
    `width` sample steps: its distance (inf: none) and index (−1). Without derivatives."""
    sg = jax.lax.stop_gradient
    o, d, centers, radii = sg((o, d, centers, radii))
    ox, dx, oy, dy = sg(tuple(diff))
    n = centers.shape[0]
    k = jnp.arange(n)[:, None]
    h = jnp.maximum(hit.index, 0)
    r = radii[:, None]
    disc = r**2 - tab.l2
    tk = -tab.b - jnp.sqrt(jnp.maximum(disc, 0))
    th = sg(hit.t)[None, :]
    gap = sum((centers[:, None, i] - centers[h][None, :, i]) ** 2 for i in range(3))  # no reduction over 3
    cuts = gap < (r + radii[h][None, :]) ** 2
    ok = (live & hit.found & hit.entering)[None, :] & (k != hit.index[None, :]) & (tab.f2 > r**2) & (disc > 0)
    ok = ok & (tk >= th) & cuts
    normal = (o[:, None, :] + tk[None] * d[:, None, :] - centers.T[:, :, None]) / r[None]
    nh = sg(hit.normal_out)
    thx, thy = entry_rate(nh, th[0], d, ox, dx), entry_rate(nh, th[0], d, oy, dy)
    gx = entry_rate(normal, tk, d[:, None, :], ox[:, None, :], dx[:, None, :]) - thx[None, :]
    gy = entry_rate(normal, tk, d[:, None, :], oy[:, None, :], dy[:, None, :]) - thy[None, :]
    floor = jnp.asarray(tiny(o.dtype), o.dtype)
    delta = (tk - th) / jnp.sqrt(jnp.maximum(gx**2 + gy**2, floor))
    score = jnp.where(ok & (delta < width), delta, jnp.inf)
    idx = jnp.argmin(score, axis=0)
    best = jnp.take_along_axis(score, idx[None], axis=0)[0]
    return best, jnp.where(jnp.isfinite(best), idx, -1).astype(jnp.int32)
