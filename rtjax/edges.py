"""The silhouette-aware mode: box-filtered edges whose derivatives include edge motion.

A pixel-centre render is piecewise constant across a sphere's silhouette and across a
shadow's edge, so its derivative misses what moves them. Spheres make both edges
analytic. A ray (o, d) passes a sphere (c, r)'s outline at the signed angular gap
g = φ − asin(r/|f|) (φ: the angle between d and the direction to the centre), and a
parallel light's shadow ray passes an occluder's shadow cylinder at |l| − r (l: the
offset of the ray from the centre). With the ray's differentials (how o and d change
per pixel: ∂o, ∂d, carried along the chain through reflections and refractions by
forward-mode AD) each changes per pixel at a rate across and down; their ratio δ is
the signed distance to the edge in pixels and the rate's direction is the edge's
normal in the image. Two edges are handled that way:

* Silhouettes, on every segment of the chain (seen directly, in mirrors, through
  glass). Per pixel the one visible silhouette nearest to its ray over the whole chain
  is blended: pixel = α·C_in + (1 − α)·C_out, α the fraction of a box of `width`
  pixels on the sphere's side of the edge (exact for a straight edge: a trapezoid's
  CDF). Both sides are traced from that segment on, through the centroids of their
  parts of the box (exact for a straight edge and colours linear across the pixel):
  C_out with the sphere removed, C_in with it met (grazing its outline if the offset
  ray misses it).
* Shadow edges, at every hit: a parallel light's shadow of a sphere is a cylinder, the
  shadow ray's distance to it is |l| − r, and the hit point's motion per pixel gives
  its rate. The nearest occluder edge's hard factor (0 or kt²) becomes 1 − (1 − τ)·α;
  in box mode the two nearest occluders' edges are both filtered (where one
  occluder's shadow grazes another, their edges run a fraction of a pixel apart).

Box mode also takes intersection curves of spheres cutting into one another
(`rtjax.curves`) and the boundary of total internal reflection where a ray leaves a
glass sphere (`critical_terms`) as a pixel's edge, where nearer.

Not covered: a second edge in the same pixel (the nearer one in pixels wins, chosen
by a bound on the distance, see `_candidates`), the
specular term's cut-off at a terminator, and the curvature of an outline within a
pixel. As `width` → 0, α becomes a step and the image is the plain one. Cost: the
chain with its differentials, plus a second chain from the edge's segment on.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Bool, Float, Int

from . import curves, spheres
from .numerics import clamp, dot, lookup, normalize, safe_div, safe_sqrt, spread, take_rows, tiny

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


def _cdf(y, s, e, ab):
    """`coverage`'s F at y in the support [−s, s], bounded to [0, 1]."""
    return clamp(_ramps(y, s, e, 2) / (2 * ab), 0, 1)


def coverage(x, a, b):
    """Fraction of a unit square on the inner side of a straight edge.

    x: signed distance from the square's centre to the edge in units of its side,
    positive inside; (a, b): the edge normal's components in the image. The fraction is
    the CDF F of z = a·U₁ + b·U₂ for U uniform on [−½, ½]: a trapezoid's integral, C¹.
    x is clamped to the trapezoid's support [−s, s] (F is 0 or 1 beyond it): the ramps'
    squares would cancel catastrophically at a far edge (`FAR`). F is bounded to
    [0, 1]: at the support's ends rounding puts it just past them, and a visibility of
    1 − F a rounding error below 0 would leave a channel it scales (a highlight where
    the diffuse colour has none) just below 0, where `clamp_colour` drops the channel's
    derivative.
    """
    s, e, ab = _trapezoid(a, b)
    return _cdf(jnp.clip(x, -s, s), s, e, ab)


def split_box(x, a, b):
    """Coverage α and the centroids of the square's inside and outside parts.

    Centroids are positions along the inward normal, in units of the side, relative to
    the centre: E[z | z > −x] and E[z | z < −x], from F and G = ∫F (cubic ramps).
    """
    s, e, ab = _trapezoid(a, b)
    x = jnp.clip(x, -s, s)  # as in `coverage`: beyond, the box lies on one side

    def g(y):
        return _ramps(y, s, e, 3) / (6 * ab)

    alpha = _cdf(x, s, e, ab)
    inside = jnp.clip(safe_div(g(x), alpha) - x, -s, s)
    outside = jnp.clip(-x - safe_div(g(-x), _cdf(-x, s, e, ab)), -s, s)
    return alpha, inside, outside


