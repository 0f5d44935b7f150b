"""The silhouette-aware mode: box-filtered edges whose derivatives include edge motion.

A pixel-centre render is piecewise constant across a sphere's silhouette and across a
shadow's edge, so its derivative misses what moves them. Spheres make both edges
analytic, so this mode blends, per pixel, across the one nearest edge:

* Primary silhouettes. For each sphere the sine of the angle between the pixel's ray
  and the sphere's silhouette cone is closed-form, g = (l·q + b·r)/D² (l: distance from
  the centre to the ray, D: from the centre to the eye, q = √(D² − r²), b = (o − c)·d);
  its rate per pixel comes from the ray's change per pixel (a jvp of the camera), so
  δ = g/|∇g| is the signed distance to the silhouette in pixels, and the edge's
  direction in the image is ∇g/|∇g|. The nearest visible silhouette within reach is
  blended: pixel = α·C_in + (1 − α)·C_out, where α is the fraction of a box of side
  `width` pixels inside the silhouette (exact for a straight edge), C_in the colour
  of a ray through the centroid of the box's inside part (made to meet the sphere,
  grazing its silhouette if the linearised offset misses it) and C_out the colour of
  a ray through the centroid of the outside part, traced with that sphere removed.
* Shadow edges at primary hits. A parallel light's shadow of sphere j is a cylinder;
  the signed distance of the shadow ray to it is |l| − r, and its rate per pixel
  follows from the hit point's motion per pixel on the surface. The nearest occluder
  edge's hard factor (0 or kt²) becomes 1 − (1 − τ)·α.

What it does not cover: silhouettes and shadow edges seen in mirrors or through glass
(secondary segments are traced as in the plain mode), a second edge in the same pixel,
and the specular term's cut-off at the terminator. As `width` → 0, α becomes a step
and the image is the plain one. Cost: two traces (one with the edge sphere toggled)
plus per-sphere edge distances: about 2–3× a plain render.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .camera import primary_rays
from .numerics import dot, normalize, safe_div, safe_sqrt, tiny
from .scene import Params, Structure
from . import spheres

#: Smallest |component| of an edge's normal used in the box filter: keeps the
#: trapezoid formula's division well conditioned for axis-aligned edges.
_MIN_COMPONENT = 0.05


def _trapezoid(a, b):
    a, b = jnp.abs(a), jnp.abs(b)
    a, b = jnp.maximum(a, b), jnp.maximum(jnp.minimum(a, b), _MIN_COMPONENT)
    return (a + b) / 2, (a - b) / 2, a * b


def _ramps(x, s, e, power):
    def ramp(z):
        return jnp.maximum(z, 0) ** power

    return ramp(x + s) - ramp(x + e) - ramp(x - e) + ramp(x - s)


def coverage(x, a, b):
    """Fraction of a unit square on the inner side of a straight edge.

    x: signed distance from the square's centre to the edge in units of its side,
    positive inside; (a, b): the edge normal's components in the image. The fraction is
    the CDF F of z = a·U₁ + b·U₂ for U uniform on [−½, ½]: a trapezoid's integral, C¹.
    """
    s, e, ab = _trapezoid(a, b)
    return _ramps(x, s, e, 2) / (2 * ab)


def split_box(x, a, b):
    """Coverage α and the centroids of the square's inside and outside parts.

    Centroids are positions along the inward normal, in units of the side, relative to
    the centre: E[z | z > −x] and E[z | z < −x], from F and G = ∫F (cubic ramps).
    """
    s, e, ab = _trapezoid(a, b)

    def f(y):
        return _ramps(y, s, e, 2) / (2 * ab)

    def g(y):
        return _ramps(y, s, e, 3) / (6 * ab)

    alpha = f(x)
    inside = jnp.clip(safe_div(g(x), alpha) - x, -s, s)
    outside = jnp.clip(-x - safe_div(g(-x), f(-x)), -s, s)
    return alpha, inside, outside


class Footprint(NamedTuple):
    """How a primary ray's direction changes per sample step, across and down (3, P)."""

    dx: Float[Array, "3 p"]
    dy: Float[Array, "3 p"]
    width: float  # edge width in sample steps (pixels when spp = 1)


