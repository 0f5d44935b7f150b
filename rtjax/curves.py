"""Intersection curves of spheres that cut into one another, as edges of the silhouette
mode's box filter.

Where the surface of a sphere E cuts that of the sphere H a ray meets, the nearest hit
switches from H to E where the hit lies on E: a curve that is not an outline, so the
silhouette search (`edges.EdgeWatch`) does not see it. Across it the colour jumps like
across a silhouette, so it is box-filtered the same way: its signed distance δ = s/|∇s|
in sample steps, s the hit's distance from E's surface (positive on H's side), the rate
from the ray differentials, the sides traced with H removed (E's side) and with E
removed (H's side). The hit may enter H or leave it, the ray be outside E or inside it
(glass)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import spheres
from .numerics import dot, norm, normalize, safe_div, safe_sqrt, tiny


def inside(b, f2, r2, is_origin):
    """Whether rays are inside spheres, from b = f·d and f2 = |f|² (`spheres.offsets`):
    |f| < r, or, on the sphere the ray leaves (`is_origin`), pointing inward (b < 0), as
    `spheres.roots` decides it. Not differentiated (a discrete choice)."""
    return jnp.where(is_origin, b < 0, f2 < r2)


def curve_terms(o, d, diff, ce, re, ch, rh, leaves_e, leaves_h):
    """Signed distance δ (sample steps, > 0 on H's side) from rays to the curve where
    sphere E (ce, re) cuts into H (ch, rh), and the curve's normal (nx, ny) in the image;
    `leaves_e`, `leaves_h`: whether each ray starts on E's or H's surface, leaving it
    (which, with the ray's direction, says whether it is inside: `inside`).

    The curve is the zero set of s = ±(|P − c_E| − r_E), P the ray's hit on H (its far
    root from inside H; `spheres.root_at`), the sign − from inside E: s is the hit's
    distance from E's surface, > 0 where H is met first, and smooth wherever H is met
    (unlike t_E − t_H, whose rate has no bound where the ray grazes E). δ = s/|∇s|, ∇s from the ray
    differentials; differentiable in the scene, the rate included: off the curve (δ ≠ 0,
    within the box) δ moves with it."""
    sg = jax.lax.stop_gradient
    fh, b, l = spheres.offsets(o, d, ch)
    fe, be, _ = spheres.offsets(*sg((o, d, ce)))
    in_e = inside(be, dot(fe, fe), sg(re) ** 2, leaves_e)
    in_h = inside(sg(b), sg(dot(fh, fh)), sg(rh) ** 2, leaves_h)
    dtype = jnp.result_type(o)
    floor = jnp.asarray(tiny(dtype), dtype)
    sq = safe_sqrt(rh**2 - dot(l, l), floor)
    th, nh = spheres.root_at(b, l, sq, d, rh, in_h)
    sign = jnp.where(in_e, -1, 1)
    u = o + th * d - ce
    s = sign * (norm(u) - re)
    ne = sign * normalize(u)
    gx, gy = (dot(ne, spheres.surface_motion(nh, th, d, ~in_h, do, dd)) for do, dd in (diff[:2], diff[2:]))
    norm_ = safe_sqrt(gx**2 + gy**2, floor)
    return safe_div(s, norm_), safe_div(gx, norm_), safe_div(gy, norm_)


def nearest_curve(o, d, diff, origin, live, hit: spheres.Hit, tab: spheres.Table, centers, radii,
                  width) -> tuple[Float[Array, " p"], Int[Array, " p"]]:
    """Per ray that meets a sphere H (its hit, entering or leaving it): among the spheres
    E whose surfaces cut H's, the one whose curve with H is nearest (`curve_terms`' δ),
    within `width` sample steps: its distance (inf: none) and index (−1); `origin`, the
    sphere each ray leaves (or −1). Without derivatives."""
    sg = jax.lax.stop_gradient
    o, d, centers, radii = sg((o, d, centers, radii))
    ox, dx, oy, dy = sg(tuple(diff))
    n = centers.shape[0]
    k = jnp.arange(n)[:, None]
    h = jnp.maximum(hit.index, 0)
    r = radii[:, None]
    rh = radii[h][None, :]
    th = sg(hit.t)
    gap = sum((centers[:, None, i] - centers[h][None, :, i]) ** 2 for i in range(3))  # no reduction over 3
    cuts = (gap < (r + rh) ** 2) & (gap > (r - rh) ** 2)
    leaves = origin[None, :] == k
    within = inside(tab.b, tab.f2, r**2, leaves)
    # a ray leaving E outward: the curve it would see near its origin is the previous
    # segment's, where the ray met E (or H from inside E) there
    ok = (live & hit.found)[None, :] & (k != hit.index[None, :]) & cuts & (within | ~leaves)
    u = (o + th * d)[:, None, :] - centers.T[:, :, None]
    dist = jnp.sqrt(jnp.maximum(dot(u, u), tiny(o.dtype)))
    nh = sg(hit.normal_out)
    gx, gy = (dot(u / dist, spheres.surface_motion(nh, th, d, hit.entering, do, dd)[:, None, :])
              for do, dd in ((ox, dx), (oy, dy)))
    floor = jnp.asarray(tiny(o.dtype), o.dtype)
    delta = jnp.abs(dist - r) / jnp.sqrt(jnp.maximum(gx**2 + gy**2, floor))  # |s|/|∇s|: s's sign is the side
    score = jnp.where(ok & (delta < width), delta, jnp.inf)
    idx = jnp.argmin(score, axis=0)
    best = jnp.take_along_axis(score, idx[None], axis=0)[0]
    return best, jnp.where(jnp.isfinite(best), idx, -1).astype(jnp.int32)