class Differentials(NamedTuple):
    """How each ray's origin and direction change per sample step, across and down."""

    ox: Float[Array, "3 p"]
    dx: Float[Array, "3 p"]
    oy: Float[Array, "3 p"]
    dy: Float[Array, "3 p"]


class Motion(NamedTuple):
    """How each hit point moves per sample step, across and down."""

    x: Float[Array, "3 p"]
    y: Float[Array, "3 p"]


def hit_motion(hit: spheres.Hit, d, diff: Differentials) -> Motion:
    """How the hit point moves per sample step (`spheres.surface_motion`), across and
    down; differentiable in the scene, as the differentials are (see `trace.segment`)."""
    return Motion(*(spheres.surface_motion(hit.normal_out, hit.t, d, hit.entering, do, dd)
                    for do, dd in ((diff.ox, diff.dx), (diff.oy, diff.dy))))


def edge_terms(o, d, ox, dx, oy, dy, c, r):
    """Signed distance δ (in sample steps) from rays to |l| = r, positive outside: for a
    parallel light's shadow ray, the occluder's shadow cylinder (silhouettes use
    `outline_terms`); the edge's normal (nx, ny) in the image; where along the ray it
    passes closest (t); whether the ray starts outside the sphere.

    Rays (3, P) against one sphere per ray (c: (3, P)), or broadcast (3, N, P)."""
    f, b, lvec = spheres.offsets(o, d, c)
    floor = jnp.asarray(tiny(o.dtype), o.dtype)
    l = safe_sqrt(dot(lvec, lvec), floor)
    lhat = normalize(lvec)
    t = -b
    rx = dot(lhat, ox + spread(t) * dx)
    ry = dot(lhat, oy + spread(t) * dy)
    delta, nx, ny = _signed(l - r, rx, ry)
    return delta, nx, ny, t, dot(f, f) > r**2


#: |δ| (sample steps) given where an edge's distance has no rate along a ray: beyond any box.
FAR = 1e6


def _signed(gap, rx, ry):
    """An edge's signed distance δ = gap / rate in sample steps and its unit normal
    (nx, ny) in the image, from the gap and its rates across (rx) and down (ry).

    Where δ would pass ±`FAR`, above all where the rate vanishes (a ray aimed at a
    sphere's centre: the apex of its outline cone; a shadow ray through an occluder's
    centre), the edge lies beyond any box: δ = ±FAR by the gap's sign, normal (1, 0),
    and the division is not taken (its derivative would overflow)."""
    floor = jnp.asarray(tiny(gap.dtype), gap.dtype)
    rate = safe_sqrt(rx**2 + ry**2, floor)
    far = jnp.abs(gap) >= FAR * rate
    rate = jnp.where(far, 1, rate)
    delta = jnp.where(far, jnp.where(gap < 0, -FAR, FAR).astype(gap.dtype), gap / rate)
    return delta, jnp.where(far, 1, rx / rate), jnp.where(far, 0, ry / rate)


def outline_terms(o, d, ox, dx, oy, dy, c, r):
    """Signed distance δ (in sample steps) from rays to a sphere's outline as seen from
    their origins, positive outside, and the outline's normal (nx, ny) in the image.

    The distance is angular: g = φ − φ_s, φ the angle between the ray and the direction
    to the centre, φ_s = asin(r/|f|) the outline cone's half angle (one atan2, without
    the angles' cancellation), its rate per sample step from the ray differentials.
    |l| − r (`edge_terms`) has the same zero set, but it goes as sin φ, which is far
    from linear where a ray passes a sphere seen large and near its tangent, as a
    reflected ray passes the floor near its horizon: there its linearised distance was
    off by up to half a pixel. Rays (3, P) against one sphere per ray (c: (3, P))."""
    floor = jnp.asarray(tiny(o.dtype), o.dtype)

    def g(o, d):
        f, b, lvec = spheres.offsets(o, d, c)
        l, q = safe_sqrt(dot(lvec, lvec), floor), safe_sqrt(dot(f, f) - r**2, floor)
        return jnp.arctan2(l * q + b * r, l * r - b * q)

    gap, rx = jax.jvp(g, (o, d), (ox, dx))
    ry = jax.jvp(g, (o, d), (oy, dy))[1]
    return _signed(gap, rx, ry)


