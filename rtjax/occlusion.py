"""Sky occlusion: how much of the sky (the ambient light's source) the spheres hide from a
surface point.

The assignment's ambient term ke·d·L lights every point as if the whole sky saw it. A
photograph's sky light does not reach the floor under a ball or the gap between two
balls: the contact shadows a photo shows around every sphere, which a model without
them reads as geometry (docs/FITTING.md). With `Params.occlusion` set (one weight per
sphere; `None`, the default, leaves the assignment's shading and adds no code), the
ambient term of a hit seen directly (not in a mirror or through glass:
`trace.primary_sky`) becomes ke·V·d·L with

    V = clip(1 − Σ_j w_j·F_j, 0, 1),

F_j the cosine-weighted share of the hemisphere above the hit that sphere j covers (its
form factor, horizon-clipped; the sphere hit is left out) and w_j its weight: 1 for an
occluder that sends back nothing, less for one that reflects sky light on (a floor,
say, whose weight 0 leaves it out). Overlapping occluders count twice (hence the clip).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .numerics import components

#: Inside this of the horizon-clipped branch's ends (y = ±1), arccos and √(1 − y²) keep
#: finite derivatives; the form factor changes there by ~1e-7 of a hemisphere.
_EDGE = 1e-7


def form_factor(cos_t, sin2_s):
    """The cosine-weighted share of the hemisphere about a normal that a sphere covers,
    seen at angle θ from the normal (cos θ) and subtending half-angle σ (sin²σ < 1): cos θ·sin²σ
    when the sphere lies wholly above the horizon, else the horizon-clipped closed form
    (Lagarde & de Rousiers, "Moving Frostbite to PBR", 2014: a sphere light's
    illuminance, divided by π). Continuous in both arguments, finite derivatives."""
    above = cos_t * cos_t > sin2_s
    c = jnp.where(above, 0, cos_t)  # the clipped branch on safe values where it is not used
    sin_t = jnp.sqrt(jnp.maximum(1 - c * c, _EDGE))
    x = jnp.sqrt(1 / sin2_s - 1)
    y = jnp.clip(-x * c / sin_t, -1 + _EDGE, 1 - _EDGE)
    rim = sin_t * jnp.sqrt(1 - y * y)
    clipped = ((c * jnp.arccos(y) - x * rim) * sin2_s + jnp.arctan2(rim, x)) / jnp.pi
    return jnp.where(above, sin2_s * jnp.maximum(cos_t, 0), jnp.maximum(clipped, 0))


def sky_visibility(
    point: Float[Array, "3 p"],
    normal: Float[Array, "3 p"],
    index: Int[Array, " p"],
    centers: Float[Array, "n 3"],
    radii: Float[Array, " n"],
    weights: Float[Array, " n"],
) -> Float[Array, " p"]:
    """V = clip(1 − Σ_j w_j·F_j, 0, 1) at each hit `point` with outward unit `normal`,
    the sphere hit (`index`) left out: the share of the ambient light that reaches it.
    Every ray against every sphere (N·P form factors)."""
    p0, p1, p2 = components(point)
    n0, n1, n2 = components(normal)
    w0, w1, w2 = (centers[:, k, None] - q[None] for k, q in enumerate((p0, p1, p2)))  # (N, P) toward each centre
    d2 = w0 * w0 + w1 * w1 + w2 * w2
    # sin²σ below 1 (a hit on or inside another sphere, or within rounding of it, as a
    # floor's point where a ball rests on it is in float32): its sky hidden as if
    # just outside, and the clipped branch's derivatives finite
    d2 = jnp.where(d2 > 0, d2, 1)  # 0 only for a hit at a centre, where no sphere is left out
    sin2_s = jnp.minimum(radii[:, None] ** 2 / d2, 1 - _EDGE)
    cos_t = (n0[None] * w0 + n1[None] * w1 + n2[None] * w2) / jnp.sqrt(d2)
    own = jnp.arange(centers.shape[0])[:, None] == index[None]
    weights = jnp.broadcast_to(weights, radii.shape)
    hidden = jnp.sum(jnp.where(own, 0, weights[:, None] * form_factor(cos_t, sin2_s)), 0)
    return jnp.clip(1 - hidden, 0, 1)