def primary_footprint(p: Params, s: Structure, offset, spp: int, width: float):
    """Primary rays and their footprint: d and ∂d per sample step, by forward-mode AD."""

    def dirs(off):
        return primary_rays(p.eye, p.refp, p.vang, s.width, s.height, off)[1]

    step = jnp.asarray(1 / spp, offset.dtype)
    zero = jnp.zeros((), offset.dtype)
    d, dx = jax.jvp(dirs, (offset,), (jnp.stack([step, zero]),))
    _, dy = jax.jvp(dirs, (offset,), (jnp.stack([zero, step]),))
    o = jnp.broadcast_to(p.eye[:, None], d.shape)
    return o, d, Footprint(dx, dy, width)


def _silhouette_terms(o, d, fp: Footprint, c, r):
    """Signed distance to the silhouette in samples, edge normal (nx, ny), eye outside?

    Works for (3, P) against one sphere per ray (c: (3, P), r: (P,)) and broadcasts to
    (3, N, P) against all spheres.
    """
    f = o - c
    b = dot(f, d)
    lvec = f - b * d
    l2 = dot(lvec, lvec)
    d2 = dot(f, f)
    outside = d2 > r**2
    l = safe_sqrt(l2, jnp.asarray(tiny(o.dtype), o.dtype))
    q = safe_sqrt(d2 - r**2, (1e-6 * r) ** 2)
    g = safe_div(l * q + b * r, d2)
    lhat = normalize(lvec)
    gx, gy = dot(lhat, fp.dx), dot(lhat, fp.dy)
    rate = safe_sqrt(gx**2 + gy**2, jnp.asarray(tiny(o.dtype), o.dtype))
    return safe_div(g, rate), safe_div(gx, rate), safe_div(gy, rate), outside, b


def choose_silhouette(o, d, fp: Footprint, centers, radii, plain: spheres.Hit) -> Int[Array, " p"]:
    """Per ray, the sphere whose visible silhouette is nearest within reach, or −1.

    Visible: the centre ray hits that sphere first (from outside), or it misses it and
    the sphere's closest point to the ray lies in front of whatever the ray hits.
    """
    o, d, fp, centers, radii = jax.lax.stop_gradient((o, d, fp, centers, radii))
    c = centers.T[:, :, None]
    delta, _, _, outside, b = _silhouette_terms(o[:, None, :], d[:, None, :], _bcast(fp), c, radii[:, None])
    n = centers.shape[0]
    is_hit = plain.index[None, :] == jnp.arange(n)[:, None]
    in_front = (-b > 0) & (~plain.found[None, :] | (-b < plain.t[None, :]))
    visible = outside & jnp.where(is_hit, plain.entering[None, :] & (delta < 0), (delta >= 0) & in_front)
    score = jnp.where(visible & (jnp.abs(delta) < fp.width), jnp.abs(delta), jnp.inf)
    best = jnp.argmin(score, axis=0)
    return jnp.where(jnp.isfinite(jnp.min(score, axis=0)), best, -1)


def _bcast(fp: Footprint) -> Footprint:
    return Footprint(fp.dx[:, None, :], fp.dy[:, None, :], fp.width)


def _chosen_or_regular(edge, o, d, centers, radii):
    """Centre and radius of each ray's chosen sphere; where none is chosen, a stand-in
    sphere well clear of the ray (so the unused branch has finite derivatives: the
    double-where pattern, applied to the geometry)."""
    e = jnp.maximum(edge, 0)
    c, r = centers.T[:, e], radii[e]
    x, y, z = d
    use_z = jnp.abs(z) < 0.9
    side = normalize(jnp.stack([jnp.where(use_z, y, 0), jnp.where(use_z, -x, z), jnp.where(use_z, 0, -y)]))
    stand_in = o + r * (3 * d + 2 * side)  # d × ẑ or d × x̂, unit: 2r off the ray, 3r along it
    has = edge >= 0
    return jnp.where(has, c, jax.lax.stop_gradient(stand_in)), r


