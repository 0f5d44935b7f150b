"""The assignment's shading formulas (DECK.md §3), term for term.

Per hit, with N the unit normal facing the incoming ray, V toward where the ray came
from, L the unit light vector, R_L = 2(N·L)N − L and cos γ = R_L·V (Phong):

    opaque:       I = Σ ke·d·L + S·[(1 − ke)·max(N·L, 0)·d·L + ks·L·max(cos γ, 0)^β·[N·L > 0]]
    transparent:  I = Σ S·ks·L·max(cos γ, 0)^β·[N·L > 0]  + kt·T     (T: the next ray)
    mirror:       I = R                                              (R: the next ray)

One formula serves all three: a transparent sphere is an opaque one with d = 0, and a
mirror one with d = 0 and ks = 0; what follows the hit (T, R) is the tracer's business.

Beyond the assignment, for photographs (`Params.fresnel`): glass met from outside
reflects a colour E with Fresnel's reflectance F and passes the rest,
I = F·E + (1 − F)·(its transparent I) (`fresnel_reflectance`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .numerics import dot, safe_pow, spread


def phong_angles(n: Float[Array, "3 p"], v: Float[Array, "3 p"], light: Float[Array, " 3"]):
    """N·L and cos γ = R_L·V for every ray, for one light, each (P,)."""
    nl = dot(n, light[:, None])
    r_l = spread(2 * nl) * n - light[:, None]
    return nl, dot(r_l, v)


def local_light(
    d: Float[Array, "3 p"],
    ks: Float[Array, " p"],
    beta: Float[Array, " p"],
    ke: Float[Array, ""],
    nl: Float[Array, " p"],
    cos_g: Float[Array, " p"],
    visibility: Float[Array, " p"],
    light_color: Float[Array, " 3"],
    sky: Float[Array, " p"] | None = None,
) -> Float[Array, "3 p"]:
    """One light's term: ke·d·L + S·[(1 − ke)·max(N·L, 0)·d·L + ks·L·max(cos γ, 0)^β·[N·L > 0]];
    with `sky` (the share of the sky each hit sees, `rtjax.occlusion`) the ambient part
    is ke·sky·d·L."""
    diffuse = (1 - ke) * jnp.maximum(nl, 0)
    specular = jnp.where(nl > 0, ks * safe_pow(cos_g, beta), 0)
    ambient = ke if sky is None else ke * sky
    return (spread(ambient + visibility * diffuse) * d + spread(visibility * specular)) * light_color[:, None]


def fresnel_reflectance(ior: Float[Array, " p"], cos_i: Float[Array, " p"]) -> Float[Array, " p"]:
    """Fresnel's reflectance of a surface of index `ior` in air at incidence cos θ,
    Schlick's approximation F0 + (1 − F0)(1 − cos θ)^5 with F0 = ((n − 1)/(n + 1))²: what
    a glass ball reflects, nearly all of it at its rim, where photographs show it."""
    f0 = ((ior - 1) / (ior + 1)) ** 2
    return f0 + (1 - f0) * (1 - jnp.clip(cos_i, 0, 1)) ** 5
