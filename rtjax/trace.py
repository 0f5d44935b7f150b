"""The fixed-depth Whitted chain: what each hit adds and which one ray it spawns.

Each hit spawns at most one ray (mirror → reflected, glass → refracted, or internally
reflected past the critical angle), so a pixel's path is a chain of depth + 1 segments,
unrolled at trace time. What is compiled follows the `Structure`: no secondary rays
without mirrors or glass, no Snell's law without glass, no shadow rays without lights,
no texture lookups without textures.
"""

from __future__ import annotations

import functools

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
    grids: tuple = ()  # per light, its shadow-ray grid (large scenes, `spheres.light_grid`)


def prepare(s: Structure, p: Params) -> Material:
    opaque = jnp.asarray(s.mask(OPAQUE))
    glass = jnp.asarray(s.mask(GLASS))
    lights = normalize(p.light_dirs, axis=-1)
    tmin = spheres.tmin_for(spheres.scene_scale(p.centers, p.radii, p.eye))
    grids = tuple(spheres.light_grid(l, p.centers, p.radii, tmin) for l in lights) if spheres.culls(s.n_spheres) else ()
    return Material(
        diffuse=p.diffuse * opaque[:, None],
        ks=p.ks * ~jnp.asarray(s.mask(MIRROR)),
        beta=p.beta,
        shadow_factor=jnp.where(glass, p.kt**2, 0),
        lights=lights,
        tmin=tmin,
        grids=grids,
    )


def surface_colour(s: Structure, p: Params, m: Material, idx, normal_out) -> Float[Array, "3 p"]:
    """The diffuse colour d at each hit: the sphere's own, or its texture's texel."""
    d = m.diffuse.T[:, idx]
    if s.has(TEXTURE):
        d = textured_diffuse(p.textures, jnp.asarray(s.texture_index())[idx], normal_out, d)
    return d


def shade_hit(s: Structure, p: Params, m: Material, hit: spheres.Hit, n, v, soft=None, keyed: bool = False):
    """Local light at each hit: Σ over lights of ambient, diffuse and specular with shadows.

    `soft` = (∂P/∂x, ∂P/∂y, width, sided): box-filter the nearest shadow edge
    (silhouette mode). `sided`: shadows sharp at the centre, and also the nearest
    shadow edge over the lights as an `edges.Flip` (see `edges.soft_shadow`); then
    (colour, flip) is returned. `keyed` (hard shadows): (colour, each light's
    visibility) is returned, for the rays' `Rays.key`.
    """
    total = jnp.zeros_like(n)
    sided = soft is not None and soft[-1]
    flip = edges.Flip.none(n[0]) if sided else None
    visible = []
    if s.n_lights == 0:
        return (total, flip) if sided else (total, visible) if keyed else total
    idx = jnp.maximum(hit.index, 0)
    d = surface_colour(s, p, m, idx, hit.normal_out)
    ks, beta = m.ks[idx], m.beta[idx]
    for i, (light, colour) in enumerate(zip(m.lights, p.light_colors)):
        nl, cos_g = phong_angles(n, v, light)
        if soft is None:
            ray = jnp.broadcast_to(light[:, None], n.shape)
            vis = spheres.transmission(hit.point, ray, p.centers, p.radii, hit.index, m.tmin, m.shadow_factor,
                                       active=hit.live, grid=m.grids[i] if m.grids else None)
            visible.append(vis)
        elif sided:
            vis, there, x = edges.soft_shadow(hit, light, p.centers, p.radii, m.tmin, m.shadow_factor, *soft)
        else:
            vis = edges.soft_shadow(hit, light, p.centers, p.radii, m.tmin, m.shadow_factor, *soft)
        term = local_light(d, ks, beta, p.ke, nl, cos_g, vis, colour)
        if sided:
            flip = flip.nearer(edges.Flip(x, local_light(d, ks, beta, p.ke, nl, cos_g, there, colour) - term))
        total = total + term
    return (total, flip) if sided else (total, visible) if keyed else total


#: FNV-1a's 32-bit prime, which mixes each hit into a ray's `Rays.key`.
_FNV_PRIME = 16777619


def _mix(key, value):
    return (key ^ value.astype(jnp.uint32)) * jnp.uint32(_FNV_PRIME)


def hit_key(key, hit: spheres.Hit, visibility, live):
    """`key` with this hit folded in where `live`: the sphere met (or none) and each
    light's visibility (quantised: which occluders block it). Two samples whose chains
    have equal keys meet the same spheres in the same order under the same shadows, so
    no silhouette or shadow edge lies between them (up to hash collisions)."""
    new = _mix(key, hit.index + 1)
    for vis in visibility:
        new = _mix(new, jnp.round(jax.lax.stop_gradient(vis) * 2**20))
    return jnp.where(live, new, key)


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