def _chosen_or_regular(edge, o, d, centers, radii):
    """Centre and radius of each ray's chosen sphere; where none is chosen, a stand-in
    sphere well clear of the ray (so the unused branch has finite derivatives: the
    double-where pattern, applied to the geometry)."""
    e = jnp.maximum(edge, 0)
    c, r = take_rows(centers, e), lookup(radii, e)
    x, y, z = d
    use_z = jnp.abs(z) < 0.9
    side = normalize(jnp.stack([jnp.where(use_z, y, 0), jnp.where(use_z, -x, z), jnp.where(use_z, 0, -y)]))
    stand_in = o + r * (3 * d + 2 * side)  # d × ẑ or d × x̂, unit: 2r off the ray, 3r along it
    return jnp.where(edge >= 0, c, jax.lax.stop_gradient(stand_in)), r


def _candidates(gap, reach, ok, width: float):
    """Per ray, the sphere whose edge is nearest in sample steps among the `ok` ones
    within `width` steps, or −1 (`_scores`)."""
    return _nearest(_scores(gap, reach, ok, width))


def _scores(gap, reach, ok, width: float):
    """Per sphere and ray, a lower bound of the distance to the sphere's edge in sample
    steps where the sphere is `ok` and the bound within `width`, else inf.

    The exact distance δ needs each sphere's own edge normal; `gap` (per ray and
    sphere: |l| − r for a shadow cylinder, the angular gap for an outline) over `reach`
    (per ray and sphere, or per ray), a bound on gap's rate over the ray's footprint,
    is a lower bound of |δ|: no edge within `width` is missed, and only the chosen
    sphere's δ is computed exactly (`edge_terms`, `outline_terms`). The choice among
    several edges within reach follows the bound (they agree up to the footprint's
    shape)."""
    bound = jnp.abs(gap) / reach
    return jnp.where(ok & (bound < width), bound, jnp.inf)


def _nearest(score):
    """Per ray, the sphere of smallest finite score, or −1. (argmin and a gather: XLA's
    CPU backend runs a min over the leading axis much slower than argmin.)"""
    idx = jnp.argmin(score, axis=0)
    best = jnp.take_along_axis(score, idx[None], axis=0)[0]
    return checkpoint_name(jnp.where(jnp.isfinite(best), idx, -1).astype(jnp.int32), spheres.CHOICE)


class Flip(NamedTuple):
    """Per pixel, its nearest shadow edge over the chain (sided mode, `soft_shadow`):
    how the colour changes if the pixel's centre lay on the edge's other side, and the
    centre's distance to the edge in box widths (inf: none within reach)."""

    x: Float[Array, " p"]
    delta: Float[Array, "3 p"]

    @staticmethod
    def none(like) -> "Flip":
        p = like.shape[-1]
        return Flip(jnp.full(p, jnp.inf, like.dtype), jnp.zeros((3, p), like.dtype))

    def nearer(self, other: "Flip") -> "Flip":
        """Per pixel, whichever of the two edges is nearer."""
        return jax.tree_util.tree_map(lambda a, b: jnp.where(self.x < other.x, a, b), self, other)


class Shadow(NamedTuple):
    """One light's visibility at each hit (`soft_shadow`)."""

    here: Float[Array, " p"]  # at the pixel: box-filtered (box mode) or at its centre (sided mode)
    there: Float[Array, " p"]  # sided mode: had the centre lain across its nearest shadow edge (else `here`)
    x: Float[Array, " p"]  # sided mode: the centre's distance to that edge in box widths (inf: none)
    near: Bool[Array, " p"]  # an edge filtered (box mode: either) may cross the hit's box (within `CROSSING` boxes)


class ShadowEdge(NamedTuple):
    """One light's shadow edge at each hit (`shadow_edges`)."""

    occluder: Int[Array, " p"]  # the occluder whose shadow cylinder it is, or −1 (none within reach)
    delta: Float[Array, " p"]  # the hit's signed distance to that cylinder, in sample steps
    nx: Float[Array, " p"]  # the edge's normal in the image
    ny: Float[Array, " p"]


def shadow_edges(hit: spheres.Hit, light, centers, radii, tmin, motion: Motion, width, tab: spheres.Table,
                 count: int) -> tuple[ShadowEdge, ...]:
    """One light's `count` nearest shadow edges within `width` sample steps of each hit,
    nearest first, each of another occluder (`soft_shadow`); `tab`: the hits'
    `light_table`. The bounds that choose them are taken once for all `count`."""
    n = centers.shape[0]
    ray = jnp.broadcast_to(light[:, None], hit.point.shape)
    still = jnp.zeros_like(ray)  # a parallel light: the shadow ray's direction does not move
    sg = jax.lax.stop_gradient
    reach = safe_sqrt(sg(dot(motion.x, motion.x) + dot(motion.y, motion.y)), jnp.asarray(tiny(ray.dtype), ray.dtype))
    own = hit.index[None, :] == jnp.arange(n)[:, None]
    ahead = (-tab.b > tmin) & ~own & hit.found[None, :]
    score = _scores(jnp.sqrt(tab.l2) - sg(radii)[:, None], reach, ahead, width)
    found = []
    for _ in range(count):
        edge = _nearest(score)
        score = jnp.where(spheres.others(edge, n), score, jnp.inf)
        c, r = _chosen_or_regular(edge, hit.point, ray, centers, radii)
        delta, nx, ny, _, _ = edge_terms(hit.point, ray, motion.x, still, motion.y, still, c, r)
        found.append(ShadowEdge(edge, delta, nx, ny))
    return tuple(found)


