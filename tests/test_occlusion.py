"""Sky occlusion (rtjax.occlusion): the form factor against Monte Carlo integration and
its closed-form limits; a floor pixel's ambient term beside a ball against the sky
share a NumPy Monte Carlo finds from the same point; no occlusion (None) against zero
weights; derivatives against central differences in float64."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import first_hits, quick_xla

import rtjax
from rtjax.occlusion import form_factor

#: A floor (sphere 0, top at z = 0) with a ball resting on it, lit from above and the
#: side; 24 × 18 pixels looking down at the ball's foot.
DECK = """sphe 0 0 -1000 1000
opaq 0.8 0.7 0.6 0 1
sphe 0 0 2 2
opaq 0.2 0.4 0.9 0 1
plig 1 -0.5 2 200 180 160
elig 0.4
back 30 40 50
eyep 3 -9 7
refp 0.5 0 0.5
vang 40 30
size 24
rend x.ras
"""


def scene() -> rtjax.Scene:
    return rtjax.parse_deck(DECK).frames[0].scene


def monte_carlo_hidden(point, normal, centers, radii, weights, count=200_000, seed=0) -> float:
    """Σ_j w_j · (share of cosine-weighted directions from `point` about `normal` whose
    ray meets sphere j in front of it): the weighted hidden share, sampled."""
    rng = np.random.default_rng(seed)
    u = rng.random((count, 2))
    r, phi = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u[:, 0])], 1)
    a = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    dirs = local @ np.stack([a, np.cross(normal, a), normal])
    total = 0.0
    for c, rad, w in zip(centers, radii, weights):
        oc = np.asarray(c) - point
        b = dirs @ oc
        disc = b * b - (oc @ oc - rad * rad)
        total += w * np.mean((disc > 0) & (b - np.sqrt(np.maximum(disc, 0)) > 0))  # the near root in front
    return total


@pytest.mark.parametrize("cos_t, sin2_s", [(1.0, 0.1), (0.6, 0.3), (0.3, 0.3), (0.0, 0.5), (-0.4, 0.6), (-0.9, 0.5), (0.2, 0.999)])
def test_form_factor_is_the_covered_share_of_the_hemisphere(cos_t, sin2_s):
    """A sphere at angle θ from the normal subtending σ: the sampled share of
    cosine-weighted directions that meet it, in and past the horizon-clipped range."""
    d = 10.0
    centre = d * np.array([np.sqrt(1 - cos_t**2), 0, cos_t])
    sampled = monte_carlo_hidden(np.zeros(3), np.array([0, 0, 1.0]), [centre], [d * np.sqrt(sin2_s)], [1.0], count=400_000)
    got = float(form_factor(jnp.asarray(cos_t, jnp.float64), jnp.asarray(sin2_s, jnp.float64)))
    assert abs(got - sampled) < 3e-3, (got, sampled)


def test_form_factor_limits():
    """Wholly above the horizon: cos θ·sin²σ. A sphere as large as a plane (σ → 90°):
    (1 + cos θ)/2, the share of the hemisphere below a plane. Below the horizon: 0."""
    c = np.linspace(-1, 1, 41)
    s2 = 0.2
    above = c * c > s2
    got = np.asarray(form_factor(jnp.asarray(c), jnp.asarray(s2, jnp.float64)))
    np.testing.assert_allclose(got[above & (c > 0)], c[above & (c > 0)] * s2, rtol=1e-12)
    assert np.all(got[above & (c < 0)] == 0)
    plane = np.asarray(form_factor(jnp.asarray(c[1:-1]), jnp.asarray(1 - 1e-9, jnp.float64)))
    np.testing.assert_allclose(plane, (1 + c[1:-1]) / 2, atol=1e-4)


def test_floor_beside_a_ball_sees_less_sky():
    """Every floor pixel: the rendered ambient loss ke·(1 − V)·d·L (the image without
    occlusion minus the image with it, the ball's weight 1, the floor's 0) against
    ke·(1 − V)·d·L with 1 − V sampled by Monte Carlo from the pixel's own hit point; the
    ball's pixels keep their colour (the floor does not occlude); None equals zero
    weights bit for bit."""
    s = scene().astype(jnp.float64)
    p = s.params
    plain = np.asarray(rtjax.render(s))
    occluded = np.asarray(rtjax.render(s.replace(occlusion=np.array([0.0, 1.0]))))
    assert np.array_equal(np.asarray(rtjax.render(s.replace(occlusion=np.zeros(2)))), plain)
    centers, radii = np.asarray(p.centers), np.asarray(p.radii)
    index, points, normals = first_hits(s)
    ambient = 0.4 * np.array([0.8, 0.7, 0.6]) * np.array([200, 180, 160])
    checked = 0
    for k, (row, col) in enumerate(np.ndindex(*index.shape)):
        loss = plain[row, col] - occluded[row, col]
        if index[row, col] == 1:  # the ball: the floor is no occluder
            np.testing.assert_array_equal(loss, 0)
            continue
        if index[row, col] != 0 or plain[row, col].max() >= 255:
            continue
        hidden = monte_carlo_hidden(points[row, col], normals[row, col], centers[1:], radii[1:], [1.0], count=100_000, seed=k)
        np.testing.assert_allclose(loss, ambient * hidden, atol=0.01 * ambient.max() + 1e-9, err_msg=f"pixel {row, col}")
        checked += hidden > 0.01
    assert checked >= 20  # pixels near the ball's foot, where the term matters


@pytest.mark.parametrize("edges", [0.0, 1.0])
def test_derivatives_with_occlusion_equal_central_differences(edges):
    """d/dt Σ w·image along a random direction of the ball's centre and radius and of the
    occlusion weights (float64): what occlusion adds to the derivative against what it
    adds to central differences (the image's kinks, at terminators and, in the
    silhouette-aware mode, its edges' model, part the two already without occlusion);
    in plain mode, reverse mode equals forward mode."""
    rng = np.random.default_rng(1)
    weights = jnp.asarray(rng.standard_normal((18, 24, 3)))
    dc, dr, dw = rng.standard_normal(3), rng.standard_normal(), rng.standard_normal(2)

    def derivatives(occlusion):
        s = scene().astype(jnp.float64).replace(occlusion=occlusion)

        def f(t):
            p = s.params
            moved = s.replace(centers=p.centers.at[1].add(t * dc), radii=p.radii.at[1].add(t * dr),
                              occlusion=None if occlusion is None else p.occlusion + t * dw)
            return jnp.sum(weights * rtjax.render(moved, edges=edges))

        with quick_xla():  # a tolerance check (conftest.quick_xla); these programs are compiled only here
            _, jvp = jax.jvp(f, (0.0,), (1.0,))
            if not edges:  # the mode's reverse mode is checked against its forward mode in test_reverse
                assert float(jax.grad(f)(0.0)) == pytest.approx(float(jvp), rel=1e-9)
        h = 1e-6
        return float(jvp), float((f(h) - f(-h)) / (2 * h))

    jvp, fd = derivatives(np.array([0.3, 0.9]))
    base_jvp, base_fd = derivatives(None)
    jvp, fd = jvp - base_jvp, fd - base_fd
    assert abs(fd) > 1 and abs(jvp - fd) <= 2e-5 * abs(fd), (jvp, fd)


def test_a_ball_resting_on_the_floor_has_finite_derivatives_in_float32():
    """The floor's points where the ball rests on it lie, in float32, on its surface or
    within rounding inside it (sin²σ = 1): the image and its gradient in every
    parameter stay finite (the sky share is the same function in every mode)."""
    s = scene().replace(occlusion=np.ones(2))
    assert s.params.centers.dtype == jnp.float32

    def f(p):
        return rtjax.render(rtjax.Scene(s.structure, p))

    image = f(s.params)
    grads = jax.grad(lambda p: jnp.sum(f(p)))(s.params)
    assert bool(jnp.all(jnp.isfinite(image)))
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
    assert float(jnp.sum(grads.occlusion ** 2)) > 0


def test_only_hits_seen_directly_are_occluded():
    """A mirror beside the ball: the pixels whose ray meets the mirror first keep their
    colour with occlusion on (the floor seen in it keeps the full ambient term), while
    floor pixels seen directly near the ball darken."""
    s = rtjax.parse_deck(DECK.replace("rend x.ras", "sphe 4.5 1 2 2\nmirr\nrend x.ras")).frames[0].scene
    s = s.astype(jnp.float64)
    assert s.structure.kinds == ("opaq", "opaq", "mirr")
    plain = np.asarray(rtjax.render(s))
    occluded = np.asarray(rtjax.render(s.replace(occlusion=np.array([0.0, 1.0, 1.0]))))
    first, _, _ = first_hits(s)
    assert (first == 2).sum() >= 10
    np.testing.assert_array_equal(occluded[first == 2], plain[first == 2])
    assert (plain - occluded)[first == 0].max() > 5
