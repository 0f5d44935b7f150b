"""The fixed-depth Whitted chain: what each hit adds and which one ray it spawns.

Each hit spawns at most one ray (mirror → reflected, glass → refracted, or internally
reflected past the critical angle), so a pixel's path is a chain of depth + 1 segments,
unrolled at trace time. What is compiled follows the `Structure`: no secondary rays
without mirrors or glass, no Snell's law without glass, no shadow rays without lights,
no texture lookups without textures.

A chain is traced in one of three modes (static):

* `PLAIN`: pixel centres, hard shadows (`trace`);
* `BOX`: the silhouette-aware mode, shadow edges box-filtered over each hit's
  footprint and silhouettes blended (`trace_edges`, `rtjax.edges`);
* `SIDED`: the same chain at the pixel's centre with shadows sharp, and both sides of
  its nearest silhouette and shadow edge (`trace_edges`): what a target sampled at
  pixel centres needs.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt

from . import edges, occlusion, spheres
from .compact import pack
from .numerics import clamp_colour, dot, lookup, normalize, safe_sqrt, spread, take_rows
from .scene import GLASS, MIRROR, OPAQUE, TEXTURE, Params, Structure
from .shading import fresnel_reflectance, local_light, phong_angles
from .textures import textured_diffuse

PLAIN, BOX, SIDED = "plain", "box", "sided"
Mode = Literal["plain", "box", "sided"]


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
    """The per-sphere arrays of `p` in the chain's form."""
    opaque = jnp.asarray(s.mask(OPAQUE))
    glass = jnp.asarray(s.mask(GLASS))
    lights = normalize(p.light_dirs, axis=-1)
    tmin = spheres.tmin_for(spheres.scene_scale(p.centers, p.radii, p.eye))
    grids = tuple(spheres.light_grid(l, p.centers, p.radii, tmin) for l in lights) if s.culls else ()
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
    d = take_rows(m.diffuse, idx)
    if s.has(TEXTURE):
        d = textured_diffuse(p.textures, jnp.asarray(s.texture_index())[idx], normal_out, d)
    return d


class Shade(NamedTuple):
    """Local light at each hit (`shade_hit`)."""

    colour: Float[Array, "3 p"]
    visibility: tuple[Float[Array, " p"], ...]  # per light: hard, or box-filtered in box mode
    flip: "edges.Flip | None"  # sided mode: the nearest shadow edge over the lights
    near: "Bool[Array, ' p'] | None"  # box and sided modes: some light's shadow edge or terminator may cross the hit's box, or its highlight is narrow there


def primary_sky(p: Params, hit: spheres.Hit, primary: Bool[Array, " p"]) -> Float[Array, " p"]:
    """The share of the sky each hit seen directly (`primary`) sees (`rtjax.occlusion`,
    weights `p.occlusion`), 1 at the rest: contact shadows are modelled where they are
    seen, not in mirrors or through glass. Computed only in a segment with such hits
    (`lax.cond`), so the chain's later segments skip its N·P form factors at run time."""

    def seen():
        sky = occlusion.sky_visibility(hit.point, hit.normal_out, hit.index, p.centers, p.radii, p.occlusion)
        return jnp.where(primary, sky, 1)

    return jax.lax.cond(jnp.any(primary & hit.live), seen, lambda: jnp.ones_like(hit.t))


def shade_hit(s: Structure, p: Params, m: Material, hit: spheres.Hit, n, v, mode: Mode,
              motion: edges.Motion | None = None, width=0.0, primary: Bool[Array, " p"] | None = None) -> Shade:
    """Local light at each hit: Σ over lights of ambient, diffuse and specular with shadows.

    n: the unit normal facing the ray; v: toward where the ray came from. In box and
    sided modes, `motion` (the hit point's motion per sample step) and `width` (the box
    in sample steps) place each light's nearest shadow edge (`edges.soft_shadow`).
    `primary`: the hits seen directly, where sky occlusion applies (`primary_sky`).
    """
    total = jnp.zeros_like(n)
    flip = edges.Flip.none(n[0]) if mode == SIDED else None
    near = None if mode == PLAIN else jnp.zeros(n.shape[1:], bool)
    if s.n_lights == 0:
        return Shade(total, (), flip, near)
    idx = jnp.maximum(hit.index, 0)
    d = surface_colour(s, p, m, idx, hit.normal_out)
    ks, beta = lookup(m.ks, idx), lookup(m.beta, idx)
    sky = None if p.occlusion is None else primary_sky(p, hit, hit.live if primary is None else primary)
    if mode != PLAIN:
        radius, speed = lookup(p.radii, idx), edges.hit_speed(motion)
    visible = []
    for i, (light, colour) in enumerate(zip(m.lights, p.light_colors)):
        nl, cos_g = phong_angles(n, v, light)
        if mode == PLAIN:
            ray = jnp.broadcast_to(light[:, None], n.shape)
            vis = spheres.transmission(hit.point, ray, p.centers, p.radii, hit.index, m.tmin, m.shadow_factor,
                                       active=hit.live, grid=m.grids[i] if m.grids else None)
        else:
            shadow = edges.soft_shadow(hit, light, p.centers, p.radii, m.tmin, m.shadow_factor, motion, width,
                                       sided=mode == SIDED)
            vis, near = shadow.here, (near | shadow.near | edges.near_terminator(nl, light, motion, radius, width)
                                      | edges.near_highlight(cos_g, ks, beta, speed, radius, width))
        term = local_light(d, ks, beta, p.ke, nl, cos_g, vis, colour, sky)
        if mode == SIDED:
            flip = flip.nearer(edges.Flip(shadow.x, local_light(d, ks, beta, p.ke, nl, cos_g, shadow.there, colour, sky) - term))
        total = total + term
        visible.append(vis)
    return Shade(total, tuple(visible), flip, near)