def soft_shadow(hit: spheres.Hit, light, centers, radii, tmin, factor, motion: Motion, width, sided: bool) -> Shadow:
    """Visibility of one light at each hit, its two nearest shadow edges box-filtered.

    The hard visibility of every other occluder times the soft factors
    1 − (1 − τ)·α of the two nearest edges within reach (τ: 0, or kt² for glass; α:
    fraction of the pixel's footprint on the surface inside that occluder's shadow
    cylinder; the footprint's share in both shadows taken as the product of its
    shares): where one occluder's shadow cylinder grazes another, the two shadows'
    edges run a fraction of a pixel apart, and the nearer alone would leave the other's
    hard, its motion lost. The hit's own sphere stays hard: its terminator is already
    continuous in max(N·L, 0).

    `sided`: instead, for the nearest edge, the value at the pixel's centre (the edge's
    hard factor, no edge derivative), the value had the centre lain on the edge's other
    side, and the centre's distance to the edge in box widths (differentiable; inf
    where no edge is within reach): what a target sampled at pixel centres needs
    (`rtjax.edge_samples`).
    """
    ray = jnp.broadcast_to(light[:, None], hit.point.shape)
    sg = jax.lax.stop_gradient
    tab = spheres.light_table(hit.point, light, centers)
    found = shadow_edges(hit, light, centers, radii, tmin, motion, width, tab, 1 if sided else 2)

    def blocked(e):  # what occluder e's shadow takes of the light (1, or 1 − kt² for glass)
        return 1 - factor[jnp.maximum(e, 0)]

    def near(e, delta):  # the edge may cross the box
        return (e >= 0) & (jnp.abs(sg(delta)) < CROSSING * width)

    skip = tuple(f.occluder for f in found)
    hard = spheres.transmission(hit.point, ray, centers, radii, hit.index, tmin, factor, skip=skip, tab=tab)
    if sided:
        (edge, delta_e, _, _), = found
        inside = sg(delta_e) < 0
        reached = (edge >= 0) & (jnp.abs(sg(delta_e)) < width)
        here = jnp.where(edge >= 0, 1 - blocked(edge) * inside, 1)
        there = jnp.where(reached, 1 - blocked(edge) * ~inside, here)
        return Shadow(hard * here, hard * there, jnp.where(reached, jnp.abs(delta_e) / width, jnp.inf),
                      near(edge, delta_e))
    soft = hard
    crossing = jnp.zeros_like(skip[0], bool)
    for e, delta, nx, ny in found:  # |δ| ≥ width (a candidate by the bound only): α is 0 or 1
        soft = soft * jnp.where(e >= 0, 1 - blocked(e) * coverage(-delta / width, nx, ny), 1)
        crossing = crossing | near(e, delta)
    return Shadow(soft, soft, jnp.full_like(soft, jnp.inf), crossing)


def near_terminator(nl, light, motion: Motion, radius, width):
    """Whether each hit's terminator for one light (N·L = 0, where shading's max(N·L, 0)
    and the highlight turn off) may cross its box of `width` sample steps: |N·L| within
    `CROSSING` boxes of its rate over the footprint (the normal of a sphere of radius r
    turns by the hit's motion / r). Shading is continuous there but far from linear
    across the box, and a box traced at one point takes its derivative from that point
    alone: such boxes are worth sub-boxes (`trace.subdivided_pixels`)."""
    sg = jax.lax.stop_gradient
    rate = safe_sqrt(sum(dot(sg(m), light[:, None]) ** 2 for m in motion), tiny(nl.dtype)) / sg(radius)
    return jnp.abs(sg(nl)) < CROSSING * width * rate


def hit_speed(motion: Motion):
    """How far each hit point moves per sample step, |motion| over both directions (not
    differentiated): with the sphere's radius, how fast its normal turns
    (`near_highlight`); light-independent, so taken once per hit."""
    sg = jax.lax.stop_gradient
    return safe_sqrt(sum(dot(sg(m), sg(m)) for m in motion), tiny(motion.x.dtype))


