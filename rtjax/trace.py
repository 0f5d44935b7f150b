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

from . import spheres
from .numerics import dot, normalize, safe_sqrt
from .scene import GLASS, MIRROR, OPAQUE, TEXTURE, Params, Structure
from .shading import local_light, phong_angles
from .textures import texture_colour


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
        tex_of = jnp.asarray(s.texture_index())[idx]
        for k, texels in enumerate(p.textures):
            d = jnp.where(tex_of == k, texture_colour(texels, normal_out), d)
    return d


def shade_hit(s: Structure, p: Params, m: Material, hit: spheres.Hit, n, v) -> Float[Array, "3 p"]:
    """Local light at each hit: Σ over lights of ambient, diffuse and specular with shadows."""
    total = jnp.zeros_like(n)
    if s.n_lights == 0:
        return total
    idx = jnp.maximum(hit.index, 0)
    d = surface_colour(s, p, m, idx, hit.normal_out)
    ks, beta = m.ks[idx], m.beta[idx]
    for light, colour in zip(m.lights, p.light_colors):
        ray = jnp.broadcast_to(light[:, None], n.shape)
        vis = spheres.transmission(hit.point, ray, p.centers, p.radii, hit.index, m.tmin, m.shadow_factor)
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


def trace(
    s: Structure,
    p: Params,
    o: Float[Array, "3 p"],
    d: Float[Array, "3 p"],
    depth: int,
    first_hit: spheres.Hit | None = None,
) -> Float[Array, "3 p"]:
    """Colour seen along each ray (unclamped), following the chain for `depth` more segments.

    `first_hit` replaces the first intersection pass (the silhouette mode uses it to
    toggle one sphere in or out of a pixel's view).
    """
    m = prepare(s, p)
    continues = jnp.asarray(s.mask(MIRROR, GLASS))
    glass = jnp.asarray(s.mask(GLASS))
    origin: Int[Array, " p"] = jnp.full(o.shape[1:], -1, jnp.int32)
    weight = jnp.ones(o.shape[1:], o.dtype)
    colour = jnp.zeros_like(o)
    for level in range(depth + 1):
        if level == 0 and first_hit is not None:
            hit = first_hit
        else:
            hit = spheres.Hit(o, d, p.centers, p.radii, origin, m.tmin)
        entering = dot(hit.normal_out, d) < 0
        n = jnp.where(entering, hit.normal_out, -hit.normal_out)
        local = shade_hit(s, p, m, hit, n, -d)
        seen = jnp.where(hit.found, local, p.background[:, None])
        colour = colour + weight * seen
        if level == depth or not s.needs_secondary_rays:
            break
        idx = jnp.maximum(hit.index, 0)
        alive = hit.found & continues[idx]
        weight = jnp.where(alive, weight * jnp.where(glass[idx], p.kt[idx], 1), 0)
        d = normalize(next_direction(s, p, idx, d, n, entering))
        o = hit.point
        origin = hit.index
        # One level's results are materialised before the next starts: without this
        # barrier XLA fuses across levels and recomputes shared work many times over.
        o, d, origin, weight, colour = jax.lax.optimization_barrier((o, d, origin, weight, colour))
    return colour