#: FNV-1a's 32-bit prime, which mixes each hit into a ray's `Rays.key`, and its offset basis.
_FNV_PRIME = 16777619
_FNV_BASIS = 2166136261


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


#: Floor of √k's slope in Snell's law (k = 0: the critical angle), per dtype.
TIR_SLOPE_FLOOR = {jnp.dtype(jnp.float32): 1e-8, jnp.dtype(jnp.float64): 1e-16}
#: |k| below which Snell's k counts as 0 (exactly at the critical angle), per dtype: above
#: k's rounding at the silhouette mode's grazing hits, far below any k a ray not grazing
#: its way in meets. Narrow, since it moves the boundary of total internal reflection by
#: the band over k's rate, which 16 × 16 sub-boxes resolve (docs/MEASUREMENTS.md, stop 66).
CRITICAL_BAND = {jnp.dtype(jnp.float32): 1e-5, jnp.dtype(jnp.float64): 1e-10}


def next_direction(s: Structure, p: Params, idx, d, n, entering):
    """Mirror reflection, or for glass Snell's refraction (TIR: the reflection).

    A ray that enters a sphere leaves it at the angle it entered by, so k on the way
    out is cos² of the entry angle: exactly 0 for the silhouette mode's grazing hits
    (`spheres.nearest_hit`'s `force`), where rounding alone would choose between
    refraction and TIR, differently in each compiled program (the image, its jvp, its
    vjp), and √k's slope would amplify the rounding. Within `CRITICAL_BAND` of 0, k is
    taken as 0: the ray refracts, tangent to the surface, and k carries no derivative
    (it is identically 0 along a grazing hit)."""
    cos_i = -dot(d, n)
    reflected = d + spread(2 * cos_i) * n
    if not s.has(GLASS):
        return reflected
    ior = lookup(p.ior, idx)
    eta = jnp.where(entering, 1 / ior, ior)
    k = 1 - eta**2 * (1 - cos_i**2)
    band = CRITICAL_BAND[jnp.dtype(d.dtype)]
    root = safe_sqrt(jnp.where(k > band, k, 0), jnp.asarray(TIR_SLOPE_FLOOR[jnp.dtype(d.dtype)], d.dtype))
    refracted = spread(eta) * d + spread(eta * cos_i - root) * n
    glass = jnp.asarray(s.mask(GLASS))[idx]
    return jnp.where(glass & (k > -band), refracted, reflected)


#: The dtype of `Rays.level`: reverse mode keeps it per ray and segment, so it is narrow
#: (depths up to 32767).
LEVEL = jnp.int16


class Rays(NamedTuple):
    """The chain's state: one ray per pixel, the colour gathered so far, its weight."""

    o: Float[Array, "3 p"]
    d: Float[Array, "3 p"]
    origin: Int[Array, " p"]  # sphere the ray leaves (−1: the eye)
    weight: Float[Array, " p"]  # product of kt so far; 0 once the chain has ended
    colour: Float[Array, "3 p"]
    level: Int[Array, " p"]  # this segment's index in the chain (0: primary), `LEVEL`
    flip: "edges.Flip | None" = None  # sided mode: the nearest shadow edge so far
    key: "UInt[Array, ' p'] | None" = None  # keyed traces: the chain's hits so far, hashed (`hit_key`)
    diff: "edges.Differentials | None" = None  # box and sided modes: the rays' change per sample step


def start_rays(o, d, mode: Mode, diff: edges.Differentials | None = None, keyed: bool = False) -> Rays:
    """Primary rays (from the eye) with the state `mode` carries; `keyed`: a hash of each
    chain's hits too."""
    p = o.shape[1:]
    flip = edges.Flip.none(o[0]) if mode == SIDED else None
    key = jnp.full(p, _FNV_BASIS, jnp.uint32) if keyed else None
    return Rays(o, d, jnp.full(p, -1, jnp.int32), jnp.ones(p, o.dtype), jnp.zeros_like(o), jnp.zeros(p, LEVEL), flip,
                key, diff)


