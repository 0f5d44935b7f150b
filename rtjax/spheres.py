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

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Bool, Float, Int

from .compact import pack
from .numerics import dot, lookup, normalize, safe_sqrt, spread, take_rows

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


def offsets(o, d, c):
    """f = o − c, b = f·d and the perpendicular offset l = f − b·d of rays (o, d) (unit
    d) from sphere centres c, all (3, ...) broadcast: every ray–sphere test starts here."""
    f = o - c
    b = dot(f, d)
    return f, b, f - spread(b) * d


#: Smallest |N·d| used for a hit's motion: at grazing incidence the motion is unbounded.
MIN_INCIDENCE = 0.05


def surface_motion(normal, t, d, entering, do, dd):
    """How a ray's hit P = o + t·d on a surface with outward `normal` moves as the ray
    moves by (∂o, ∂d): ∂P = ∂o + t·∂d + ∂t·d, ∂t = −N·(∂o + t·∂d)/(N·d), with |N·d|
    floored at `MIN_INCIDENCE`. N·d's sign is the hit's side (negative `entering`, else
    positive), not N·d's own, which is rounding alone at a grazing hit (the silhouette
    mode's forced ones)."""
    nd = dot(normal, d)
    nd = jnp.where(entering, jnp.minimum(nd, -MIN_INCIDENCE), jnp.maximum(nd, MIN_INCIDENCE))
    v = do + t * dd
    return v - spread(dot(normal, v) / nd) * d


class Roots(NamedTuple):
    """Both roots of rays against spheres, and whether each may be used."""

    near_ok: Bool[Array, "..."]
    far_ok: Bool[Array, "..."]
    near: Float[Array, "..."]
    far: Float[Array, "..."]


def roots(b, l2, r, is_origin, tmin) -> Roots:
    """The roots −b ∓ √(r² − |l|²) of rays against spheres (any broadcast shapes), and
    which may be used: met, beyond `tmin`, and by the origin rule (a ray leaving sphere
    k's surface meets k again only at its far side, pointing inward: b < 0).

    From a point on the surface the far root is 2|b| for b < 0, so the origin's far
    root is taken where −2b > `tmin`, decided on b rather than on −b + √disc: a ray
    leaving tangent to its sphere (a grazing hit of the silhouette mode, a refraction
    at the critical angle) has b and disc 0 but for rounding, and √disc would lift the
    rounding (~1e-8 relative in float64) to the size of `tmin`, so that whether the ray
    meets its own sphere again would differ between compiled programs."""
    disc = r**2 - l2
    meets = disc > 0
    sq = jnp.sqrt(jnp.maximum(disc, 0))
    near, far = -b - sq, -b + sq
    near_ok = meets & (near > tmin) & ~is_origin
    far_ok = jnp.where(is_origin, -2 * b > tmin, meets & (far > tmin))
    return Roots(near_ok, far_ok, near, far)


class Table(NamedTuple):
    """Every ray against every sphere (N, P), without derivatives: what the nearest hit,
    shadow rays and the silhouette mode's edge search all start from."""

    b: Float[Array, "n p"]  # f·d, f = o − c: the ray passes closest to the centre at t = −b
    l2: Float[Array, "n p"]  # |l|², l = f − b·d: the ray's squared distance from the centre
    f2: Float[Array, "n p"]  # |f|²: the origin's squared distance from the centre


def table(o, d, centers) -> Table:
    """The `Table` of rays (o, d) (unit d) against spheres centred at `centers`, with
    l = f − b·d formed explicitly (no cancellation in |f|² − b²)."""
    o, d, centers = jax.lax.stop_gradient((o, d, centers))
    f, b, l = offsets(o[:, None, :], d[:, None, :], centers.T[:, :, None])  # (3, N, P)
    return Table(b, dot(l, l), dot(f, f))