def silhouette_split(o, d, fp: Footprint, centers, radii, edge):
    """For the chosen silhouette: coverage α of the pixel's box and the directions of
    rays through the centroids of its inside and outside parts (differentiable)."""
    c, r = _chosen_or_regular(edge, o, d, centers, radii)
    delta, nx, ny, _, _ = _silhouette_terms(o, d, fp, c, r)
    alpha, z_in, z_out = split_box(-delta / fp.width, nx, ny)
    inward = -(nx * fp.dx + ny * fp.dy) * fp.width  # one box side inward, as a change of d
    has = edge >= 0
    d_in = jnp.where(has, normalize(d + z_in * inward), d)
    d_out = jnp.where(has, normalize(d + z_out * inward), d)
    return alpha, d_in, d_out


def hit_footprint(hit: spheres.Hit, d, fp: Footprint):
    """How the first hit point moves per sample step: t·(∂d − (N·∂d)/(N·d)·d).

    At grazing incidence the motion is unbounded; |N·d| is floored at 0.05 there.
    """
    nd = dot(hit.normal_out, d)
    nd = jnp.where(nd < 0, jnp.minimum(nd, -0.05), jnp.maximum(nd, 0.05))
    move = [hit.t * (dd - dot(hit.normal_out, dd) / nd * d) for dd in (fp.dx, fp.dy)]
    return move[0], move[1]


def _shadow_terms(point, ray, dpx, dpy, c, r):
    """Signed distance (in samples) from shadow rays to an occluder's shadow cylinder,
    the edge normal in the image, and b = (P − c)·L (negative: the occluder is ahead)."""
    f = point - c
    bl = dot(f, ray)
    lvec = f - bl * ray
    floor = jnp.asarray(tiny(point.dtype), point.dtype)
    l = safe_sqrt(dot(lvec, lvec), floor)
    lhat = normalize(lvec)
    sx, sy = dot(lhat, dpx), dot(lhat, dpy)
    rate = safe_sqrt(sx**2 + sy**2, floor)
    return safe_div(l - r, rate), safe_div(sx, rate), safe_div(sy, rate), bl


def soft_shadow(hit: spheres.Hit, light, centers, radii, tmin, factor, dpx, dpy, width: float):
    """Visibility of one light at each hit, its nearest shadow edge box-filtered.

    The hard visibility of every other occluder times the soft factor 1 − (1 − τ)·α of
    the nearest edge within reach (τ: 0, or kt² for glass; α: fraction of the pixel's
    footprint on the surface inside that occluder's shadow cylinder). The hit's own
    sphere stays hard: its terminator is already continuous in max(N·L, 0).
    """
    n = centers.shape[0]
    ray = jnp.broadcast_to(light[:, None], hit.point.shape)
    sg = jax.lax.stop_gradient
    delta, _, _, bl = _shadow_terms(
        sg(hit.point)[:, None, :], sg(ray)[:, None, :], sg(dpx)[:, None, :], sg(dpy)[:, None, :],
        sg(centers).T[:, :, None], sg(radii)[:, None],
    )
    own = hit.index[None, :] == jnp.arange(n)[:, None]
    near = (-bl > tmin) & ~own & hit.found[None, :] & (jnp.abs(delta) < width)
    score = jnp.where(near, jnp.abs(delta), jnp.inf)
    edge = jnp.where(jnp.isfinite(jnp.min(score, axis=0)), jnp.argmin(score, axis=0), -1)
    hard = spheres.transmission(hit.point, ray, centers, radii, hit.index, tmin, factor, skip=edge)
    c, r = _chosen_or_regular(edge, hit.point, ray, centers, radii)
    delta_e, nx, ny, _ = _shadow_terms(hit.point, ray, dpx, dpy, c, r)
    soft = 1 - (1 - factor[jnp.maximum(edge, 0)]) * coverage(-delta_e / width, nx, ny)
    return hard * jnp.where(edge >= 0, soft, 1)