def segment(s: Structure, p: Params, m: Material, rays: Rays, depth: int, mode: Mode, width=0.0,
            toggles: spheres.Toggles | None = None) -> tuple[Rays, spheres.Hit, Shade]:
    """One segment of the chain for every ray: hit, local light, the next ray.

    In box and sided modes the rays carry their differentials, which follow them
    through reflections and refractions and place each hit's nearest shadow edge
    (`width` sample steps wide); `toggles` alter this segment's hits (the silhouette
    mode's second pass). Returns the next rays, this segment's hit and its local light.
    """
    o, d = rays.o, rays.d
    active = rays.weight > 0
    hit = spheres.nearest_hit(o, d, p.centers, p.radii, rays.origin, m.tmin, s.culls,
                              None if toggles is None else toggles.at(rays.level), active)
    entering = hit.entering
    n = jnp.where(entering, hit.normal_out, -hit.normal_out)
    motion = None if rays.diff is None else edges.hit_motion(hit, d, rays.diff)
    shade = shade_hit(s, p, m, hit, n, -d, mode, motion, width, rays.level == 0)
    key = rays.key if rays.key is None else hit_key(rays.key, hit, shade.visibility, active)
    flip = rays.flip
    if flip is not None:  # this hit's nearest shadow edge, weighted like the colour it would change
        seen = hit.found & active
        flip = flip.nearer(edges.Flip(jnp.where(seen, shade.flip.x, jnp.inf), rays.weight * shade.flip.delta))
    colour = rays.colour + spread(rays.weight) * jnp.where(hit.found, shade.colour, p.background[:, None])
    if not s.needs_secondary_rays:
        return rays._replace(weight=jnp.zeros_like(rays.weight), colour=colour, flip=flip, key=key), hit, shade
    idx = jnp.maximum(hit.index, 0)
    alive = hit.found & jnp.asarray(s.mask(MIRROR, GLASS))[idx] & (rays.level < depth)
    glass = jnp.asarray(s.mask(GLASS))[idx]
    passes = jnp.where(glass, lookup(p.kt, idx), 1)
    if p.fresnel is not None and s.has(GLASS):  # glass seen from outside reflects p.fresnel, passes the rest
        reflects = jnp.where(glass & entering & hit.found & active, fresnel_reflectance(lookup(p.ior, idx), dot(n, -d)), 0)
        colour = colour + spread(rays.weight * reflects) * p.fresnel[:, None]
        passes = passes * (1 - reflects)
    weight = jnp.where(alive, rays.weight * passes, 0)

    def turn(d, n):
        return normalize(next_direction(s, p, idx, d, n, entering))

    new_d = turn(d, n)
    new_diff = None
    if rays.diff is not None:
        # differentials of the next ray: ∂o' = ∂P, ∂d' through the reflection/refraction
        # with ∂N = ±∂P/r (the facing normal of a sphere moves with the hit point). They
        # carry the scene's derivatives: an edge's distance δ = gap/rate from a pixel's
        # centre moves with the rate wherever δ ≠ 0, as in a mirror or glass sphere that
        # moves (the world it shows stretches), and the box filter reads δ across the box.
        sign = jnp.where(entering, 1, -1).astype(o.dtype) / p.radii[idx]
        outs = [jax.jvp(turn, (d, n), (dd, sign * dp))[1] for dd, dp in ((rays.diff.dx, motion.x),
                                                                          (rays.diff.dy, motion.y))]
        new_diff = edges.Differentials(motion.x, outs[0], motion.y, outs[1])
    return Rays(hit.point, new_d, hit.index, weight, colour, rays.level + 1, flip, key, new_diff), hit, shade


#: Rays per tier of the chain: after each tier, the rays still alive are packed into the
#: next, smaller one (see `_chain`); a tier is worth its extra compiled copy of the
#: segment only on large ray counts.
TIER_DIVISOR = 8
TIER_MIN = 512


def tiers(n: int) -> tuple[int, ...]:
    """Buffer sizes of the chain's tiers for `n` rays: `n`, then `n`/`TIER_DIVISOR` when
    that is at least `TIER_MIN` (static)."""
    small = n // TIER_DIVISOR
    return (n, small) if small >= TIER_MIN else (n,)


#: What reverse mode keeps of a segment besides its input: the discrete choices it made
#: (`spheres.CHOICE`: spheres met, shadow rays blocked, edges chosen), so that the
#: recomputation does not test every ray against every sphere again.
KEEP = jax.checkpoint_policies.save_only_these_names(spheres.CHOICE)