def near_highlight(cos_g, ks, beta, speed, radius, width):
    """Whether each hit's specular highlight for one light (ks·max(cos γ, 0)^β, a lobe
    about 1/√β wide in γ) may be narrower than its box of `width` sample steps shows:
    over the box γ turns by up to twice the normal's turn (the hit's `hit_speed` / r),
    and where that is over `HIGHLIGHT_TURN` lobe widths within `HIGHLIGHT_REACH` widths
    of the lobe's peak, shading is smooth but far from linear across the box (a small
    sphere's highlight, or one a glass ball shrinks, inside a pixel): such boxes are
    worth sub-boxes (`trace.subdivided_pixels`), as a point's derivative is not the box's."""
    sg = jax.lax.stop_gradient
    turn = 2 * CROSSING * width * speed / sg(radius)
    gamma = jnp.arccos(jnp.clip(sg(cos_g), -1, 1))
    root = jnp.sqrt(sg(beta))
    return (sg(ks) > 0) & (turn * root > HIGHLIGHT_TURN) & ((gamma - turn) * root < HIGHLIGHT_REACH)


def edge_pixels(keys: Int[Array, "h+2r w+2r"], reach: int) -> Bool[Array, "h w"]:
    """Which samples of a lattice have keys (`trace.hit_key`: the spheres each chain
    meets and the shadows on them) not all equal within `reach` samples across and
    down. `keys` holds the lattice and a ring `reach` samples wide around it.

    A straight edge that crosses a pixel's box (of side ≤ 2·`reach` samples) separates
    its centre from the corner of its (2·`reach` + 1)² neighbourhood that lies beyond
    the edge, so a pixel not chosen has no silhouette or shadow edge in its box (bar
    outlines curving within it, and features narrower than the samples' spacing that
    fall between them): its plain colour is its box-filtered colour."""
    k = 2 * reach + 1
    lo = jax.lax.reduce_window(keys, jnp.uint32(0xFFFFFFFF), jax.lax.min, (k, k), (1, 1), "VALID")
    hi = jax.lax.reduce_window(keys, jnp.uint32(0), jax.lax.max, (k, k), (1, 1), "VALID")
    return lo != hi


#: A straight edge crosses a square box only within √½ of its side from the centre
#: (its half-diagonal); farther, the box lies on one side (α is 0 or 1).
CROSSING = 0.5**0.5
#: A highlight whose lobe (width 1/√β in γ) turns over its box by more than this many
#: widths, and whose peak lies within `HIGHLIGHT_REACH` widths of the box (where the lobe
#: is over e^(−REACH²/2) of its peak), is far from linear across the box (`near_highlight`).
HIGHLIGHT_TURN = 0.5
HIGHLIGHT_REACH = 3.0
#: Within this many boxes of the outline of the sphere a ray meets, its shading is far
#: from linear across a box (the hit's depth, and so its normal and shading, change as
#: the square root of the distance from the rim): `EdgeWatch`'s `nonlinear` boxes.
RIM = 1.5


class Best(NamedTuple):
    """The nearest visible silhouette found so far along each pixel's chain."""

    score: Float[Array, " p"]  # |δ| in sample steps (inf: none yet)
    edge: Int[Array, " p"]  # its sphere, or −1
    rays: object  # the chain's rays at that segment (`trace.Rays`, with their differentials), before it
    partner: Int[Array, " p"]  # an intersection curve: the sphere H the edge's sphere cuts into (else −1)
    nonlinear: "Bool[Array, ' p'] | None" = None  # watched: a shadow edge, terminator, narrow highlight or rim near a hit (`EdgeWatch`)
    critical: "Bool[Array, ' p'] | None" = None  # watched for: the edge is where its glass sphere's exit turns to TIR

    def nearer(self, score, edge, partner, critical: bool) -> "Best":
        """Per ray, this edge or the one given (its `score`, sphere, `partner` and whether
        it is a TIR boundary), whichever scores lower."""
        closer = score < self.score
        return self._replace(score=jnp.where(closer, score, self.score), edge=jnp.where(closer, edge, self.edge),
                             partner=jnp.where(closer, partner, self.partner),
                             critical=None if self.critical is None else jnp.where(closer, critical, self.critical))


