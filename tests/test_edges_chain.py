"""The silhouette mode's derivatives inside mirrors and glass and where pixels hold several
edges (issue 21), against the supersampled finite differences of the independent float64
reference renderer.

Scenes (`edge_scenes.py`, 24–48 px): the issue's held-out-like scene (a floor, an
opaque sphere, a mirror and a glass sphere, one light, shadows on the floor), spheres
that cut into one another, a glass sphere of high index seen near its rim, a 32-px
image whose pixels hold several edges, three opaque spheres on a floor (outlines over
their own shadows), and the eye inside a glass sphere, where part of the view is
totally reflected (its boundary an edge). Parameters: centres and radii of every
sphere but the floor, and on the first scene the light's direction and the eye.

The yardstick, `tests/data/edges_yardstick.npz`, is made by `scripts/edges_yardstick.py`
(about 45 minutes): central differences of `rtjax.reference` box-filtered from 64 × 64
samples per pixel with a step of 0.04 px of image motion, and from 48 × 48 with 0.05 px
to confirm (the fine ones, asserted against), and the coarse ones of the issue's own
measurement (16 × 16 and 24 × 24 samples, 0.3 and 0.6 px), whose steps average the
derivative where edges crowd (inside glass: per-pixel cosines down to 0.69 against the
fine ones). Its images are checked against the reference here, so a stale file fails.
Compared: J = Σ w·image (fixed random weights w), its derivatives' cosine over the
parameters and their median relative error, and the derivative images' cosine per
parameter. docs/EDGES.md tabulates the figures.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from edge_derivatives import COARSE_KEYS, FINE_KEYS, compare, derivative_images, own_differences, yardsticks
from conftest import quick_xla
from edge_scenes import DECKS, FLOOR, SPP
from rtjax import reference


@functools.lru_cache(maxsize=None)
def mode(name: str):
    """The mode as `render` does it by default at these sizes: 16 × 16 sub-boxes where
    edges are (4 × 4 in the pixels an edge, a terminator or a narrow highlight may
    cross or near a rim, 4 × 4 again in their sub-boxes the same rule picks)."""
    return derivative_images(name, edges=1.0, subdivide=None)


@pytest.mark.parametrize("name", ["crowded"])
def test_yardstick_is_the_reference_of_these_scenes(name):
    """The stored supersampled image is the reference's for today's scene (not stale)."""
    frame = reference.parse_deck_text(DECKS[name][0])[0]
    image = reference.render_reference(frame, depth=DECKS[name][1], spp=SPP)
    np.testing.assert_allclose(yardsticks(name)["image"], image, atol=1e-3)


@pytest.mark.parametrize("name", list(DECKS))
def test_yardsticks_agree(name):
    """The yardsticks are converged: the fine ones (64 × 64 samples with a step of
    0.04 px, 48 × 48 with 0.05 px) agree in every derivative image and in sum; the
    coarse ones (16 × 16 and 24 × 24 samples, steps 0.3 and 0.6 px) agree in sum with
    the finest, though per pixel their steps average the derivative where edges crowd."""
    ys = yardsticks(name)
    finest, confirm = (ys[k] for k in FINE_KEYS)
    c = compare(confirm, finest, ys["names"])
    assert c.cosine > 0.999 and c.pixel_cosines.min() > 0.975, c.summary()
    for key in COARSE_KEYS:
        c = compare(ys[key], finest, ys["names"])
        assert c.cosine > 0.98, (key, c.summary())
        c = compare(ys[key], ys[COARSE_KEYS[0]], ys["names"])
        assert c.cosine > 0.99, (key, c.summary())


# (scene) → (cosine over the spheres' parameters ≥, median relative error ≤, per-pixel
# cosine ≥), asserted against both fine yardsticks: the figures measured, with a little
# room (docs/EDGES.md). With the default's 16 × 16 sub-boxes where edges are the issue's
# goals (0.99, 5 %, 0.98) are met on all five. Measured (16 × 16 with narrow highlights
# subdivided, since stop 60; 4 × 4 and one box at stop 58–59 in brackets):
GOALS = {
    "heldout": (0.9995, 0.05, 0.978),  # 0.9997, 3.4–4.0 %, 0.981 (eye z) (4 × 4: 0.9998, 2.8–2.9 %, 0.979; one box: 0.9973, 3.4–5.3 %, 0.821)
    "overlap": (0.9995, 0.03, 0.99),  # 0.9999, 1.7 %, 0.993 (glass) (4 × 4: 0.9964, 6.0–6.4 %, 0.955; one box: 0.9800, 13.8–16.2 %, 0.582)
    "tir": (0.9998, 0.025, 0.99),  # 0.9999, 1.0–1.3 %, 0.996 (4 × 4: 0.9998, 1.7–2.2 %, 0.991; one box: 0.9983, 11.0–11.3 %, 0.945)
    # since stop 64 (two shadow edges per footprint) 0.9995–0.9996, 2.8–3.3 %, 0.986: the
    # glass's rim pixels lost a cancellation that had put their sums within 1.5–1.6 %
    "crowded": (0.999, 0.035, 0.983),  # 0.9999, 1.5–1.6 %, 0.991 (glass x) (4 × 4: 0.9907, 19.6–20.2 %, 0.936; one box: 0.9891, 26.3–26.8 %, 0.742)
    "opaque": (0.9995, 0.03, 0.995),  # 1.0000, 0.6–1.4 %, 0.999 (4 × 4: 0.9997, 2.5–2.8 %, 0.997; one box: 0.9980, 7.8–8.8 %, 0.979)
    # since stop 63 (the boundary of total internal reflection an edge; before: −0.977, 71–80 %, 0.295)
    "inside": (0.9995, 0.02, 0.99),  # 1.0000, 0.3–1.1 %, 0.993 (one box: 1.0000, 4.4–4.6 %, 0.968)
}
# the same against the coarse yardsticks (the issue's own kind), whose per-pixel figures
# their steps bound: measured heldout 0.9971, 3.6–12.9 %, 0.794; overlap 0.9837,
# 2.5–2.8 %, 0.666; tir 0.9995, 2.5–4.1 %, 0.921; crowded 0.9991, 5.6–7.9 %, 0.860 (4.1–4.2 % before stop 64);
# opaque 0.9994, 1.5–5.5 %, 0.925; inside 1.0000, 1.5–2.5 %, 0.570
COARSE_GOALS = {
    "heldout": (0.996, 0.15, 0.78),
    "overlap": (0.98, 0.05, 0.65),
    "tir": (0.998, 0.06, 0.90),
    "crowded": (0.9985, 0.09, 0.84),
    "opaque": (0.999, 0.07, 0.91),
    "inside": (0.9995, 0.04, 0.55),
}
# the image's mean distance from the supersampled one (levels): measured heldout
# 0.253 one box, 0.067 4 × 4, 0.035 16 × 16; overlap 0.251, 0.089, 0.042; tir 0.195,
# 0.056, 0.021; crowded 0.576, 0.097, 0.036; opaque 0.190, 0.100, 0.027; inside 0.202
# one box, 0.044 16 × 16 (1.10 and 0.79 without the boundary of total internal reflection)
IMAGE_GOALS = {"heldout": 0.05, "overlap": 0.055, "tir": 0.035, "crowded": 0.05, "opaque": 0.04, "inside": 0.055}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(DECKS))
def test_derivatives_match_the_supersampled_reference(name):
    ys = yardsticks(name)
    image, jac = mode(name)
    assert np.abs(image - ys["image"]).mean() <= IMAGE_GOALS[name]
    for keys, goals in ((FINE_KEYS, GOALS), (COARSE_KEYS, COARSE_GOALS)):
        cos, rel, pix = goals[name]
        for key in keys:
            c = compare(jac, ys[key], ys["names"])
            assert c.cosine >= cos, (key, c.summary())
            assert c.median <= rel, (key, c.summary())
            assert c.pixel_cosines.min() >= pix, (key, c.summary())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["crowded", "overlap"])
def test_derivatives_are_the_images_own(name):
    """jacfwd of the mode is the derivative of the mode's own image: central differences
    of the same render, each parameter stepped by 10⁻⁶ px of image motion, agree in
    every pixel. Mirrors and glass stretch the world they show as they move, so the
    ray differentials past them (and an intersection curve's rate) carry the scene's
    derivatives: each pixel's distance to an edge, δ = gap/rate, moves with the rate
    wherever δ ≠ 0 (before they did, the mirror's and the glass sphere's summed
    derivatives were 7–673 % off their images' own on crowded)."""
    ys = yardsticks(name)
    image, jac = mode(name)
    fd = own_differences(name, 1e-6, subdivide=None)
    c = compare(jac, fd, ys["names"])
    assert np.all(c.relative < 1e-5), c.summary()
    for n, a, b in zip(ys["names"], jac, fd):
        assert np.abs(a - b).max() <= 1e-5 * np.abs(b).max(), n


# two opaque spheres cutting into one another, seen from the front: their intersection
# curve is an edge (`rtjax.curves`). Per-pixel cosine of jacfwd against the reference's
# finite difference (48 × 48 samples, 0.05 px) for (sphere, axis): measured 0.999, 0.997,
# 0.999, 0.998 with `render`'s default at 32 px (16 × 16 sub-boxes where edges are);
# 4 × 4 0.996, 0.987, 0.999, 0.996. Against 16 × 16 samples at 0.3 px (the yardstick
# until stop 59, whose step averages the derivative where edges crowd): 0.967, 0.942,
# 0.988, 0.957 (16 × 16), 0.973, 0.964, 0.987, 0.962 (4 × 4); one box 0.959, 0.968,
# 0.985, 0.948 (with the depth difference t_E − t_H for the curve's distance 0.934,
# 0.960, 0.983, 0.938; without the curves 0.827, 0.561, 0.976, 0.846)
CUTTING = ("sphe -4 0 0 8\nopaq 0.9 0.5 0.2 0.4 10\nsphe 6 -3 1 7\nopaq 0.3 0.7 0.9 0.4 10\n"
           "plig 0.5 -0.4 1 180 170 160\nelig 0.15\nback 30 40 90\neyep 0 -100 10\nrefp 0 0 0\nvang 20 20\n"
           "size 32\nrend x.ras\n")


def depth0_cosine(deck: str, k: int, axis: int, step: float, spp: int) -> float:
    """Cosine between the mode's derivative image (jacfwd of `render`, depth 0) against
    sphere k's centre (axis 0–2) or radius (axis 3) and the reference's central
    difference (±`step` pixel footprints at the look-at point's distance, `spp` × `spp`
    samples a pixel)."""
    import copy

    import jax
    import jax.numpy as jnp

    import rtjax

    s = rtjax.parse_deck(deck).frames[0].scene.astype(jnp.float64)
    frame = reference.parse_deck_text(deck)[0]
    p = s.params
    h = step * float(jnp.linalg.norm(p.refp - p.eye)) * 2 * np.tan(np.radians(float(p.vang[0])) / 2) / s.structure.width

    def moved(e):
        f = copy.deepcopy(frame)
        if axis == 3:
            f.spheres[k]["r"] += e
        else:
            f.spheres[k]["center"][axis] += e
        return reference.render_reference(f, depth=0, spp=spp)

    fd = (moved(h) - moved(-h)) / (2 * h)

    def image(t):
        c = s.params.centers.at[k, axis].add(t) if axis < 3 else s.params.centers
        r = s.params.radii.at[k].add(t) if axis == 3 else s.params.radii
        return rtjax.render(s.replace(centers=c, radii=r), edges=1.0, depth=0)

    jac = np.asarray(jax.jacfwd(image)(0.0))
    return float(np.sum(jac * fd) / (np.linalg.norm(jac) * np.linalg.norm(fd)))


@pytest.mark.slow
@pytest.mark.parametrize("k, axis, floor", [(1, 0, 0.995), (1, 1, 0.993), (0, 2, 0.995), (1, 3, 0.995)])
def test_intersection_curves_are_edges(k, axis, floor):
    cos = depth0_cosine(CUTTING, k, axis, 0.05, spp=48)
    assert cos >= floor, cos


# a glass ball shadowing an opaque one (fresh11 of docs/MEASUREMENTS.md, stop 64, at depth
# 0 and 40 px): where the ball's shadow cylinder grazes the opaque sphere, the two
# shadows' edges on the floor run a fraction of a sub-box apart. Per-pixel cosine of
# jacfwd (`render`'s default, 16 × 16 sub-boxes) against the reference's central
# difference (32 × 32 samples, 0.05 px) for the opaque sphere's (axis): measured 0.9981,
# 0.9982, 0.9992 with both edges box-filtered; 0.9912, 0.9858, 0.9919 with the nearer
# one alone (the other's shadow hard, its motion lost)
SHADOWED = FLOOR + ("sphe -2 -4 -2 5\ntrpa 0.9 1.4 0.1 10\nsphe 3 6 -10 5\nopaq 0.8 0.7 0.6 0.3 10\n"
                    "plig -0.4 -0.8 0.65 190 190 190\nelig 0.12\nback 40 50 70\neyep 20 -70 20\nrefp 0 0 -6\n"
                    "vang 30 30\nsize 40\nrend x.ras\n")


@pytest.mark.slow
@pytest.mark.parametrize("axis, floor", [(0, 0.996), (1, 0.996), (3, 0.997)])
def test_two_shadow_edges_in_one_box(axis, floor):
    cos = depth0_cosine(SHADOWED, 2, axis, 0.05, spp=32)
    assert cos >= floor, cos


# The edge of a box seen in a mirror and through a glass ball's rim (fresh5 of
# docs/MEASUREMENTS.md, stop 62; the spheres in heldout's order, so its structure): at a
# rim the side of the edge, traced from the eye, leaves the glass in another direction
# than the box's ray, away from the floor whose outline is the box's edge. Forced to
# meet the floor, it met it at its closest point behind its origin, and that point's
# shading (a soft shadow over a footprint hundreds of times the box's) took 77 of the
# pixel's derivative against the mirror's y, which the reference puts at about 5.
RIM = FLOOR + (
    "sphe 9 -4 -11 3.5\nopaq 0.9 0.8 0.1 0.3 10\nsphe 0 8 -7 7\nmirr\nsphe -2 -6 -10 4\ntrpa 0.8 1.45 0.3 20\n"
    "plig -0.3 -0.5 1 190 180 170\nelig 0.2\nback 20 20 40\neyep 0 -60 60\nrefp 0 0 -9\nvang 30 30\nsize 36\n"
    "rend x.ras\n")


@pytest.mark.slow
def test_an_edge_seen_through_a_glass_rim_has_sides_that_see_the_scene():
    """A 1/16-px box (a second-level sub-box of the pixel in column 17, row 16) whose
    edge, the floor's outline, lies in the mirror seen through the glass ball's rim: its
    colour and its derivative against the mirror's y as the reference's 64 × 64 samples
    of the box give them (its central differences at ±0.005 units: −19; at ±0.01: −32,
    the sampled band's noise), not those of a point behind the side's ray."""
    import copy

    import jax
    import jax.numpy as jnp

    import rtjax

    s = rtjax.parse_deck(RIM).frames[0].scene.astype(jnp.float64)
    k = 16
    corner = np.array([17 + 2 / k, 16 + 7 / k])

    def colour(t):
        c = s.params.centers.at[2, 1].add(t)
        return rtjax.render_samples(s.replace(centers=c), (corner + 0.5 / k)[None], step=1 / k, edges=1.0, depth=6)[0]

    with quick_xla(clear=True):  # a tolerance check (conftest.quick_xla)
        value, slope = (np.asarray(a) for a in jax.jvp(colour, (0.0,), (1.0,)))

    frame = reference.parse_deck_text(RIM)[0]
    grid = corner + np.stack(np.meshgrid(*[(np.arange(64) + 0.5) / 64 / k] * 2), -1).reshape(-1, 2)

    def box(e):
        f = copy.deepcopy(frame)
        f.spheres[2]["center"][1] += e
        return reference.render_positions(f, grid, depth=6).mean(0)

    np.testing.assert_allclose(value, box(0.0), atol=0.1)
    np.testing.assert_allclose(slope, (box(0.005) - box(-0.005)) / 0.01, atol=40)  # the point behind: 21,749


@pytest.mark.slow
def test_the_index_of_refraction_moves_the_boundary_of_total_internal_reflection():
    """With the eye inside a glass sphere (`inside`), the index n moves the boundary of
    total internal reflection (rays more than r/n from the centre are reflected) across
    the image: the derivative of J = Σ w·image with respect to n against central
    differences (±0.003) of the reference's 16 × 16 samples a pixel. Measured −215,729
    against −216,541 (32 × 32 samples: −215,820); before the boundary was an edge of
    the mode, +9,817."""
    import copy

    import jax
    import jax.numpy as jnp

    import rtjax

    text, depth = DECKS["inside"]
    s = rtjax.parse_deck(text).frames[0].scene.astype(jnp.float64)
    w = np.random.default_rng(1).uniform(size=(s.structure.height, s.structure.width, 3))

    def weighted(t):
        return jnp.sum(w * rtjax.render(s.replace(ior=s.params.ior.at[1].add(t)), depth=depth, edges=1.0))

    with quick_xla(clear=True):  # a tolerance check (conftest.quick_xla)
        slope = float(jax.jvp(weighted, (0.0,), (1.0,))[1])

    frame = reference.parse_deck_text(text)[0]

    def reference_weighted(dn):
        f = copy.deepcopy(frame)
        f.spheres[1]["n"] += dn
        return np.sum(w * reference.render_reference(f, depth=depth, spp=16))

    truth = (reference_weighted(0.003) - reference_weighted(-0.003)) / 0.006
    assert abs(slope - truth) <= 0.02 * abs(truth), (slope, truth)