def _chain(s: Structure, p: Params, m: Material, rays: Rays, depth: int, mode: Mode, width=0.0,
           toggles: spheres.Toggles | None = None, watch: edges.EdgeWatch | None = None):
    """Segments until `rays.level` passes `depth`: one `lax.scan` body (compiled once,
    whatever the depth), each segment skipped at run time by a `lax.cond` once no ray is
    alive (both modes of differentiation go through `lax.cond`). `toggles` alter the
    first segment only; `watch` (the silhouette mode's `edges.EdgeWatch`) is folded over
    the segments. Returns the rays after the last segment and the fold (None without).

    Each segment that runs is checkpointed: reverse mode keeps only the state entering
    it (not the colour gathered so far, nor toggles when there are none; the level is
    narrow) and recomputes the segment's intermediates from it, so the gradient's memory
    hardly grows with the depth (forward mode and the image are unaffected). The
    checkpoint sits inside the `lax.cond`: a skipped segment fills no residuals but the
    state it would have kept (a checkpoint around the `lax.cond` made reverse mode fill
    zeros for every intermediate of every skipped segment). The recomputation
    is another compiled program than the forward pass, so its rounding differs: the
    choices rounding alone used to settle (at the silhouette mode's grazing hits:
    `next_direction`, `spheres.roots`, `edges.hit_motion`) are made on quantities
    rounding does not flip, so both passes follow the same paths.

    Wavefront compaction: most rays end after a segment or two, but a scan over all of
    them pays for every ray at every segment. So the chain runs in `tiers`: a tier's
    segments run while more rays are alive than the next tier holds; then the live ones
    (their state, toggles and fold) are packed into the next tier's buffer, in order,
    traced on there and scattered back (`compact.pack`). Each ray meets the same
    arithmetic either way; the image is the same."""
    if not s.needs_secondary_rays:
        rays2, hit, shade = segment(s, p, m, rays, depth, mode, width, toggles)
        return rays2, None if watch is None else watch(rays, hit, watch.empty(rays), shade.near)
    best = None if watch is None else watch.empty(rays)
    sizes = tiers(rays.weight.shape[0])

    def run(c):
        r, tg, b = c
        if watch is None:  # the colour gathered so far stays outside (`gather`)
            r = r._replace(colour=jnp.zeros_like(r.o))
        r2, h, shade = segment(s, p, m, r, depth, mode, width, tg)
        tg = tg if tg is None or tg.level is not None else spheres.Toggles.off(tg.exclude)  # None: none carried
        return r2, tg, (b if watch is None else watch(r, h, b, shade.near))

    segment_kept = jax.checkpoint(run, prevent_cse=False, policy=KEEP)

    def gather(c):
        """One segment; without a fold, the colour gathered so far is added after the
        checkpoint (0 + x is x exactly), so reverse mode need not keep it per segment."""
        if watch is not None:
            return segment_kept(c)
        r, tg, b = c
        r2, tg2, b2 = segment_kept((r._replace(colour=None), tg, b))
        return r2._replace(colour=r.colour + r2.colour), tg2, b2

    def body(carry, _, nxt):
        return jax.lax.cond(jnp.sum(carry[0].weight > 0) > nxt, gather, lambda c: c, carry), None

    def tier(state, i):
        nxt = sizes[i + 1] if i + 1 < len(sizes) else 0
        state, _ = jax.lax.scan(functools.partial(body, nxt=nxt), state, length=depth + 1)
        if not nxt:
            return state
        # at most `nxt` rays are alive now (or none: every ray ended within the depth)
        packed = pack(state[0].weight > 0, nxt)
        sub = packed.gather(state)
        sub = (sub[0]._replace(weight=jnp.where(packed.valid, sub[0].weight, 0)),) + sub[1:]
        return packed.scatter(state, tier(sub, i + 1))

    rays, _, best = tier((rays, toggles, best), 0)
    return rays, best


class Traced(NamedTuple):
    """What a plain trace gives per ray (`trace`)."""

    colour: Float[Array, "3 p"]  # unclamped
    key: "UInt[Array, ' p'] | None"  # keyed traces: the chain's hits and shadows hashed (`hit_key`)


def trace(s: Structure, p: Params, o: Float[Array, "3 p"], d: Float[Array, "3 p"], depth: int,
          keyed: bool = False) -> Traced:
    """Colour seen along each ray, following the chain for `depth` more segments.

    On most scenes most rays end after one or two segments, and a segment whose rays
    have all ended is skipped at run time. `keyed`: each ray's chain of hits and shadows
    hashed too, for the silhouette mode's choice of pixels (`edges.edge_pixels`).
    """
    rays, _ = _chain(s, p, prepare(s, p), start_rays(o, d, PLAIN, keyed=keyed), depth, PLAIN)
    return Traced(rays.colour, rays.key)