def plane_basis(light):
    """Two unit vectors spanning the plane ⊥ to a unit vector (no gradient)."""
    light = jax.lax.stop_gradient(light)
    use_z = jnp.abs(light[2]) < 0.9
    e1 = normalize(jnp.cross(light, jnp.where(use_z, jnp.array([0.0, 0, 1], light.dtype), jnp.array([1.0, 0, 0], light.dtype))))
    return e1, jnp.cross(light, e1)


def light_table(o, light, centers) -> Table:
    """The `table` of rays from points o that all point along one unit vector `light`,
    from coordinates along it and in the plane ⊥ it: (o − c)·L = o·L − c·L, and |l|²
    is the squared distance of their projections on the plane. A third of the
    arithmetic of `table`; the rounding of o·L (relative to |o|, not |o − c|) stays far
    below the scene-relative `tmin`."""
    o, light, centers = jax.lax.stop_gradient((o, light, centers))
    e1, e2 = plane_basis(light)
    frame = jnp.stack([light, e1, e2])  # (3, 3)
    po, pc = frame @ o, centers @ frame.T  # (3, P), (N, 3)
    b, u, v = (po[i][None, :] - pc[:, i][:, None] for i in range(3))
    l2 = u * u + v * v
    return Table(b, l2, b * b + l2)


def table_roots(tab: Table, radii, origin, tmin) -> Roots:
    """`roots` for every sphere and ray (N, P) of a `Table`."""
    is_origin = origin[None, :] == jnp.arange(radii.shape[0])[:, None]
    return roots(tab.b, tab.l2, radii[:, None], is_origin, tmin)


def others(skip, n: int) -> Bool[Array, "n p"]:
    """Per sphere and ray (N, P): is the sphere not the one `skip` names for the ray?"""
    return skip[None, :] != jnp.arange(n)[:, None]


def nearest(o, d, centers, radii, origin: Int[Array, " p"], tmin, cull: bool, exclude=None, active=None,
            tab: Table | None = None):
    """Per ray: distance to the nearest valid root (+inf if none), which sphere, and
    whether it is that sphere's far root. Not differentiated (a discrete choice).

    `cull`: test each group of rays only against the spheres it can meet
    (`culled_nearest`, for large scenes): the same answer. `exclude` (per ray, a sphere
    index or −1) removes one sphere. `active` (per ray, or None for all) marks the rays
    whose answer is used; the others may get any answer. `tab`: this ray–sphere
    `table`, when the caller has it."""
    o, d, centers, radii = jax.lax.stop_gradient((o, d, centers, radii))
    if cull:
        return culled_nearest(o, d, centers, radii, origin, tmin, exclude, active)
    near_ok, far_ok, near, far = table_roots(table(o, d, centers) if tab is None else tab, radii, origin, tmin)
    if exclude is not None:
        keep = others(exclude, centers.shape[0])
        near_ok, far_ok = near_ok & keep, far_ok & keep
    # Far roots carry a minus sign (both roots are > tmin > 0), so one argmin over |t|
    # (ties: the lowest index, as `_signed_nearest`) and one gather answer all three
    # questions: over all spheres, faster on XLA's CPU backend than two reductions.
    signed = jnp.where(near_ok, near, jnp.where(far_ok, -far, jnp.inf))
    idx = jnp.argmin(jnp.abs(signed), axis=0).astype(jnp.int32)
    t = jnp.take_along_axis(signed, idx[None], axis=0)[0]
    return jnp.abs(t), idx, t < 0


def narrowest(n: int):
    """The narrowest signed integer dtype that holds ±(n + 1) (static)."""
    for dtype in (jnp.int8, jnp.int16):
        if n + 1 <= jnp.iinfo(dtype).max:
            return dtype
    return jnp.int32


