"""The fixed-depth Whitted chain: what each hit adds and which one ray it spawns.

Each hit spawns at most one ray (mirror → reflected, glass → refracted, or internally
reflected past the critical angle), so a pixel's path is a chain of depth + 1 segments,
unrolled at trace time. What is compiled follows the `Structure`: no secondary rays
without mirrors or glass, no Snell's law without glass, no shadow rays without lights,
no texture lookups without textures.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import edges, spheres
from .numerics import dot, normalize, safe_sqrt
from .scene import GLASS, MIRROR, OPAQUE, TEXTURE, Params, Structure
from .shading import local_light, phong_angles
from .textures import textured_diffuse


class Material(NamedTuple):
    """Per-sphere arrays in the form the chain uses (kinds folded in, lights normalised)."""

    diffuse: Float[Array, "n 3"]  # 0 for mirror and glass
    ks: Float[Array, " n"]  # 0 for mirror
    beta: Float[Array, " n"]
    shadow_factor: Float[Array, " n"]  # kt² for glass, 0 for the rest
    lights: Float[Array, "l 3"]  # unit vectors toward the lights
    tmin: Float[Array, ""]


def prepare(s: Structure, p: Params) -> Material:
    opaque = jnp.asarray(s.mask(OPAQUE))
    glass = jnp.asarray(s.mask(GLASS))
    return Material(
        diffuse=p.diffuse * opaque[:, None],
        ks=p.ks * ~jnp.asarray(s.mask(MIRROR)),
        beta=p.beta,
        shadow_factor=jnp.where(glass, p.kt**2, 0),
        lights=normalize(p.light_dirs, axis=-1),
        tmin=spheres.tmin_for(spheres.scene_scale(p.centers, p.radii, p.eye)),
    )


def surface_colour(s: Structure, p: Params, m: Material, idx, normal_out) -> Float[Array, "3 p"]:
    """The diffuse colour d at each hit: the sphere's own, or its texture's texel."""
    d = m.diffuse.T[:, idx]
    if s.has(TEXTURE):
        d = textured_diffuse(p.textures, jnp.asarray(s.texture_index())[idx], normal_out, d)
    return d


def shade_hit(s: Structure, p: Params, m: Material, hit: spheres.Hit, n, v, soft=None) -> Float[Array, "3 p"]:
    """Local light at each hit: Σ over lights of ambient, diffuse and specular with shadows.

    `soft` = (∂P/∂x, ∂P/∂y, width): box-filter the nearest shadow edge (silhouette mode).
    """
    total = jnp.zeros_like(n)
    if s.n_lights == 0:
        return total
    idx = jnp.maximum(hit.index, 0)
    d = surface_colour(s, p, m, idx, hit.normal_out)
    ks, beta = m.ks[idx], m.beta[idx]
    for light, colour in zip(m.lights, p.light_colors):
        if soft is None:
            ray = jnp.broadcast_to(light[:, None], n.shape)
            vis = spheres.transmission(hit.point, ray, p.centers, p.radii, hit.index, m.tmin, m.shadow_factor)
        else:
            vis = edges.soft_shadow(hit, light, p.centers, p.radii, m.tmin, m.shadow_factor, *soft)
        nl, cos_g = phong_angles(n, v, light)
        total = total + local_light(d, ks, beta, p.ke, nl, cos_g, vis, colour)
    return total


def next_direction(s: Structure, p: Params, idx, d, n, entering):
    """Mirror reflection, or for glass Snell's refraction (TIR: the reflection)."""
    cos_i = -dot(d, n)
    reflected = d + 2 * cos_i * n
    if not s.has(GLASS):
        return reflected
    eta = jnp.where(entering, 1 / p.ior[idx], p.ior[idx])
    k = 1 - eta**2 * (1 - cos_i**2)
    root = safe_sqrt(k, jnp.asarray(1e-8 if d.dtype == jnp.float32 else 1e-16, d.dtype))
    refracted = eta * d + (eta * cos_i - root) * n
    glass = jnp.asarray(s.mask(GLASS))[idx]
    return jnp.where(glass & (k > 0), refracted, reflected)