#: Pass 2 of the silhouette mode takes a quarter of its rays' pixels (at least
#: `EDGE_CAPACITY_MIN`): edge pixels are a few per cent of an image and grow like its
#: perimeter.
EDGE_CAPACITY_SHARE = 4
EDGE_CAPACITY_MIN = 4096


#: Where pass 2 has room for every ray (`edge_capacity`'s minimum: small images, and
#: the sub-boxes' rounds), it traces the sides of its edges in this many tiles, those
#: past the last edge skipped at run time (`tiled`), so that its cost follows the edges
#: found; elsewhere its rays are pixels chosen near edges, mostly edges themselves, and
#: one chain (whose tiers pack the rays still alive) is the cheaper.
SIDE_TILES = 8


def edge_capacity(n: int) -> int:
    """How many of `n` pixels pass 2 of the silhouette mode traces; beyond, the surplus
    keeps its colour through the centre."""
    return min(n, max(EDGE_CAPACITY_MIN, n // EDGE_CAPACITY_SHARE))


def trace_edges(s: Structure, p: Params, o, d, diff: edges.Differentials, depth: int, width, mode: Mode,
                capacity: int | None = None, subdivide: int = 0) -> edges.EdgeSamples:
    """The silhouette-aware trace of each pixel (box or sided `mode`), colours clamped.

    Pass 1 traces the chain with ray differentials and shadow edges, and finds the one
    silhouette nearest to its ray (in pixels) over all segments: primary, reflected or
    refracted. Pass 2 traces, for the pixels that have one (packed, up to `capacity`,
    default `edge_capacity`), both sides of that edge from its segment on (the edge
    sphere met on one side, removed on the other): through the centroids of their parts
    of the pixel's box in box mode, whose blend (`EdgeSamples.blended`) is the pixel's
    box-filtered colour; just across the edge where it passes nearest to the centre in
    sided mode. Its cost follows the edges' length, not the image's area. Where pass 2
    has room for every ray (`capacity` left to `edge_capacity` on at most its minimum of
    rays: small images, sub-boxes), the sides run in `SIDE_TILES` tiles, those past the
    last edge skipped.

    Box mode, `subdivide` (static, halvings of the box; 0: none): the pixels whose box an
    edge may cross (`subdivided_pixels`) are traced again as k × k sub-boxes, k =
    2^`subdivide` (`_subdivided`; beyond 4 × 4 in two levels, `sub_box_levels`), each
    with its own nearest edge and sides; their blend is their mean. A pixel may hold
    several edges, and through a curved mirror or glass the world behind is far from
    linear across it: one straight edge per pixel misplaces their derivatives.
    """
    n = o.shape[1]
    default = edge_capacity(n)
    tiles = SIDE_TILES if capacity is None and default == n else 1  # room for every ray: pass 2 mostly empty
    capacity = default if capacity is None else min(n, capacity)
    if subdivide and mode == BOX:
        return _subdivided(s, p, (o, d, diff), depth, width, capacity, tiles, subdivide)
    return _edge_pass(s, p, (o, d, diff), depth, width, mode, capacity, tiles).samples


class EdgePass(NamedTuple):
    """What one silhouette-aware pass over a batch of rays gives (`_edge_pass`)."""

    samples: edges.EdgeSamples
    subdivided: "Bool[Array, ' p'] | None"  # box mode with `subdivided`: `subdivided_pixels`


def _edge_pass(s: Structure, p: Params, primary, depth: int, width, mode: Mode, capacity: int, tiles: int,
               live=None, subdivided: bool = False) -> EdgePass:
    """Passes 1 and 2 of `trace_edges` over the rays `primary` (o, d, differentials),
    pass 2's sides in `tiles` tiles (`SIDE_TILES`); `live` (traced): only the first
    `live` rays are wanted (the rest start ended); `subdivided` (static, box mode):
    which pixels want sub-boxes too."""
    o, d, diff = primary
    n = o.shape[1]
    m = prepare(s, p)
    critical = edges.Critical(jnp.asarray(s.mask(GLASS)), p.ior, depth) if mode == BOX and s.has(GLASS) else None
    watch = edges.EdgeWatch(p.centers, p.radii, m.tmin, width, curves=mode == BOX, nonlinear=subdivided,
                            critical=critical)
    first = start_rays(o, d, mode, diff)
    if live is not None:
        first = first._replace(weight=jnp.where(jnp.arange(n) < live, first.weight, 0))
    rays, best = _chain(s, p, m, first, depth, mode, width, watch=watch)
    centre = clamp_colour(rays.colour)
    packed = pack(best.edge >= 0, capacity)
    b = packed.gather(best)
    r0 = b.rays

    def two(a, b=None):  # each packed edge's two sides next to one another: the valid ones first
        return jnp.stack([a, a if b is None else b], axis=-1).reshape(a.shape[:-1] + (2 * a.shape[-1],))

    none = jnp.full(packed.index.shape, -1, jnp.int32)
    if mode == BOX:  # both sides traced from the eye, the edge's segment toggled
        side = edges.primary_sides(b, packed.gather((o, d, diff)), p.centers, p.radii, width, p.ior)
        start = start_rays(two(side.o_in, side.o_out), two(side.d_in, side.d_out), BOX,
                           edges.Differentials(*(two(a) for a in packed.gather(diff))))
        start = start._replace(weight=two(packed.valid.astype(start.weight.dtype)))
        # E's side: a silhouette's sphere forced, a curve's partner H removed; the other side: E
        # removed; either side of the boundary of total internal reflection as it comes
        curve = b.partner >= 0
        toggled = side.edge if b.critical is None else jnp.where(b.critical, none, side.edge)
        toggles = spheres.Toggles(two(jnp.where(curve, b.partner, none), toggled),
                                  two(jnp.where(curve, none, toggled), none), two(r0.level))
    else:
        side = edges.both_sides(b, p.centers, p.radii, width)
        start = Rays(two(side.o_in, side.o_out), two(side.d_in, side.d_out), two(r0.origin),
                     two(jnp.where(packed.valid, r0.weight, 0)), two(r0.colour), two(r0.level),
                     diff=edges.Differentials(*(two(a) for a in r0.diff)))
        toggles = spheres.Toggles(two(none, side.edge), two(side.edge, none))
    colour = tiled(lambda r, t: _chain(s, p, m, r, depth, mode, width, t)[0].colour, -(-2 * capacity // tiles),
                   start, toggles, count=2 * packed.count, checkpointed=False)
    inside, outside = jnp.moveaxis(clamp_colour(colour).reshape(3, capacity, 2), -1, 0)
    blended = packed.scatter(centre, spread(side.alpha) * inside + spread(1 - side.alpha) * outside)
    if mode == SIDED:
        flipped, shadow_x = clamp_colour(rays.colour + rays.flip.delta), rays.flip.x
    else:
        flipped, shadow_x = centre, jnp.full((n,), jnp.inf, centre.dtype)
    samples = edges.EdgeSamples(centre=centre, blended=blended,
                                inside=packed.scatter(centre, inside), outside=packed.scatter(centre, outside),
                                alpha=packed.scatter(jnp.ones_like(side.alpha, shape=(n,)), side.alpha),
                                x=packed.scatter(jnp.zeros_like(side.x, shape=(n,)), side.x), flipped=flipped,
                                shadow_x=shadow_x)
    return EdgePass(samples, subdivided_pixels(best, width) if subdivided else None)


def subdivided_pixels(best: edges.Best, width):
    """Which pixels `trace_edges` subdivides into sub-boxes: those whose box (`width` sample
    steps) the nearest silhouette or intersection curve may cross (within
    `edges.CROSSING` boxes), seen directly, in a mirror or through glass, and those with
    a shadow edge or a terminator that may cross it, a highlight narrow across it, or a
    rim near it, at any hit (`Best.nonlinear`). Where one edge crosses a box, others
    often lie near it (an outline and its own shadow on the floor, two shadows, a
    reflection's edges near a mirror's rim), and one straight edge per pixel misplaces
    their derivatives; across a terminator or a narrow highlight, or near a rim, the
    colour is far from linear, and one point's derivative is not the box's."""
    crossed = (best.edge >= 0) & (best.score < edges.CROSSING * width)
    return crossed | best.nonlinear


def sub_box_offsets(halvings: int) -> tuple[tuple[float, float], ...]:
    """A pixel's k × k sub-boxes (k = 2^`halvings`): their centres' offsets from its
    centre in boxes, x fastest ((±¼, ±¼) for 2 × 2)."""
    k = 2**halvings
    steps = [(2 * i + 1 - k) / (2 * k) for i in range(k)]
    return tuple((sx, sy) for sy in steps for sx in steps)


#: The most halvings of a box in one level of sub-boxes (`sub_box_levels`).
LEVEL_HALVINGS = 2
#: A second level of sub-boxes divides at most this share of the first level's
#: sub-boxes (those an edge may cross; beyond, they keep their first-level colour).
REFINED_SHARE = 2


def sub_box_levels(halvings: int) -> tuple[int, ...]:
    """The levels of sub-boxes that reach 2^`halvings` × 2^`halvings` boxes in a pixel:
    the first of at most `LEVEL_HALVINGS` halvings, a second (dividing only the
    first level's sub-boxes that an edge may cross) of the rest: (2,) for 4 × 4, (2, 2)
    for 16 × 16 where edges are."""
    first = min(halvings, LEVEL_HALVINGS)
    return (first,) if first == halvings else (first, halvings - first)


def _subdivided(s: Structure, p: Params, primary, depth: int, width, capacity: int, tiles: int,
                halvings: int) -> edges.EdgeSamples:
    """`trace_edges` in box mode with sub-boxes: rounds of one compiled pass
    (`_edge_pass`, a `lax.scan`) over the same number of rays. Round 0 traces the
    pixels and picks those to subdivide (up to `capacity`); each later round traces the
    sub-boxes of some of them (the primary rays moved to the sub-boxes' centres by their
    differentials, which shrink with the boxes), and is skipped at run time past the
    last. The levels of `sub_box_levels`: the first divides the chosen pixels into
    k × k sub-boxes, each with its own nearest edge and sides, and picks those an edge
    may cross (`subdivided_pixels` of the sub-boxes); a second divides those again.
    A box's blend is the mean of its sub-boxes'.

    One pass serves all rounds, so the mode's program holds the chain's passes once:
    its compile time is near the one-box mode's, whatever the sub-boxes (docs/EDGES.md,
    "Cost")."""
    n = primary[0].shape[1]
    levels = sub_box_levels(halvings)
    offsets = [jnp.asarray(sub_box_offsets(h), primary[0].dtype) for h in levels]  # (kk, 2) per level
    kks = [2 ** (2 * h) for h in levels]
    # boxes divided per level: the pixels picked, then a share of the first level's sub-boxes
    groups = [max(1, capacity // kk) for kk in kks]  # boxes divided per round: their sub-boxes fill ≤ capacity
    caps = [capacity] + [capacity * kks[0] // REFINED_SHARE] * (len(levels) - 1)
    rounds = [-(-cap // g) for cap, g in zip(caps, groups)]
    size = max(n, *(kk * g for kk, g in zip(kks, groups)))  # rays per round (> n only for images of under k² pixels)
    first_boxes = rounds[0] * groups[0] * kks[0]  # the first level's sub-boxes, round after round
    starts = [1 + sum(rounds[:i]) for i in range(len(levels))]  # each level's first round

    def padded(chosen, level: int):  # the boxes chosen[level] picked, padded to whole rounds
        return jnp.pad(chosen[level].index, (0, rounds[level] * groups[level] - caps[level]))

    def where_in_pixel(chosen, level: int, q):
        """The sub-boxes of level `level`'s round q (of the boxes chosen[level] picked), as
        `size` rays: their pixels, their centres' offsets from the pixels' centres in
        pixel boxes (2, size), how much smaller than a pixel they are, and how many of
        them are wanted."""
        g, kk = groups[level], kks[level]
        box = padded(chosen, level)[q * g + jnp.arange(g)]
        if level == 0:
            pixel, centre, scale = box, jnp.zeros((2, g), offsets[0].dtype), 1.0
        else:  # a first-level sub-box: its pixel, and its centre
            pixel = padded(chosen, 0)[box // kks[0]]
            centre, scale = offsets[0][box % kks[0]].T, 2.0 ** -levels[0]
        moved = jnp.repeat(centre, kk, axis=-1) + jnp.tile(offsets[level].T * scale, (1, g))
        return (pad_last(jnp.repeat(pixel, kk), size), pad_last(moved, size),
                jnp.asarray(scale * 2.0 ** -levels[level], offsets[0].dtype), kk * jnp.clip(chosen[level].count - q * g, 0, g))

    def level_round(r):
        """Which level round r traces (the last one that has begun), and its round within it."""
        level = sum((r >= start).astype(jnp.int32) for start in starts[1:])
        return level, r - jnp.asarray(starts)[level]

    def one(r, level, q, chosen):
        pixel, moved, step, live = where_in_pixel(chosen, 0, jnp.clip(q, 0, rounds[0] - 1))
        for i in range(1, len(levels)):
            pixel, moved, step, live = (jnp.where(level == i, a, b) for a, b in zip(
                where_in_pixel(chosen, i, jnp.clip(q, 0, rounds[i] - 1)), (pixel, moved, step, live)))
        po, pd, pdf = jax.tree_util.tree_map(lambda a: a[..., pixel], primary)
        o, d = edges.moved_rays(po, pd, pdf, spread(moved[0] * width), spread(moved[1] * width))
        sub = (o, d, edges.Differentials(*(a * step for a in pdf)))
        rays = jax.tree_util.tree_map(lambda a, b: jnp.where(r == 0, pad_last(a, size), b), primary, sub)
        return _edge_pass(s, p, rays, depth, width, BOX, capacity, tiles, jnp.where(r == 0, n, live), subdivided=True)

    def body(carry, r):
        chosen, picked = carry
        level, q = level_round(jnp.maximum(r, 1))
        wanted = jnp.asarray([c.count for c in chosen]) > q * jnp.asarray(groups)
        out = checkpointed_or_zeros((r == 0) | wanted[level], one, r, level, q, chosen, prevent_cse=False)
        # rays past a round's `live` start ended: no edge, not subdivided (`_edge_pass`)
        if len(levels) > 1:  # the first level's sub-boxes an edge may cross, round after round
            g = groups[0] * kks[0]
            here = jax.lax.dynamic_update_slice(picked, out.subdivided[:g], (jnp.clip(q, 0, rounds[0] - 1) * g,))
            picked = jnp.where((r > 0) & (level == 0), here, picked)
            chosen = (chosen[0], jax.lax.cond(r == starts[1] - 1, lambda: pack(picked, caps[1]), lambda: chosen[1]))
        chosen = (jax.lax.cond(r == 0, lambda: pack(out.subdivided[:n], capacity), lambda: chosen[0]),) + chosen[1:]
        return (chosen, picked), out.samples

    empty = tuple(pack(jnp.zeros(m, bool), cap) for m, cap in zip([n, first_boxes], caps))
    picked = jnp.zeros(first_boxes if len(levels) > 1 else 0, bool)  # the first level's sub-boxes to divide again
    (chosen, _), samples = jax.lax.scan(body, (empty, picked), jnp.arange(1 + sum(rounds)))
    pixels = jax.tree_util.tree_map(lambda a: a[0, ..., :n], samples)

    def boxes(level):  # (3, rounds·groups·kk) level `level`'s sub-boxes' colours, round after round
        lo, g = starts[level], groups[level] * kks[level]
        return jnp.moveaxis(samples.blended[lo:lo + rounds[level], :, :g], 0, 1).reshape(3, rounds[level] * g)

    def means(level, colours):  # (3, caps[level]) each divided box's colour: its sub-boxes' mean
        return colours.reshape(3, rounds[level] * groups[level], kks[level]).mean(axis=-1)[:, :caps[level]]

    first = boxes(0)
    if len(levels) > 1:
        first = chosen[1].scatter(first, means(1, boxes(1)))
    return pixels._replace(blended=chosen[0].scatter(pixels.blended, means(0, first)))


def checkpointed_or_zeros(run, fn, *args, prevent_cse: bool = True, checkpointed: bool = True):
    """`fn(*args)` when `run` (traced), `checkpointed` (reverse mode recomputes it rather
    than storing its intermediates), else zeros shaped as its outputs, chosen at run time
    (`lax.cond`): a skipped part of the work costs nothing. fn is traced once, for both
    its program and its outputs' shapes (`jax.eval_shape` would trace it a second time)."""
    program, shapes = jax.make_jaxpr(fn, return_shape=True)(*args)
    treedef = jax.tree_util.tree_structure(shapes)

    def traced(*a):
        return jax.tree_util.tree_unflatten(treedef, jax.extend.core.jaxpr_as_fun(program)(*jax.tree_util.tree_leaves(a)))

    def zeros(*a):
        return jax.tree_util.tree_map(lambda v: jnp.zeros(v.shape, v.dtype), shapes)

    return jax.lax.cond(run, jax.checkpoint(traced, prevent_cse=prevent_cse) if checkpointed else traced, zeros, *args)


def pad_last(a, size: int):
    """(..., k) → (..., size), k ≤ size, padded with copies of the last ray (valid rays,
    so padding computes nothing singular)."""
    return jnp.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, size - a.shape[-1])], mode="edge")


def tiled(fn, tile: int, *arrays, count=None, checkpointed: bool = True):
    """fn(*arrays) → a pytree of (..., P) arrays, run over tiles of `tile` rays one after
    another (`lax.map`) when P > tile: bounds memory on large images (the image does not
    depend on it). `count` (traced): only the first `count` rays are wanted; tiles
    wholly past them are skipped at run time (their outputs are zeros), and the others
    are `checkpointed` (reverse mode recomputes a tile instead of storing its
    intermediates: stored per tile they cost more than the recomputation), unless fn
    checkpoints its own parts (the chain's segments)."""
    n = jax.tree_util.tree_leaves(arrays)[0].shape[-1]
    if n <= tile:
        return fn(*arrays)
    m = -(-n // tile)

    def split(a):  # (..., P) → (m, ..., tile), padding with copies of the last ray
        return jnp.moveaxis(pad_last(a, m * tile).reshape(a.shape[:-1] + (m, tile)), -2, 0)

    def join(a):  # (m, ..., tile) → (..., P)
        return jnp.moveaxis(a, 0, -2).reshape(a.shape[1:-1] + (m * tile,))[..., :n]

    parts = jax.tree_util.tree_map(split, arrays)
    if count is None:
        out = jax.lax.map(lambda a: fn(*a), parts)
    else:
        def one(ia):
            i, a = ia
            return checkpointed_or_zeros(i * tile < count, fn, *a, checkpointed=checkpointed)

        out = jax.lax.map(one, (jnp.arange(m), parts))
    return jax.tree_util.tree_map(join, out)