class Rays(NamedTuple):
    """The chain's state: one ray per pixel, the colour gathered so far, its weight."""

    o: Float[Array, "3 p"]
    d: Float[Array, "3 p"]
    origin: Int[Array, " p"]  # sphere the ray leaves (−1: the eye)
    weight: Float[Array, " p"]  # product of kt so far; 0 once the chain has ended
    colour: Float[Array, "3 p"]
    level: Int[Array, " p"]  # this segment's index in the chain (0: primary)
    flip: "edges.Flip | None" = None  # the nearest shadow edge so far (sided mode only)
    key: "Int[Array, ' p'] | None" = None  # the chain's hits so far, hashed (`hit_key`; keyed traces only)


def start_rays(o, d, sided: bool = False, keyed: bool = False) -> Rays:
    p = o.shape[1:]
    flip = edges.Flip.none(o[0]) if sided else None
    key = jnp.full(p, 2166136261, jnp.uint32) if keyed else None  # FNV-1a's offset basis
    return Rays(o, d, jnp.full(p, -1, jnp.int32), jnp.ones(p, o.dtype), jnp.zeros_like(o), jnp.zeros(p, jnp.int32), flip,
                key)


def segment(
    s: Structure,
    p: Params,
    m: Material,
    rays: Rays,
    depth: int,
    toggles=None,
    diff: "edges.Differentials | None" = None,
    width: float = 0.0,
    sided: bool = False,
):
    """One segment of the chain for every ray: hit, local light, the next ray.

    With `diff` (the rays' change per sample step) the nearest shadow edge of each hit
    is box-filtered over `width` steps and the differentials follow the rays; `toggles`
    (exclude, force) alter this segment's hit (silhouette mode, `spheres.Hit`);
    `sided`: shadows sharp at the centre instead, and the rays' `flip` (where they
    carry one) keeps the nearest shadow edge (`edges.soft_shadow`).
    Returns the next rays, their differentials (or None) and this segment's hit.
    """
    o, d = rays.o, rays.d
    hit = spheres.Hit(o, d, p.centers, p.radii, rays.origin, m.tmin, *(toggles or (None, None)), active=rays.weight > 0)
    entering = hit.entering
    n = jnp.where(entering, hit.normal_out, -hit.normal_out)
    moves = None if diff is None else edges.hit_motion(hit, o, d, diff)
    soft = None if moves is None else (moves[0], moves[1], width, sided)
    keyed = rays.key is not None
    local = shade_hit(s, p, m, hit, n, -d, soft, keyed=keyed)
    key = rays.key
    if keyed:
        local, visible = local
        key = hit_key(key, hit, visible, rays.weight > 0)
    flip = rays.flip
    if soft is not None and sided:
        local, shadow = local
        if flip is not None:  # this hit's nearest shadow edge, weighted like the colour it would change
            seen = hit.found & (rays.weight > 0)
            flip = flip.nearer(edges.Flip(jnp.where(seen, shadow.x, jnp.inf), rays.weight * shadow.delta))
    colour = rays.colour + rays.weight * jnp.where(hit.found, local, p.background[:, None])
    if not s.needs_secondary_rays:
        return rays._replace(weight=jnp.zeros_like(rays.weight), colour=colour, flip=flip, key=key), None, hit
    idx = jnp.maximum(hit.index, 0)
    alive = hit.found & jnp.asarray(s.mask(MIRROR, GLASS))[idx] & (rays.level < depth)
    glass = jnp.asarray(s.mask(GLASS))[idx]
    weight = jnp.where(alive, rays.weight * jnp.where(glass, p.kt[idx], 1), 0)

    def turn(d, n):
        return normalize(next_direction(s, p, idx, d, n, entering))

    new_d = turn(d, n)
    new_diff = None
    if diff is not None:
        # differentials of the next ray: ∂o' = ∂P, ∂d' through the reflection/refraction
        # with ∂N = ±∂P/r (the facing normal of a sphere moves with the hit point). They
        # scale edge distances (δ = (|l| − r)/rate), whose derivative at an edge, where
        # |l| = r, does not depend on the rate: so they carry no derivative themselves.
        sg = jax.lax.stop_gradient
        sign = jnp.where(entering, 1, -1).astype(o.dtype) / sg(p.radii)[idx]
        outs = [jax.jvp(turn, (sg(d), sg(n)), (dd, sign * dp))[1] for dd, dp in ((diff.dx, moves[0]), (diff.dy, moves[1]))]
        new_diff = edges.Differentials(*sg((moves[0], outs[0], moves[1], outs[1])))
    nxt = Rays(hit.point, new_d, hit.index, weight, colour, rays.level + 1, flip, key)
    return nxt, new_diff, hit