def _segment(s: Structure, p: Params, m: Material, state, toggles=None, footprint=None):
    """One segment of the chain for every ray: hit, local light, the next ray.

    `toggles` and `footprint` apply to the first segment only (silhouette mode).
    """
    o, d, origin, weight, colour = state
    toggles = toggles if toggles is not None else (None, None)
    hit = spheres.Hit(o, d, p.centers, p.radii, origin, m.tmin, *toggles)
    entering = hit.entering
    n = jnp.where(entering, hit.normal_out, -hit.normal_out)
    soft = None
    if footprint is not None:
        soft = (*edges.hit_footprint(hit, d, footprint), footprint.width)
    local = shade_hit(s, p, m, hit, n, -d, soft)
    colour = colour + weight * jnp.where(hit.found, local, p.background[:, None])
    if not s.needs_secondary_rays:
        return o, d, origin, jnp.zeros_like(weight), colour
    idx = jnp.maximum(hit.index, 0)
    alive = hit.found & jnp.asarray(s.mask(MIRROR, GLASS))[idx]
    glass = jnp.asarray(s.mask(GLASS))[idx]
    weight = jnp.where(alive, weight * jnp.where(glass, p.kt[idx], 1), 0)
    d = normalize(next_direction(s, p, idx, d, n, entering))
    return hit.point, d, hit.index, weight, colour


def trace(
    s: Structure,
    p: Params,
    o: Float[Array, "3 p"],
    d: Float[Array, "3 p"],
    depth: int,
    toggles: tuple[Int[Array, " p"], Int[Array, " p"]] | None = None,
    footprint: "edges.Footprint | None" = None,
) -> Float[Array, "3 p"]:
    """Colour seen along each ray (unclamped), following the chain for `depth` more segments.

    The segments after the first are one `lax.scan` body (compiled once, whatever the
    depth) in which a segment runs only if some ray is still alive (a `lax.cond`, which
    skips the work at run time and differentiates in both modes): on most tiles of
    most scenes the chain ends after one or two segments.
    `toggles` = (exclude, force), per ray a sphere index or −1, alter the first
    segment for the silhouette mode (see `spheres.Hit`); `footprint` (the primary
    rays' change per pixel) softens the first segment's shadow edges (`edges`).
    """
    m = prepare(s, p)
    state = (
        o,
        d,
        jnp.full(o.shape[1:], -1, jnp.int32),
        jnp.ones(o.shape[1:], o.dtype),
        jnp.zeros_like(o),
    )
    state = _segment(s, p, m, state, toggles, footprint)
    if depth == 0 or not s.needs_secondary_rays:
        return state[4]

    def further(st, _):
        st = jax.lax.cond(jnp.any(st[3] > 0), lambda x: _segment(s, p, m, x), lambda x: x, st)
        return st, None

    # One compiled segment, run `depth` times (compile time does not grow with depth).
    state, _ = jax.lax.scan(further, state, length=depth)
    return state[4]


def trace_tiled(s: Structure, p: Params, o, d, depth: int, tile: int, toggles=None, footprint=None) -> Float[Array, "3 p"]:
    """`trace` over tiles of `tile` rays, one after another (`lax.map`).

    Tiles keep each segment's arrays small (cache-resident on a CPU) and let a tile
    whose rays have all ended skip the rest of its chain. Neighbouring pixels tend
    to end together (a patch of background, an opaque sphere), so image-order tiles work.
    """
    n = o.shape[1]
    if n <= tile:
        return trace(s, p, o, d, depth, toggles, footprint)
    count = -(-n // tile)
    pad = count * tile - n

    def split(a):  # (..., P) → (count, ..., tile), padding with copies of the last ray
        a = jnp.concatenate([a, jnp.repeat(a[..., -1:], pad, axis=-1)], axis=-1) if pad else a
        return jnp.moveaxis(a.reshape(a.shape[:-1] + (count, tile)), -2, 0)

    args = (
        split(o),
        split(d),
        None if toggles is None else tuple(split(t) for t in toggles),
        None if footprint is None else (split(footprint.dx), split(footprint.dy)),
    )

    def one(a):
        fp = None if a[3] is None else edges.Footprint(a[3][0], a[3][1], footprint.width)
        return trace(s, p, a[0], a[1], depth, a[2], fp)

    out = jax.lax.map(one, args)
    return jnp.moveaxis(out, 0, -2).reshape(3, count * tile)[:, :n]