class EdgeWatch:
    """Folded over a chain's segments: keeps, per pixel, the visible silhouette nearest
    to its ray. Visible: the segment's ray meets that sphere first, from outside; or it
    misses it and passes closest to it in front of whatever it meets. `curves`: also
    the intersection curves of spheres cutting into the one a ray meets
    (`curves.nearest_curve`), where they are nearer. `nonlinear`: also whether, at a
    hit of any segment (seen directly, in a mirror or through glass), a shadow edge or a
    terminator may cross the box or a highlight is narrow across it (as the segment's
    shading found them: `Shade.near`), or the rim of the sphere met lies within `RIM`
    boxes (`Best.nonlinear`): where the box's colour is far from linear across it,
    though no silhouette crosses it. `critical` (a `Critical`): also the boundary of
    total internal reflection where a ray leaves a glass sphere (`critical_terms`)."""

    def __init__(self, centers, radii, tmin, width: float, curves: bool = False, nonlinear: bool = False,
                 critical: "Critical | None" = None):
        self.centers, self.radii, self.tmin, self.width, self.curves = centers, radii, tmin, width, curves
        self.nonlinear, self.critical = nonlinear, critical

    def empty(self, rays) -> Best:
        """No edge found yet (the fold's start)."""
        n = rays.weight.shape
        none = jnp.full(n, -1, jnp.int32)
        nonlinear = jnp.zeros(n, bool) if self.nonlinear else None
        critical = None if self.critical is None else jnp.zeros(n, bool)
        return Best(jnp.full(n, jnp.inf, rays.o.dtype), none, rays, none, nonlinear, critical)

    def __call__(self, rays, hit: spheres.Hit, best: Best, near=None) -> Best:
        """`best` with this segment's nearest visible silhouette where it is nearer;
        `near` (with `nonlinear`): per hit, whether the shading found a light's shadow
        edge or terminator within `CROSSING` boxes of it or a narrow highlight there
        (`Shade.near`)."""
        n = self.centers.shape[0]
        tab = spheres.table(rays.o, rays.d, self.centers) if hit.table is None else hit.table
        sg = jax.lax.stop_gradient
        ox, dx, oy, dy = sg(tuple(rays.diff))
        t = -tab.b
        floor = jnp.asarray(tiny(t.dtype), t.dtype)
        r = sg(self.radii)[:, None]
        r2 = r**2
        # |sin g| ≤ |g| (1 where |g| ≥ π/2), g the outline cone's angular gap
        # (`outline_terms`), over a bound on g's rate per sample step,
        # |∂d| + |∂o|·(1 + r/q)/|f|: a lower bound of |δ|
        q = safe_sqrt(tab.f2 - r2, floor)  # the distance to the outline's tangent points
        l = safe_sqrt(tab.l2, floor)
        gap = jnp.where(l * r + t * q > 0, (l * q - t * r) / tab.f2, 1)
        moved = safe_sqrt(dot(ox, ox) + dot(oy, oy), floor)
        reach = safe_sqrt(dot(dx, dx) + dot(dy, dy), floor) + moved * (1 + r / q) / safe_sqrt(tab.f2, floor)
        k = jnp.arange(n)[:, None]
        outside = tab.f2 > r2
        is_hit = hit.index[None, :] == k
        inside_outline = (tab.l2 < r2) & (t > 0)  # within the outline's cone, ahead
        met = is_hit & hit.entering[None, :] & inside_outline
        passed = ~is_hit & ~inside_outline & (q > self.tmin) & (~hit.found[None, :] | (q < hit.t[None, :]))
        ok = (rays.weight > 0)[None, :] & outside & (rays.origin[None, :] != k) & (met | passed)
        edge = _candidates(gap, reach, ok, self.width)
        cc, rr = _chosen_or_regular(edge, rays.o, rays.d, self.centers, self.radii)
        delta = outline_terms(*sg((rays.o, rays.d, ox, dx, oy, dy, cc, rr)))[0]
        score = jnp.where((edge >= 0) & (jnp.abs(delta) < self.width), jnp.abs(delta), jnp.inf)
        edge = jnp.where(jnp.isfinite(score), edge, -1)
        critical = None if self.critical is None else jnp.zeros_like(edge, bool)
        here = Best(score, edge, rays, jnp.full_like(edge, -1), None, critical)
        if self.curves:
            cscore, cedge = curves.nearest_curve(rays.o, rays.d, rays.diff, rays.origin, rays.weight > 0, hit, tab,
                                                 self.centers, self.radii, self.width)
            here = here.nearer(cscore, cedge, hit.index, critical=False)
        if self.critical is not None:
            here = here.nearer(self.critical.score(rays, hit, self.centers, self.radii, self.width), hit.index, -1,
                               critical=True)
        better = checkpoint_name(here.score < best.score, spheres.CHOICE)
        chosen = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), here._replace(nonlinear=None),
                                        best._replace(nonlinear=None))
        if not self.nonlinear:
            return chosen
        rim = jnp.any(ok & met & (jnp.abs(gap) / reach < RIM * self.width), axis=0)  # a lower bound of |δ|, as above
        return chosen._replace(nonlinear=best.nonlinear | (near & hit.found & (rays.weight > 0)) | rim)


