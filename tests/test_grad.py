"""Gradient checks (issue 3, "Derivatives you can trust"): for every parameter family of
`rtjax.Params` (textures: tests/test_textures.py), the float64 derivative of a plain
(pixel-centre) render in forward mode (jvp; one-hot tangents, i.e. jacfwd's columns) and
reverse mode (vjp, i.e. grad of a weighted image sum) against central finite
differences, on small images of three scenes: opaque spheres with highlights, a cast
shadow and two lights; a mirror; a glass sphere. Plus float32 against float64 images.

Away from silhouettes: a pixel-centre render is piecewise smooth, and its derivative
leaves out what jumps across a pixel centre (edges: tests/test_edges.py). The points
below are generic and the steps tiny (1e-6 relative); each test first checks that the
difference quotient is the same at h and h/10, which it is not when an edge (or a kink:
a terminator, a highlight's cut-off, clamping) sits within h of a pixel centre.

Compile cost: one jitted function per scene structure (`_derivatives`), shared by all
the families of that scene (the tangent batch has the same shape for each family). The
checks are tolerances and the compile is most of their cost: the module runs under
XLA's quick build (`conftest.quick_build`, which says why that checks the same program).
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rtjax

from conftest import SCENES

pytestmark = pytest.mark.usefixtures("quick_build")

FAMILIES = ("centers", "radii", "diffuse", "ks", "beta", "kt", "ior", "light_dirs", "light_colors", "background", "ke", "eye", "refp", "vang")

# A generic camera (no symmetry puts an edge on a pixel centre); 24 × 18 pixels.
CAMERA = "eyep 6 -60 9\nrefp 0.5 0 0.3\nvang 40 30\nsize 24\nrend x.ras\n"

DECKS = {
    # opaque spheres: highlights (ks, β), the small sphere's shadow on the big one, two lights
    "opaque": (
        "sphe 0 0 0 10\nopaq 0.9 0.6 0.3 0.5 12\n"
        "sphe -7 -13 7 4\nopaq 0.3 0.7 0.9 0.35 6\n"
        "plig -0.7 -1.2 0.9 150 140 130\nplig 1 -0.6 0.4 70 80 100\n"
        "back 20 30 60\nelig 0.15\n",
        0,
    ),
    # a mirror showing a floor (a huge sphere), spheres in front of it and one behind the
    # camera, seen only in the mirror
    "mirror": (
        "sphe 0 0 0 14\nmirr\n"
        "sphe 11 -19 9 5\nopaq 0.8 0.3 0.2 0.4 8\n"
        "sphe -14 -12 -8 4\nopaq 0.2 0.6 0.9 0.2 5\n"
        "sphe -25 -80 20 20\nopaq 0.3 0.9 0.4 0.2 5\n"
        "sphe 0 0 -1017 1000\nopaq 0.7 0.7 0.6 0 1\n"
        "plig -0.5 -1 0.8 120 110 100\nplig 0.4 0.6 0.5 90 100 110\n"
        "back 20 30 60\nelig 0.2\n",
        3,
    ),
    # a glass sphere (kt, n, its own highlight) in front of an opaque one
    "glass": (
        "sphe 0 -12 0 7\ntrpa 0.8 1.4 0.3 9\n"
        "sphe 2 14 1 13\nopaq 0.9 0.7 0.2 0.3 7\n"
        "plig -0.5 -1 0.8 160 150 140\nplig 0.8 -0.3 0.3 60 60 80\n"
        "back 20 30 60\nelig 0.2\n",
        4,
    ),
}

#: Families that no sphere of the scene uses: their derivative must be exactly zero.
UNUSED = {"opaque": {"kt", "ior"}, "mirror": {"kt", "ior"}, "glass": set()}

#: Per-sphere material entries that a kind ignores (Params: they get zero gradient).
IGNORED_BY = {"diffuse": ("mirr", "trpa"), "ks": ("mirr",), "beta": ("mirr",), "kt": ("opaq", "mirr"), "ior": ("opaq", "mirr")}

REL_STEP = 1e-6  # central difference step, relative to max(1, |x|)
TOL = 1e-5  # relative to the largest |derivative| of the family (measured: ≤ 4e-7)


@functools.lru_cache(maxsize=None)
def scene(name: str) -> rtjax.Scene:
    text, _ = DECKS[name]
    return rtjax.parse_deck(text + CAMERA).frames[0].scene.astype(jnp.float64)


def _with(params: rtjax.Params, **leaves) -> rtjax.Params:
    fields = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    fields.update(leaves)
    return rtjax.Params(**fields)


@functools.partial(jax.jit, static_argnames=("structure", "depth"))
def _derivatives(params, tangents, cotangents, structure, depth):
    """The image; J·t for a batch of tangents (one-hot: columns of jax.jacfwd); Jᵀ·c for
    a batch of cotangents (the first is uniform: jax.grad of the image's mean). Both
    from one linearisation (the JVP rules' tangent equations, and their transpose: what
    `jax.vjp` does), one program for both modes."""

    def f(p):
        return rtjax.render(rtjax.Scene(structure, p), depth=depth)

    image, linear = jax.linearize(f, params)
    pullback = jax.linear_transpose(linear, params)
    return image, jax.vmap(linear)(tangents), jax.vmap(lambda c: pullback(c)[0])(cotangents)


def _one_hot(params: rtjax.Params, family: str, count: int) -> rtjax.Params:
    """`count` tangents (a batch): the first size(family) are the family's unit vectors,
    the rest zero. `count` is the same for every family of a scene: one compilation."""
    zeros = jax.tree_util.tree_map(lambda a: jnp.zeros((count,) + a.shape, a.dtype), params)
    leaf = getattr(params, family)
    basis = jnp.eye(count, leaf.size, dtype=leaf.dtype).reshape((count,) + leaf.shape)
    return _with(zeros, **{family: basis})


@functools.lru_cache(maxsize=None)
def _cotangents(name: str) -> jax.Array:
    s = scene(name).structure
    shape = (s.height, s.width, 3)
    uniform = jnp.full(shape, 1 / np.prod(shape), jnp.float64)
    random = jax.random.normal(jax.random.key(3), (2,) + shape, jnp.float64)
    return jnp.concatenate([uniform[None], random])


def _central_differences(name: str, family: str, rel: float) -> np.ndarray:
    """(size(family), H, W, 3): ∂image/∂x_i by central differences, step rel·max(1, |x_i|)."""
    s = scene(name)
    depth = DECKS[name][1]
    x = np.asarray(getattr(s.params, family), np.float64)
    columns = []
    for i in range(x.size):
        h = rel * max(1.0, abs(x.flat[i]))
        plus, minus = x.copy(), x.copy()
        plus.flat[i] += h
        minus.flat[i] -= h
        up = np.asarray(rtjax.render(s.replace(**{family: plus}), depth=depth))
        down = np.asarray(rtjax.render(s.replace(**{family: minus}), depth=depth))
        columns.append((up - down) / (2 * h))
    return np.stack(columns)


CASES = [(name, family) for name in DECKS for family in FAMILIES]


@pytest.mark.slow
@pytest.mark.parametrize("name, family", CASES, ids=[f"{n}-{f}" for n, f in CASES])
def test_derivative_matches_central_differences(name, family):
    s = scene(name)
    depth = DECKS[name][1]
    count = max(getattr(s.params, f).size for f in FAMILIES)
    cot = _cotangents(name)
    image, jvps, grads = _derivatives(s.params, _one_hot(s.params, family, count), cot, s.structure, depth)
    assert np.all(np.isfinite(np.asarray(image)))
    n = getattr(s.params, family).size
    forward = np.asarray(jvps)[:n]  # (n, H, W, 3)
    reverse = np.asarray(getattr(grads, family)).reshape(len(cot), n)  # (cotangents, n)

    fd = _central_differences(name, family, REL_STEP)
    scale = np.abs(fd).max()

    if family in UNUSED[name]:
        assert scale == 0 and not forward.any() and not reverse.any(), "an unused family has a derivative"
        return
    assert scale > 0.1, f"{family} hardly changes the image (max |∂image| = {scale:.3g}): the scene does not exercise it"

    # away from edges and kinks: the difference quotient does not depend on the step
    fd10 = _central_differences(name, family, REL_STEP / 10)
    assert np.abs(fd - fd10).max() <= TOL * scale, "finite differences unstable: an edge or kink within the step"

    # forward mode: every column of the Jacobian
    np.testing.assert_allclose(forward, fd, rtol=0, atol=TOL * scale, err_msg=f"jvp ({family})")

    # reverse mode: Jᵀ·c against c·(finite-difference Jacobian), for each cotangent
    expected = np.einsum("khwc,nhwc->kn", np.asarray(cot), fd)
    for k in range(len(cot)):
        np.testing.assert_allclose(reverse[k], expected[k], rtol=0, atol=TOL * np.abs(expected[k]).max() + 1e-12, err_msg=f"vjp {k} ({family})")

    # entries a sphere's kind ignores (a mirror's colour, an opaque sphere's n, ...): zero
    if family in IGNORED_BY:
        ignored = np.array([k in IGNORED_BY[family] for k in s.structure.kinds])
        shape = getattr(s.params, family).shape
        f_cols = forward.reshape(shape + forward.shape[1:])[ignored]
        r_cols = reverse.reshape((len(cot),) + shape)[:, ignored]
        assert not f_cols.any() and not r_cols.any(), "an entry that the sphere's kind ignores has a derivative"


def test_fresnel_derivatives_match_central_differences():
    """The glass scene with `Params.fresnel` (glass reflecting a colour by Fresnel's law):
    d/dt Σ w·image along a random direction of the glass sphere's centre, its index and
    the reflected colour, forward mode against central differences at two steps, reverse
    mode against forward mode (float64)."""
    s = scene("glass").replace(fresnel=np.array([70.0, 90.0, 120.0]))
    depth = DECKS["glass"][1]
    rng = np.random.default_rng(5)
    w = jnp.asarray(rng.standard_normal((s.structure.height, s.structure.width, 3)))
    dc, dn, de = rng.standard_normal(3), rng.standard_normal(), rng.standard_normal(3)

    def f(t):
        p = s.params
        moved = s.replace(centers=p.centers.at[0].add(t * dc), ior=p.ior.at[0].add(t * dn), fresnel=p.fresnel + t * de)
        return jnp.sum(w * rtjax.render(moved, depth=depth))

    _, jvp = jax.jvp(f, (0.0,), (1.0,))
    grad = jax.grad(f)(0.0)
    fd, fd10 = (float((f(h) - f(-h)) / (2 * h)) for h in (REL_STEP, REL_STEP / 10))
    assert abs(fd - fd10) <= TOL * abs(fd), "finite differences unstable: an edge or kink within the step"
    assert float(jvp) == pytest.approx(fd, rel=TOL) and float(grad) == pytest.approx(float(jvp), rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("edges", [0.0, 1.0])
def test_float32_agrees_with_float64_on_the_sample_deck(edges):
    """The sample deck at 96 × 71: ≥ 99.5 % of pixels within half a level (per channel's
    worst), plain and silhouette-aware."""
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        deck = rtjax.parse_deck(f.read()).frames[0].scene.resized(96)
    single = np.asarray(rtjax.render(deck, edges=edges))
    double = np.asarray(rtjax.render(deck.astype(jnp.float64), edges=edges))
    assert single.dtype == np.float32 and double.dtype == np.float64
    off = np.abs(single - double).max(axis=-1)
    assert np.mean(off < 0.5) >= 0.995, f"{np.mean(off < 0.5):.4f} of pixels within 0.5 levels"
    assert np.median(off) < 1e-3


@pytest.mark.parametrize("n", [5, 40])
def test_lookup_derivatives_equal_a_gathers(n):
    """`numerics.lookup` (per-sphere values at each ray's sphere) has a gather's value and
    derivatives, forward and reverse, in float64; for tables up to `LOOKUP_ONE_HOT_MAX`
    rows its reverse mode has no scatter (XLA's CPU backend runs one ray at a time)."""
    from rtjax import numerics

    rng = np.random.default_rng(n)
    table = jnp.asarray(rng.normal(size=n))
    idx = jnp.asarray(rng.integers(0, n, size=300), jnp.int32)
    weights = jnp.asarray(rng.normal(size=300))
    dt = jnp.asarray(rng.normal(size=n))

    def gathered(t):
        return t[idx]

    def looked_up(t):
        return numerics.lookup(t, idx)

    for f in (gathered, looked_up):
        assert np.array_equal(f(table), table[np.asarray(idx)])
    np.testing.assert_allclose(jax.jvp(looked_up, (table,), (dt,))[1], jax.jvp(gathered, (table,), (dt,))[1],
                               rtol=1e-15, atol=0)
    expected = np.bincount(np.asarray(idx), weights=np.asarray(weights), minlength=n)
    grad = jax.grad(lambda t: jnp.sum(weights * looked_up(t)))(table)
    np.testing.assert_allclose(grad, expected, rtol=1e-12, atol=1e-12)
    text = jax.jit(jax.grad(lambda t: jnp.sum(weights * looked_up(t)))).lower(table).as_text()
    assert ("scatter" in text) == (n > numerics.LOOKUP_ONE_HOT_MAX)


@pytest.mark.parametrize("edges", [0.0, 1.0])
def test_a_channel_at_zero_takes_the_inside_derivative(edges):
    """A diffuse colour with a zero channel and no highlight puts that channel exactly at
    the clamp's lower bound on the whole sphere: forward and reverse mode both give the
    derivative into the range, the forward difference's (the channel is linear in the
    colour there). `jnp.clip` halved it at that tie, and the render's jvp and vjp, which
    round the channel to 0 or just above it, disagreed by a factor of 2
    (test_reverse's sample deck)."""
    deck = "sphe 0 0 0 10\nopaq 0.9 0.6 0 0 1\nplig -0.5 -1 0.8 150 140 130\nback 20 30 60\nelig 0.15\n" + CAMERA
    s = rtjax.parse_deck(deck).frames[0].scene.astype(jnp.float64)

    def blue(b):
        return rtjax.render(s.replace(diffuse=s.params.diffuse.at[0, 2].set(b)), edges=edges)[..., 2]

    h = 1e-3
    fd = (np.asarray(blue(h)) - np.asarray(blue(0.0))) / h
    assert np.count_nonzero(fd > 1) > 50  # the sphere's lit pixels
    tangent = np.asarray(jax.jvp(blue, (0.0,), (1.0,))[1])
    np.testing.assert_allclose(tangent, fd, rtol=1e-7, atol=1e-7)
    w = np.random.default_rng(0).uniform(0, 1, fd.shape)
    assert float(jax.grad(lambda b: jnp.sum(blue(b) * w))(0.0)) == pytest.approx(float(np.sum(fd * w)), rel=1e-7)