def keep_hit(best, idx, far, n: int):
    """(found, idx, far) of `nearest`, passed through one narrow code per ray named
    `CHOICE` (±(idx + 1), negative at a far root, 0: no hit): what reverse mode keeps
    of the choice instead of every ray against every sphere. Without a hit, idx is 0."""
    found = jnp.isfinite(best)
    code = checkpoint_name(jnp.where(found, jnp.where(far, -(idx + 1), idx + 1), 0).astype(narrowest(n)), CHOICE)
    return code != 0, jnp.maximum(jnp.abs(code).astype(jnp.int32) - 1, 0), code < 0


def keep_blocked(blocked):
    """A (N, P) mask passed through its bits packed along N (one byte per 8 spheres and
    ray) named `CHOICE`: what reverse mode keeps of which spheres block each shadow ray."""
    n = blocked.shape[0]
    word = checkpoint_name(jnp.packbits(blocked, axis=0), CHOICE)
    return jnp.unpackbits(word, axis=0, count=n).astype(bool)


def sphere_geometry(o, d, c, r):
    """Per ray, for one given sphere each: b, l (3, P), √disc (with a capped slope)."""
    _, b, l = offsets(o, d, c)
    disc = r**2 - dot(l, l)
    sq = safe_sqrt(disc, (SLOPE_REL[jnp.dtype(o.dtype)] * r) ** 2)
    return b, l, sq


def root_at(b, l, sq, d, r, far):
    """The root t = −b ∓ √disc of rays (unit d) on spheres (the far one, +, where `far`)
    and the outward normal there, (l ± √disc·d)/r, from `sphere_geometry`'s b, l, √disc:
    accurate far from the origin (no o + t·d − c cancellation)."""
    s = jnp.where(far, 1, -1).astype(b.dtype) * sq
    return -b + s, (l + spread(s) * d) / spread(r)


class Toggles(NamedTuple):
    """How the silhouette mode alters a segment's hits, per ray (a sphere index or −1 for
    none): `exclude` removes that sphere; `force` makes the ray see it (see `Hit`).
    `level`: the segment of the chain they alter, per ray (None: the first one traced)."""

    exclude: Int[Array, " p"]
    force: Int[Array, " p"]
    level: "Int[Array, ' p'] | None" = None

    @staticmethod
    def off(like) -> "Toggles":
        none = jnp.full(like.shape, -1, jnp.int32)
        return Toggles(none, none)

    def at(self, level) -> "Toggles":
        """These toggles for the segment at `level` (per ray): off where it is not theirs."""
        if self.level is None:
            return self
        now = level == self.level
        return Toggles(jnp.where(now, self.exclude, -1), jnp.where(now, self.force, -1))


class Hit(NamedTuple):
    """The nearest hit of each ray (`nearest_hit`)."""

    found: Bool[Array, " p"]
    index: Int[Array, " p"]  # the sphere met, or −1
    entering: Bool[Array, " p"]  # the ray met its near root, from outside
    t: Float[Array, " p"]  # distance (0 where none: no inf in later arithmetic)
    normal_out: Float[Array, "3 p"]  # outward unit normal (0 where none)
    point: Float[Array, "3 p"]  # the hit point (the origin where none)
    live: Bool[Array, " p"]  # the hits whose shading is used: found, on an active ray
    table: Table | None  # every ray against every sphere (None where spheres are culled)