def critical_terms(o, d, df: Differentials, c, r, ior):
    """Signed distance δ (in sample steps) from rays inside a glass sphere (c, r) of index
    `ior` to the boundary of total internal reflection at their exit, positive on the
    reflecting side, and its normal (nx, ny) in the image.

    At the exit cos²θ = 1 − |l|²/r² (l: the ray's offset from the centre), so Snell's
    k = 1 − ior²(1 − cos²θ) crosses 0 where |l| = r/ior: the boundary is the cylinder of
    that radius around the ray, and |l| − r/ior (`edge_terms`) its distance. A ray that
    refracted into a lone sphere leaves it at its entry angle and never meets it
    (`Critical.score`); one that another sphere turned inside it, or the eye inside it,
    may."""
    delta, nx, ny, _, _ = edge_terms(o, d, *df, c, r / ior)
    return delta, nx, ny


class Critical(NamedTuple):
    """Where the silhouette mode watches for the boundary of total internal reflection
    (`EdgeWatch`): the glass spheres, their indices and the chain's depth (a ray at
    the last segment spawns no next one, so its exit has no such edge)."""

    glass: Bool[Array, " n"]
    ior: Float[Array, " n"]
    depth: int

    def score(self, rays, hit: spheres.Hit, centers, radii, width):
        """Per ray, |δ| to the boundary at this segment's exit from a glass sphere, where
        within `width` sample steps (else inf); not differentiated (it chooses)."""
        sg = jax.lax.stop_gradient
        k = jnp.maximum(hit.index, 0)
        # a chord keeps its angle with the surface at both ends: a ray that reached its exit
        # from the same sphere's surface (refracted in, or reflected inside) meets k as it
        # was there (≥ 0 refracted in from air: the boundary only a phantom at the rim)
        arrived = rays.origin != hit.index
        leaving = hit.found & ~hit.entering & self.glass[k] & arrived & (rays.weight > 0) & (rays.level < self.depth)
        c, r, ior = take_rows(sg(centers), k), lookup(sg(radii), k), lookup(sg(self.ior), k)
        delta = jnp.abs(critical_terms(*sg((rays.o, rays.d, rays.diff)), c, r, ior)[0])
        return jnp.where(leaving & (delta < width), delta, jnp.inf)


class Sides(NamedTuple):
    """Both sides of each pixel's chosen edge: rays through the centroids of the two
    parts of the pixel's box, and the fraction α on the edge sphere's side (at the
    boundary of total internal reflection, the side that refracts out)."""

    edge: Int[Array, " p"]
    alpha: Float[Array, " p"]
    x: Float[Array, " p"]  # the pixel centre's signed distance to the edge in box widths, > 0 inside
    o_in: Float[Array, "3 p"]
    d_in: Float[Array, "3 p"]
    o_out: Float[Array, "3 p"]
    d_out: Float[Array, "3 p"]


#: `both_sides`: how far past the edge, in box widths, each side is traced.
ACROSS = 0.05


def moved_rays(o, d, df: Differentials, sx, sy):
    """Rays (o, d) moved (sx, sy) sample steps in the image by their differentials `df`
    (sx, sy: scalars, or per ray through `spread`)."""
    return o + sx * df.ox + sy * df.oy, normalize(d + sx * df.dx + sy * df.dy)


def offset_rays(o, d, df: Differentials, z, width, nx, ny):
    """Rays (o, d) moved `z` box sides along an edge's inward normal −(nx, ny) in the
    image, by their differentials `df` (a box is `width` sample steps wide)."""
    return moved_rays(o, d, df, spread(-z * width * nx), spread(-z * width * ny))


def both_sides(best: Best, centers, radii, width) -> Sides:
    """The sided mode's sides: coverage α (differentiable in the scene) and the rays just
    inside and just outside the edge (`ACROSS` box widths from it) where it passes nearest
    to the pixel's centre, offset along the edge segment's ray differentials: the colours
    a pixel-centre sample takes when the edge moves across it."""
    r0 = best.rays
    c, r = _chosen_or_regular(best.edge, r0.o, r0.d, centers, radii)
    delta, nx, ny = outline_terms(r0.o, r0.d, *r0.diff, c, r)
    alpha, _, _ = split_box(-delta / width, nx, ny)
    # the edge lies at z = −x = δ/width along the inward normal
    z_in, z_out = delta / width + ACROSS, delta / width - ACROSS
    return Sides(best.edge, alpha, -delta / width, *offset_rays(r0.o, r0.d, r0.diff, z_in, width, nx, ny),
                 *offset_rays(r0.o, r0.d, r0.diff, z_out, width, nx, ny))