#: Rays per tier of the chain: after each tier, the rays still alive are packed into the
#: next, smaller one (see `_chain`). A tier is worth its extra compiled copy of the
#: segment only on large ray counts: a fit's coarse levels (a few thousand rays) use
#: one; its full-size level (up to a quarter of the image) two: on the sample deck's
#: example fit, 0.5 s a step instead of 1.1 s, for 3 s more compiling.
TIER_DIVISOR = 8
TIER_MIN = 512


def tiers(n: int) -> tuple[int, ...]:
    """Buffer sizes of the chain's tiers for `n` rays: `n`, then `n`/8 when that is at
    least `TIER_MIN` (static). On the sample deck 42 % of the rays go on after the
    first segment, 28 % after the second and 3.5 % after the third."""
    small = n // TIER_DIVISOR
    return (n, small) if small >= TIER_MIN else (n,)


def _gather(tree, sel):
    return jax.tree_util.tree_map(lambda a: a[..., sel], tree)


def _chain(s, p, m, rays, depth, diff=None, width=0.0, toggles=None, watch=None, sided=False):
    """Segments until `rays.level` passes `depth`: one `lax.scan` body (compiled once,
    whatever the depth), each segment skipped at run time by a `lax.cond` once no ray is
    alive (both modes of differentiation go through `lax.cond`). `toggles` alter the
    first segment only.

    Wavefront compaction: most rays end after a segment or two, but a scan over all of
    them pays for every ray at every segment. So the chain runs in `tiers`: a tier's
    segments run while more rays are alive than the next tier holds; then the live ones
    (their state, differentials, toggles and watch) are packed into the next tier's
    buffer, in order, traced on there and scattered back. Each ray meets the same
    arithmetic either way; the image is the same.

    `watch(rays, diff, hit, best)` → best is folded over the segments (silhouette mode)."""
    if not s.needs_secondary_rays:
        rays2, _, hit = segment(s, p, m, rays, depth, toggles, diff, width, sided)
        return rays2, None if watch is None else watch(rays, diff, hit, watch.empty(rays, diff))
    if toggles is None:
        toggles = (jnp.full(rays.weight.shape, -1, jnp.int32),) * 2
    best = None if watch is None else watch.empty(rays, diff)
    sizes = tiers(rays.weight.shape[0])

    def body(carry, _, nxt):
        def run(c):
            r, df, tg, b = c
            r2, df2, h = segment(s, p, m, r, depth, tg, df, width, sided)
            off = jnp.full_like(tg[0], -1)
            return r2, df2, (off, off), (b if watch is None else watch(r, df, h, b))

        return jax.lax.cond(jnp.sum(carry[0].weight > 0) > nxt, run, lambda c: c, carry), None

    def tier(state, i):
        nxt = sizes[i + 1] if i + 1 < len(sizes) else 0
        state, _ = jax.lax.scan(functools.partial(body, nxt=nxt), state, length=depth + 1)
        if not nxt:
            return state
        # at most `nxt` rays are alive now (or none: every ray ended within the depth)
        live = state[0].weight > 0
        (sel,) = jnp.nonzero(live, size=nxt, fill_value=0)
        valid = jnp.arange(nxt) < jnp.sum(live)
        packed = _gather(state, sel)
        packed = (packed[0]._replace(weight=jnp.where(valid, packed[0].weight, 0)),) + packed[1:]
        done = tier(packed, i + 1)
        to = jnp.where(valid, sel, live.shape[0])  # padding goes nowhere
        return jax.tree_util.tree_map(lambda a, b: a.at[..., to].set(b, mode="drop"), state, done)

    rays, _, _, best = tier((rays, diff, toggles, best), 0)
    return rays, best


def trace(s: Structure, p: Params, o: Float[Array, "3 p"], d: Float[Array, "3 p"], depth: int, keyed: bool = False):
    """Colour seen along each ray (unclamped), following the chain for `depth` more segments.

    On most scenes most rays end after one or two segments, and a segment whose rays
    have all ended is skipped at run time. `keyed`: (colour, key), each ray's chain of
    hits and shadows hashed (`hit_key`), for the silhouette mode's choice of pixels.
    """
    rays, _ = _chain(s, p, prepare(s, p), start_rays(o, d, keyed=keyed), depth)
    return (rays.colour, rays.key) if keyed else rays.colour