def nearest_hit(o, d, centers, radii, origin, tmin, cull: bool, toggles: Toggles | None = None, active=None) -> Hit:
    """The nearest hit of each ray: distance, sphere, point, outward normal, and whether
    the ray enters the sphere. Differentiable in the rays and spheres (the choice of
    sphere is not: `nearest`).

    The normal is (P − c)/r computed as (l ± √disc·d)/r, which stays accurate when the
    scene sits far from the origin (no large o + t·d − c cancellation). `toggles` (the
    silhouette mode's first segment): `exclude` removes one sphere; `force` makes the
    ray see that sphere: if its nearest hit is anything else, it grazes that sphere at
    its silhouette point c + r·l̂, where the ray passes closest to it (entering), if
    that lies ahead (beyond `tmin`); a ray that passes it behind its origin sees what
    it meets (through glass near a rim the side of an edge can leave in another
    direction than the pixel's ray, and a point behind it is no side of that edge).
    """
    tab = None if cull else table(o, d, centers)
    exclude = None if toggles is None else toggles.exclude
    found, idx, far = keep_hit(*nearest(o, d, centers, radii, origin, tmin, cull, exclude, active, tab),
                               centers.shape[0])
    if toggles is not None:
        passes = dot(take_rows(centers, jnp.maximum(toggles.force, 0)) - o, d) > tmin  # its outline lies ahead
        forced = (toggles.force >= 0) & (~found | (idx != toggles.force)) & passes
        found, idx, far = found | forced, jnp.where(forced, toggles.force, idx), far & ~forced
    c, r = take_rows(centers, idx), lookup(radii, idx)
    b, l, sq = sphere_geometry(o, d, c, r)
    t, normal = root_at(b, l, sq, d, r, far)
    point = o + spread(t) * d
    if toggles is not None:
        t = jnp.where(forced, -b, t)
        normal = jnp.where(forced, normalize(l), normal)
        point = jnp.where(forced, c + spread(r) * normal, point)
    return Hit(found=found, index=jnp.where(found, idx, -1), entering=found & ~far, t=jnp.where(found, t, 0),
               normal_out=jnp.where(found, normal, 0), point=jnp.where(found, point, o),
               live=found if active is None else found & active, table=tab)


def transmission(o, d, centers, radii, origin, tmin, opacity_factor, skip=(), active=None, grid=None,
                 tab: Table | None = None) -> Float[Array, " p"]:
    """Shadow visibility along parallel-light rays: Π over spheres met of their factor.

    `opacity_factor[j]` is 0 for opaque, mirror and textured spheres and kt² for glass
    (shadow rays pass straight through glass, weighted kt² per sphere, DECK.md §3).
    A sphere counts if the ray meets it ahead of the origin (its far root is ahead).
    `skip` (per-ray sphere indices, or −1 for none) leaves those spheres out (the
    silhouette mode accounts for their shadow edges smoothly). `grid`: the `light_grid`
    of the direction d every ray shares, for culled scenes (`culled_transmission`;
    `active` as in `nearest`); `tab`: the shadow rays' `table`, when the caller has it.
    """
    if grid is not None:
        return culled_transmission(o, grid, centers, radii, origin, tmin, opacity_factor, skip, active)
    radii = jax.lax.stop_gradient(radii)
    _, blocked, _, _ = table_roots(table(o, d, centers) if tab is None else tab, radii, origin, tmin)
    for k in skip:
        blocked = blocked & others(k, centers.shape[0])
    factor = jnp.where(keep_blocked(blocked), opacity_factor[:, None], 1)
    return jnp.prod(factor, axis=0)