def _chosen_or_met(edge, o, d, centers, radii):
    """Centre and radius of each ray's chosen sphere; where none is chosen, a stand-in
    sphere the ray meets (a unit sphere 2 units ahead), so that the unused branch of
    `curves.curve_terms` has finite derivatives."""
    use = edge >= 0
    k = jnp.maximum(edge, 0)
    c = jnp.where(use, take_rows(centers, k), jax.lax.stop_gradient(o + 2 * d))
    r = jnp.where(use, lookup(radii, k), 1)
    return c, r


def primary_sides(best: Best, primary, centers, radii, width, ior=None) -> Sides:
    """The box mode's sides: coverage α and the rays through the centroids of the inside
    and outside parts of the pixel's box, taken from the eye: the primary rays (o, d,
    their differentials) moved by the centroids' offsets in the image.

    The offsets are the same in both, in sample steps; through a mirror or glass the
    rays from the eye follow their own paths to the edge's segment (differentials,
    shadows and hits of their own), where a pixel's centre and its sides may see
    different things (near a rim of a mirror or glass sphere the world is compressed
    into a sliver of the image)."""
    o, d, df = primary
    r0 = best.rays
    c, r = _chosen_or_regular(best.edge, r0.o, r0.d, centers, radii)
    delta, nx, ny = outline_terms(r0.o, r0.d, *r0.diff, c, r)
    curve = best.partner >= 0
    # an intersection curve: E and H where the ray meets both (else stand-ins it meets)
    met = jnp.where(curve, best.edge, -1)
    ce, re = _chosen_or_met(met, r0.o, r0.d, centers, radii)
    ch, rh = _chosen_or_met(jnp.where(curve, best.partner, -1), r0.o, r0.d, centers, radii)
    leaves_e, leaves_h = ((r0.origin == k) & (k >= 0) for k in (met, best.partner))
    cd, cx, cy = curves.curve_terms(r0.o, r0.d, r0.diff, ce, re, ch, rh, leaves_e, leaves_h)
    delta, nx, ny = (jnp.where(curve, a, b) for a, b in ((cd, delta), (cx, nx), (cy, ny)))
    if best.critical is not None:  # the boundary of total internal reflection: the edge sphere's exit
        td, tx, ty = critical_terms(r0.o, r0.d, r0.diff, c, r, lookup(ior, jnp.maximum(best.edge, 0)))
        delta, nx, ny = (jnp.where(best.critical, a, b) for a, b in ((td, delta), (tx, nx), (ty, ny)))
    alpha, z_in, z_out = split_box(-delta / width, nx, ny)
    return Sides(best.edge, alpha, -delta / width, *offset_rays(o, d, df, z_in, width, nx, ny),
                 *offset_rays(o, d, df, z_out, width, nx, ny))


class EdgeSamples(NamedTuple):
    """What the silhouette-aware trace of each sample gives (`trace.trace_edges`): its
    colour through the centre, its box-filtered colour, and both sides of its nearest
    silhouette and shadow edge.

    Colours are clamped to 0..255; inside the renderer they are (3, K) and a sample is a
    column, `rtjax.edge_samples` returns them as (K, 3). Without a silhouette within
    reach, blended = inside = outside = centre, alpha = 1 and x = 0; without a shadow
    edge within reach (and always in box mode), flipped = centre and shadow_x = inf."""

    centre: Float[Array, "3 k"]  # through the sample's centre: shadow edges box-filtered (box mode) or sharp (sided)
    blended: Float[Array, "3 k"]  # α·inside + (1 − α)·outside: in box mode, the sample's box-filtered colour
    inside: Float[Array, "3 k"]  # traced on the edge sphere's side of the silhouette
    outside: Float[Array, "3 k"]  # traced on its other side
    alpha: Float[Array, " k"]  # the fraction of the sample's box on the edge sphere's side
    x: Float[Array, " k"]  # the centre's signed distance to the silhouette in box widths, > 0 inside
    flipped: Float[Array, "3 k"]  # sided mode: the centre's colour across its nearest shadow edge
    shadow_x: Float[Array, " k"]  # sided mode: the centre's distance to that edge in box widths (≥ 0)