def edge_capacity(n: int) -> int:
    """How many pixels pass 2 of the silhouette mode traces: edge pixels are a few per
    cent of a 400-pixel-wide image and grow like its perimeter, so a quarter of the
    pixels (at least 4096) covers them; beyond, the surplus keeps its plain colour."""
    return min(n, max(4096, n // 4))


def trace_edges(s: Structure, p: Params, o, d, diff: "edges.Differentials", depth: int, width: float,
                parts: bool = False, capacity: int | None = None) -> Float[Array, "3 p"] | Float[Array, "14 p"]:
    """The silhouette-aware colour of each pixel, clamped.

    Pass 1 traces the chain with ray differentials and soft shadow edges, and finds the
    one silhouette edge nearest to its ray (in pixels) over all segments: primary,
    reflected or refracted. Pass 2 traces, for the pixels that have one (gathered, up to
    `edge_capacity`), both sides of that edge from its segment on, through the
    centroids of their parts of the pixel (the edge sphere removed on one side, met on
    the other), and blends them by the box-filtered coverage (see `rtjax.edges`): its
    cost follows the edges' length, not the image's area.

    `parts`: instead, (14, P): the colour at the pixel's centre (shadows sharp); the
    colours traced just inside and just outside the silhouette where it passes nearest
    to the centre (both the centre's colour where a pixel has none); the centre's
    signed distance to it in box widths, positive on the sphere's side (0 where none);
    the centre's colour had it lain on the other side of its nearest shadow edge over
    the chain (the centre's colour where none), and its distance to that edge in box
    widths (inf where none).

    `capacity`: how many pixels pass 2 takes (default `edge_capacity`).
    """
    m = prepare(s, p)
    watch = edges.EdgeWatch(p.centers, p.radii, m.tmin, width)
    rays, best = _chain(s, p, m, start_rays(o, d, sided=parts), depth, diff, width, watch=watch, sided=parts)
    plain = jnp.clip(rays.colour, 0, 255)
    n = o.shape[1]
    cap = edge_capacity(n) if capacity is None else min(n, capacity)
    has = best.edge >= 0
    (sel,) = jnp.nonzero(has, size=cap, fill_value=0)
    valid = jnp.arange(cap) < jnp.sum(has)
    b = jax.tree_util.tree_map(lambda a: a[..., sel], best)
    side = edges.both_sides(b, p.centers, p.radii, width, at_edge=parts)
    r0 = b.rays

    def two(a, b=None):
        return jnp.concatenate([a, a if b is None else b], axis=-1)

    start = Rays(two(side.o_in, side.o_out), two(side.d_in, side.d_out), two(r0.origin),
                 two(jnp.where(valid, r0.weight, 0)), two(r0.colour), two(r0.level))
    none = jnp.full((cap,), -1, jnp.int32)
    twice = edges.Differentials(*(two(a) for a in b.diff))
    out, _ = _chain(s, p, m, start, depth, twice, width, (two(none, side.edge), two(side.edge, none)), sided=parts)
    inside, outside = jnp.split(jnp.clip(out.colour, 0, 255), 2, axis=-1)
    # padding slots (index 0 repeated) write nowhere: pixel 0 may itself be an edge pixel
    to = jnp.where(valid, sel, n)
    if not parts:
        return plain.at[:, to].set(side.alpha * inside + (1 - side.alpha) * outside, mode="drop")
    rows = jnp.concatenate([plain, plain, plain, jnp.zeros_like(plain[:1])])
    rows = rows.at[3:, to].set(jnp.concatenate([inside, outside, side.x[None]]), mode="drop")
    return jnp.concatenate([rows, jnp.clip(rays.colour + rays.flip.delta, 0, 255), rays.flip.x[None]])


def tiled(fn, tile: int, *arrays, count=None):
    """fn(*arrays) → a pytree of (..., P) arrays, run over tiles of `tile` rays one after
    another (`lax.map`) when P > tile: bounds memory on large images (the image does not
    depend on it). `count` (traced): only the first `count` rays are wanted; tiles
    wholly past them are skipped at run time (their outputs are zeros), and the others
    are checkpointed (reverse mode recomputes a tile instead of storing its
    intermediates: stored per tile they cost more than the recomputation)."""
    n = arrays[0].shape[-1]
    if n <= tile:
        return fn(*arrays)
    m = -(-n // tile)
    pad = m * tile - n

    def split(a):  # (..., P) → (m, ..., tile), padding with copies of the last ray
        a = jnp.concatenate([a, jnp.repeat(a[..., -1:], pad, axis=-1)], axis=-1) if pad else a
        return jnp.moveaxis(a.reshape(a.shape[:-1] + (m, tile)), -2, 0)

    def join(a):  # (m, ..., tile) → (..., P)
        return jnp.moveaxis(a, 0, -2).reshape(a.shape[1:-1] + (m * tile,))[..., :n]

    parts = jax.tree_util.tree_map(split, arrays)
    if count is None:
        out = jax.lax.map(lambda a: fn(*a), parts)
    else:
        shapes = jax.eval_shape(fn, *(a[0] for a in parts))

        def one(ia):
            i, a = ia
            return jax.lax.cond(i * tile < count, jax.checkpoint(lambda a: fn(*a)),
                                lambda a: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), a)

        out = jax.lax.map(one, (jnp.arange(m), parts))
    return jax.tree_util.tree_map(join, out)