# -- culling: each ray against the spheres it can meet ------------------------------------
#
# Beyond `CULL_ABOVE` spheres, testing every ray against every sphere costs rays ×
# spheres. Two conservative structures cut that down without changing any answer: a
# sphere is dropped for a ray only when that ray cannot meet it at any root, so the
# nearest hit (ties included: candidates stay in increasing index order) and the
# shadow factors met are those over all spheres. The choices are discrete, made under
# `stop_gradient`; what is differentiated (distances, normals, kt²) is computed after,
# as without culling.
#
# * Nearest hits (`culled_nearest`): the rays whose answer is used (`active`) are
#   packed to the front (in their order) and taken CHUNK at a time in a `while_loop`
#   that stops after the last active ray, so the cost follows the active rays, not the
#   image (after the first segment, a few per cent of the pixels). A chunk is cut into
#   groups of GROUP consecutive rays (8×8 pixels for primary rays in `coherent_order`),
#   each bounded by a ball holding its origins (centre o_c, radius ρ) and a cone
#   holding its directions (axis a, half-angle θ): if ray (o, d) meets sphere (c, r) at
#   some t > 0, the point o_c + t·d lies within R = r + ρ of c, so |c − o_c| ≤ R or the
#   angle between c − o_c and a is at most θ + asin(R/|c − o_c|). Each group tests the
#   (at most `capacity`) spheres that pass; a chunk where a group has more (incoherent
#   rays: reflections off curved mirrors, refractions) tests every sphere instead.
# * Shadow rays toward a parallel light (`LightGrid`, `culled_transmission`): all share
#   the direction L, so a ray from o meets sphere (c, r) exactly when o's projection on
#   the plane ⊥ L lies within r of c's. The spheres' discs are binned once per render on
#   a grid in that plane; each active ray tests the spheres listed in its cell (packed
#   in chunks as above) and records which of them block it as bits; the product of
#   their factors (kt² or 0) is then taken per ray, differentiably. If a cell lists more
#   than `capacity` spheres, every ray is tested against every sphere.
# Slack against rounding: radii grow by a relative `_RADIUS_SLACK` plus `tmin`, cones
# by `_ANGLE_SLACK` radians.

#: The name (`jax.ad_checkpoint.checkpoint_name`) of the discrete choices a segment makes
#: (which sphere each ray meets, which spheres block each shadow ray): reverse mode keeps
#: them rather than recomputing every ray against every sphere (`trace._chain`).
CHOICE = "choice"
#: Scenes with at most this many spheres test every ray against every sphere (the
#: fast path for small scenes); larger ones cull (`Structure.culls`).
CULL_ABOVE = 32
#: Candidate spheres listed per group of rays and per cell of a light's grid, at most.
MAX_CANDIDATES = 32
#: Rays per group (8×8 pixels when rays come in `coherent_order`).
GROUP = 64
#: Rays per chunk of the culled loops.
CHUNK = 2048
_ANGLE_SLACK = 1e-3
_RADIUS_SLACK = 1e-4

def capacity(n: int) -> int:
    """Candidate spheres per group of rays, and per cell of a light's grid (static)."""
    return min(n, MAX_CANDIDATES)


def grid_side(n: int) -> int:
    """Cells per side of a light's grid (static): about one sphere per cell."""
    return int(min(64, max(4, round(n**0.5))))


