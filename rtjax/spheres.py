"""Ray–sphere intersection: nearest hits, shadow transmission, silhouette distance.

Layout: vectors are component-major, (3, P), so every operation is elementwise over
rays and vectorises well; sphere data is (N, 3) as in `Params`.

Numerics: with f = o − c and a unit direction d, b = f·d and the perpendicular offset
l = f − b·d give disc = r² − |l|² without the cancellation of b² − (|f|² − r²) (Ray
Tracing Gems, ch. 7). Roots are −b ∓ √disc.

Two passes: the choice of the nearest sphere (all rays × all spheres) is discrete and
carries no derivative, so it runs under `stop_gradient`; the chosen sphere's distance
and normal are then recomputed per ray, differentiably, at the cost of one sphere.

Self-intersection is decided exactly, not by an epsilon: a ray that leaves the surface
of sphere k (its `origin`) cannot hit k again if it points outward (spheres are convex)
and can only hit k's far side if it points inward. Other spheres need t > `tmin`, a
length relative to the scene's scale (touching spheres), never an absolute constant.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .numerics import dot, normalize, safe_sqrt

#: Relative size of the hit-distance floor for spheres other than the ray's origin.
TMIN_REL = {jnp.dtype(jnp.float32): 1e-4, jnp.dtype(jnp.float64): 1e-9}
#: Relative floor of √disc's slope: rays this close to tangent get a capped derivative.
SLOPE_REL = {jnp.dtype(jnp.float32): 1e-4, jnp.dtype(jnp.float64): 1e-7}


def scene_scale(centers, radii, eye) -> Float[Array, ""]:
    """A length for relative tolerances: how far the scene reaches from the origin (no gradient)."""
    s = jnp.maximum(jnp.max(jnp.abs(centers) + radii[:, None]), jnp.max(jnp.abs(eye)))
    return jax.lax.stop_gradient(s)


def tmin_for(scale) -> Float[Array, ""]:
    return scale * TMIN_REL[jnp.dtype(scale.dtype)]


def _roots(o, d, centers, radii, origin, tmin):
    """For every sphere and ray (N, P): may the near / far root be used, and their values.

    The origin rule: for o on sphere k, b = r·(n_out·d), so b < 0 means inward.
    """
    c = centers.T[:, :, None]  # (3, N, 1)
    f = o[:, None, :] - c  # (3, N, P)
    dd = d[:, None, :]
    b = dot(f, dd)
    l = f - b * dd
    disc = radii[:, None] ** 2 - dot(l, l)
    meets = disc > 0
    sq = jnp.sqrt(jnp.maximum(disc, 0))
    near, far = -b - sq, -b + sq
    is_origin = origin[None, :] == jnp.arange(centers.shape[0])[:, None]
    near_ok = meets & (near > tmin) & ~is_origin
    far_ok = meets & (far > tmin) & (~is_origin | (b < 0))
    return near_ok, far_ok, near, far


def nearest(o, d, centers, radii, origin: Int[Array, " p"], tmin, exclude=None):
    """Per ray: distance to the nearest valid root (+inf if none), which sphere, and
    whether it is that sphere's far root. Not differentiated (a discrete choice)."""
    o, d, centers, radii = jax.lax.stop_gradient((o, d, centers, radii))
    near_ok, far_ok, near, far = _roots(o, d, centers, radii, origin, tmin)
    if exclude is not None:  # silhouette mode: the same rays with one sphere removed
        keep = exclude[None, :] != jnp.arange(centers.shape[0])[:, None]
        near_ok, far_ok = near_ok & keep, far_ok & keep
    # Far roots carry a minus sign (both roots are > tmin > 0), so one argmin over |t|
    # and one gather answer all three questions: the form XLA's CPU backend runs fastest.
    signed = jnp.where(near_ok, near, jnp.where(far_ok, -far, jnp.inf))
    idx = jnp.argmin(jnp.abs(signed), axis=0).astype(jnp.int32)
    t = jnp.take_along_axis(signed, idx[None], axis=0)[0]
    return jnp.abs(t), idx, t < 0


def sphere_geometry(o, d, c, r):
    """Per ray, for one given sphere each: b, l (3, P), √disc (with a capped slope)."""
    f = o - c
    b = dot(f, d)
    l = f - b * d
    disc = r**2 - dot(l, l)
    sq = safe_sqrt(disc, (SLOPE_REL[jnp.dtype(o.dtype)] * r) ** 2)
    return b, l, sq


class Hit:
    """The nearest hit of each ray: distance, sphere index, point, outward unit normal,
    and whether the ray enters the sphere (it met the near root, from outside).

    The normal is (P − c)/r computed as (l ± √disc·d)/r, which stays accurate when the
    scene sits far from the origin (no large o + t·d − c cancellation).

    The silhouette mode alters the first segment per ray: `exclude` (a sphere index or
    −1) removes one sphere; `force` (an index or −1) makes the ray see that sphere: if
    its nearest hit is anything else, it grazes that sphere at its silhouette point
    c + r·l̂, where the ray passes closest to it (entering).
    """

    def __init__(self, o, d, centers, radii, origin, tmin, exclude=None, force=None):
        best, idx, far = nearest(o, d, centers, radii, origin, tmin, exclude)
        found = jnp.isfinite(best)
        if force is not None:
            forced = (force >= 0) & (~found | (idx != force))
            found, idx, far = found | forced, jnp.where(forced, force, idx), far & ~forced
        self.found: Bool[Array, " p"] = found
        self.index: Int[Array, " p"] = jnp.where(found, idx, -1)
        self.entering: Bool[Array, " p"] = found & ~far
        sign = jnp.where(far, 1, -1).astype(o.dtype)
        c, r = centers.T[:, idx], radii[idx]
        b, l, sq = sphere_geometry(o, d, c, r)
        t = -b + sign * sq
        normal = (l + sign * sq * d) / r
        point = o + t * d
        if force is not None:
            t = jnp.where(forced, -b, t)
            normal = jnp.where(forced, normalize(l), normal)
            point = jnp.where(forced, c + r * normal, point)
        self.t = jnp.where(found, t, 0)  # no inf in later arithmetic
        self.normal_out = jnp.where(found, normal, 0)
        self.point = jnp.where(found, point, o)


def transmission(o, d, centers, radii, origin, tmin, opacity_factor, skip=None) -> Float[Array, " p"]:
    """Shadow visibility along parallel-light rays: Π over spheres met of their factor.

    `opacity_factor[j]` is 0 for opaque, mirror and textured spheres and kt² for glass
    (shadow rays pass straight through glass, weighted kt² per sphere, DECK.md §3).
    A sphere counts if the ray meets it ahead of the origin (its far root is ahead).
    `skip` (per ray, a sphere index or −1) leaves one sphere out (the silhouette mode
    accounts for it smoothly).
    """
    _, blocked, _, _ = _roots(*jax.lax.stop_gradient((o, d, centers, radii)), origin, tmin)
    if skip is not None:
        blocked = blocked & (skip[None, :] != jnp.arange(centers.shape[0])[:, None])
    factor = jnp.where(blocked, opacity_factor[:, None], 1)
    return jnp.prod(factor, axis=0)