def coherent_order(width: int, height: int, block: int = 8):
    """A permutation of row-major pixel indices visiting the image in `block`×`block`
    tiles (row-major inside each): consecutive rays then form compact groups (used by
    `render` when scenes are culled). Returns (order, inverse) as NumPy."""
    j, i = np.divmod(np.arange(width * height), width)
    key = ((j // block) * (-(-width // block)) + i // block) * block * block + (j % block) * block + i % block
    order = np.argsort(key, kind="stable")
    inverse = np.empty_like(order)
    inverse[order] = np.arange(order.size)
    return order, inverse


def first_k(ok, k: int):
    """Per row of a boolean (G, N) mask: the indices of its first `k` true entries in
    increasing order (G, k), which slots hold one, and whether the row has more."""
    g, n = ok.shape
    pos = jax.lax.associative_scan(jnp.add, ok.astype(jnp.int32), axis=1) - 1
    slot = jnp.where(ok & (pos < k), pos, k)  # slot k: the overflow's bin
    rows = jnp.broadcast_to(jnp.arange(g)[:, None], (g, n))
    idx = jnp.zeros((g, k + 1), jnp.int32).at[rows, slot].set(jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (g, n)))
    count = pos[:, -1] + 1
    return idx[:, :k], jnp.arange(k)[None, :] < count[:, None], count > k


def _cross_norm(a, b):
    x = a[1] * b[2] - a[2] * b[1]
    y = a[2] * b[0] - a[0] * b[2]
    z = a[0] * b[1] - a[1] * b[0]
    return jnp.sqrt(x * x + y * y + z * z)


def group_candidates(o, d, active, centers, radii, tmin, k: int):
    """For rays grouped (3, G, T) with `active` (G, T): per group, the first `k` spheres
    its active rays may meet (G, k), which slots are used, and whether it has more."""
    w = active.astype(o.dtype)
    count = jnp.sum(w, axis=-1)
    oc = jnp.sum(o * w, axis=-1) / jnp.maximum(count, 1)  # (3, G)
    off = o - oc[..., None]
    rho = jnp.sqrt(jnp.max(jnp.where(active, dot(off, off), 0), axis=-1))  # (G,)
    s = jnp.sum(d * w, axis=-1)
    s_len = jnp.sqrt(dot(s, s))
    axis = s / jnp.where(s_len > 0, s_len, 1)
    angle = jnp.arctan2(_cross_norm(d, axis[..., None]), dot(d, axis[..., None]))
    theta = jnp.max(jnp.where(active, angle, 0), axis=-1)
    theta = jnp.where(s_len > 1e-3 * jnp.maximum(count, 1), theta + _ANGLE_SLACK, jnp.pi)
    v = centers.T[:, None, :] - oc[:, :, None]  # (3, G, N)
    dist2 = dot(v, v)
    big_r = (radii[None, :] + rho[:, None]) * (1 + _RADIUS_SLACK) + tmin
    along = dot(v, axis[:, :, None])
    # angle(v, a) ≤ θ + β with sin β = R/|v|  ⇔  v·a ≥ |v|·cos(θ + β), for θ + β ≤ π
    bound = jnp.cos(theta)[:, None] * jnp.sqrt(jnp.maximum(dist2 - big_r**2, 0)) - jnp.sin(theta)[:, None] * big_r
    ok = (dist2 <= big_r**2) | (theta[:, None] >= jnp.pi / 2) | (along >= bound)
    return first_k(ok & jnp.any(active, axis=-1)[:, None], k)


def pair_roots(o, d, c, r, origin, k, tmin) -> Roots:
    """`roots` of rays against candidate spheres, broadcast (o, d: (3, ...); c: (3, ...);
    r, origin, sphere indices k: (...))."""
    _, b, l = offsets(o, d, c)
    return roots(b, dot(l, l), r, origin == k, tmin)


def _signed_nearest(near_ok, far_ok, near, far, k, axis):
    """Along `axis` (sphere indices `k`, broadcast): the nearest valid root, signed
    (far roots negative; +inf if none), and the first sphere that has it (0 if none).

    Two plain reductions (min |t|, then the least index·2 + far among those at the
    minimum): for the candidates of the culled loops, where an argmin over a middle
    axis is slow on XLA's CPU backend."""
    signed = jnp.where(near_ok, near, jnp.where(far_ok, -far, jnp.inf))
    a = jnp.abs(signed)
    m = jnp.min(a, axis=axis, keepdims=True)
    code = jnp.min(jnp.where(a == m, 2 * k + (signed < 0), jnp.iinfo(jnp.int32).max), axis=axis)
    m = jnp.squeeze(m, axis)
    return jnp.where(code % 2 == 1, -m, m), (code // 2).astype(jnp.int32)


def _packed(active, p: int):
    """Indices of the active rays first (in order), padded with p to whole chunks, and
    how many chunks hold them."""
    packed = pack(active, p)
    order = packed.target
    pad = -(-p // CHUNK) * CHUNK - p
    if pad:
        order = jnp.concatenate([order, jnp.full((pad,), p, order.dtype)])
    return order, (packed.count + CHUNK - 1) // CHUNK


def _chunk_loop(order, chunks, p: int, body, init):
    """body(sel, ok, carry) → carry over the chunks of packed rays (a `while_loop`);
    `ok`: the slot holds one of the `p` rays (not padding)."""

    def step(state):
        i, carry = state
        sel = jax.lax.dynamic_slice(order, (i * CHUNK,), (CHUNK,))
        return i + 1, body(sel, sel < p, carry)

    return jax.lax.while_loop(lambda s: s[0] < chunks, step, (jnp.zeros((), chunks.dtype), init))[1]


def culled_nearest(o, d, centers, radii, origin, tmin, exclude=None, active=None):
    """`nearest` (inputs already without gradient) through culling: the same answer for
    every active ray; inactive rays get "no hit"."""
    n, p = centers.shape[0], o.shape[1]
    k = capacity(n)
    if active is None:
        active = jnp.ones((p,), bool)
    if exclude is None:
        exclude = jnp.full((p,), -1, jnp.int32)
    order, chunks = _packed(active, p)
    every = jnp.arange(n, dtype=jnp.int32)
    g = CHUNK // GROUP

    def body(sel, ok, carry):
        t_out, idx_out = carry
        at = jnp.minimum(sel, p - 1)
        oc, dc, org, exc = o[:, at], d[:, at], origin[at], exclude[at]

        def all_spheres(_):
            near_ok, far_ok, near, far = pair_roots(
                oc[:, None, :], dc[:, None, :], centers.T[:, :, None], radii[:, None], org[None, :], every[:, None], tmin)
            keep = others(exc, n)
            return _signed_nearest(near_ok & keep, far_ok & keep, near, far, every[:, None], 0)

        def grouped(cv):
            cand, valid = cv
            kk = cand[..., None]  # (G, K, 1)
            near_ok, far_ok, near, far = pair_roots(
                oc.reshape(3, g, 1, GROUP), dc.reshape(3, g, 1, GROUP), jnp.moveaxis(centers[cand], -1, 0)[..., None],
                radii[cand][..., None], org.reshape(g, 1, GROUP), kk, tmin)
            keep = valid[..., None] & (exc.reshape(g, 1, GROUP) != kk)
            t, idx = _signed_nearest(near_ok & keep, far_ok & keep, near, far, kk, 1)
            return t.reshape(CHUNK), idx.reshape(CHUNK)

        cand, valid, over = group_candidates(oc.reshape(3, g, GROUP), dc.reshape(3, g, GROUP), ok.reshape(g, GROUP),
                                             centers, radii, tmin, k)
        t, idx = jax.lax.cond(jnp.any(over), all_spheres, grouped, (cand, valid))
        idx = jnp.where(jnp.isfinite(t), idx, 0)  # no root: sphere 0, as over all spheres
        return t_out.at[sel].set(t, mode="drop"), idx_out.at[sel].set(idx, mode="drop")

    init = (jnp.full((p,), jnp.inf, o.dtype), jnp.zeros((p,), jnp.int32))
    t, idx = _chunk_loop(order, chunks, p, body, init)
    return jnp.abs(t), idx, t < 0


class LightGrid(NamedTuple):
    """Spheres binned by their shadow's footprint on the plane ⊥ to a parallel light."""

    light: Float[Array, " 3"]  # unit, toward the light: every shadow ray's direction
    e1: Float[Array, " 3"]
    e2: Float[Array, " 3"]
    lo: Float[Array, " 2"]  # the grid's corner (u, v)
    cell: Float[Array, " 2"]  # cell sides
    cand: Int[Array, "c k"]  # per cell, the spheres whose disc may cover it, increasing
    valid: Bool[Array, "c k"]
    over: Bool[Array, ""]  # some cell covers more spheres than it lists


def light_grid(light, centers, radii, tmin) -> LightGrid:
    """Bin the spheres' discs seen along `light` (unit) on `grid_side(n)`² cells."""
    light, centers, radii = jax.lax.stop_gradient((light, centers, radii))
    n = centers.shape[0]
    side = grid_side(n)
    e1, e2 = plane_basis(light)
    uv = jnp.stack([centers @ e1, centers @ e2])  # (2, N)
    big_r = radii * (1 + _RADIUS_SLACK) + tmin
    lo = jnp.min(uv - big_r, axis=1)
    cell = (jnp.max(uv + big_r, axis=1) - lo) / side
    mid = lo[:, None] + (jnp.arange(side, dtype=lo.dtype) + 0.5)[None, :] * cell[:, None]  # (2, S)
    gap = jnp.maximum(jnp.abs(uv[:, None, :] - mid[:, :, None]) - cell[:, None, None] / 2, 0)  # (2, S, N)
    # a disc overlaps cell (i, j) iff its centre is within R of the cell's rectangle
    ok = gap[0][:, None, :] ** 2 + gap[1][None, :, :] ** 2 <= big_r**2  # (S, S, N)
    cand, valid, over = first_k(ok.reshape(side * side, n), capacity(n))
    return LightGrid(light, e1, e2, lo, cell, cand, valid, jnp.any(over))


def _cell_of(grid: LightGrid, o):
    side = int(round(grid.cand.shape[0] ** 0.5))  # static: the grid is side × side cells
    i = jnp.clip(jnp.floor((dot(o, grid.e1[:, None]) - grid.lo[0]) / grid.cell[0]), 0, side - 1).astype(jnp.int32)
    j = jnp.clip(jnp.floor((dot(o, grid.e2[:, None]) - grid.lo[1]) / grid.cell[1]), 0, side - 1).astype(jnp.int32)
    return i * side + j


def culled_transmission(o, grid: LightGrid, centers, radii, origin, tmin, factor, skip=(), active=None):
    """`transmission` along `grid.light` through the grid: each active ray tests the
    spheres listed for its cell (the same factors met; inactive rays get 1)."""
    p = o.shape[1]
    if active is None:
        active = jnp.ones((p,), bool)
    o_sg, centers_sg, radii_sg = jax.lax.stop_gradient((o, centers, radii))
    cells = _cell_of(grid, o_sg)
    listing = jnp.concatenate([centers_sg, radii_sg[:, None]], axis=1)[grid.cand]  # (C, K, 4): per cell, its spheres
    k = grid.cand.shape[1]
    bit = (jnp.uint32(1) << jnp.arange(k, dtype=jnp.uint32))
    light = grid.light[:, None]

    def body(sel, ok, bits):
        at = jnp.minimum(sel, p - 1)
        c = cells[at]
        sph, cand, valid = listing[c], grid.cand[c], grid.valid[c]  # (CHUNK, K, ·): row gathers
        oc = o_sg[:, at][:, :, None]
        _, blocked, _, _ = pair_roots(oc, light[:, :, None], jnp.moveaxis(sph[..., :3], -1, 0), sph[..., 3],
                                       origin[at][:, None], cand, tmin)
        blocked = blocked & valid
        for s in skip:
            blocked = blocked & (s[at][:, None] != cand)
        word = jnp.sum(jnp.where(blocked, bit, jnp.uint32(0)), axis=1, dtype=jnp.uint32)
        return bits.at[sel].set(word, mode="drop")

    def listed(_):
        order, chunks = _packed(active, p)
        bits = checkpoint_name(_chunk_loop(order, chunks, p, body, jnp.zeros((p,), jnp.uint32)), CHOICE)
        blocked = (bits[:, None] & bit) != 0  # (P, K)
        return jnp.prod(jnp.where(blocked, factor[grid.cand][cells], 1), axis=1)

    def all_spheres(_):
        d = jnp.broadcast_to(light, o.shape)
        _, blocked, _, _ = table_roots(table(o_sg, d, centers_sg), radii_sg, origin, tmin)
        for k in skip:
            blocked = blocked & others(k, centers.shape[0])
        return jnp.prod(jnp.where(blocked, factor[:, None], 1), axis=0)

    return jax.lax.cond(grid.over, all_spheres, listed, None)
