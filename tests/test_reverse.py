"""Reverse mode through the chain (issue 20): the gradient of a rendered image equals its
forward-mode derivatives and finite differences, in plain and silhouette-aware modes,
on a scene whose paths pass through a mirror and a glass sphere (depth ≥ 2); and the
compiled reverse gradient's memory does not grow with depth (XLA's memory analysis).

The chain's segments are checkpointed (`rtjax.trace`) in every mode, so reverse mode
stores each segment's rays, not its intermediates; these tests pin that the numbers are
those of plain autodiff (forward mode does not go through the checkpoint's
recomputation). The silhouette-aware mode's check is on the sample deck (40 px), whose
grazing hits on mirror and glass silhouettes the small scene here lacks.

Every check here is an identity to rounding, a tolerance or XLA's memory analysis, and
compile time is most of their cost: the module runs under XLA's quick build
(`conftest.quick_build`, which says why that checks the same program).
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rtjax

from conftest import SCENES

pytestmark = pytest.mark.usefixtures("quick_build")

#: A mirror, a glass sphere in front of it, an opaque sphere seen in both, a floor; two
#: lights. 32 × 24 pixels from a generic camera.
DECK = (
    "sphe 0 0 0 12\nmirr\n"
    "sphe 6 -18 2 5\ntrpa 0.8 1.45 0.3 9\n"
    "sphe -13 -11 6 4\nopaq 0.8 0.3 0.2 0.4 8\n"
    "sphe 0 0 -1015 1000\nopaq 0.7 0.7 0.6 0 1\n"
    "plig -0.5 -1 0.8 120 110 100\nplig 0.4 -0.6 0.5 90 100 110\n"
    "back 20 30 60\nelig 0.2\n"
    "eyep 7 -60 10\nrefp 0.5 0 0.3\nvang 42 32\nsize 32\nrend x.ras\n"
)
DEPTH = 4


@functools.lru_cache(maxsize=None)
def scene() -> rtjax.Scene:
    return rtjax.parse_deck(DECK).frames[0].scene.astype(jnp.float64)


def _random_like(params: rtjax.Params, key: int) -> rtjax.Params:
    """Random tangent directions, one per float leaf (scaled to each leaf's size)."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    keys = jax.random.split(jax.random.key(key), len(leaves))
    out = [jax.random.normal(k, a.shape, a.dtype) * (0.1 + 0.01 * jnp.abs(a)) for k, a in zip(keys, leaves)]
    return jax.tree_util.tree_unflatten(tree, out)


def _inner(a: rtjax.Params, b: rtjax.Params) -> float:
    return float(sum(jnp.vdot(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))))


def assert_dot_products(image, p, structure, least: float) -> np.ndarray:
    """⟨Jᵀc, t⟩ = ⟨c, J t⟩ to rounding (float64) for a random cotangent c and three random
    tangents t over all parameters of `image(p)`, each ⟨c, J t⟩ at least `least` in size.
    Returns the image (forward mode's primal output)."""
    c = jax.random.normal(jax.random.key(7), (structure.height, structure.width, 3), jnp.float64)
    pullback = jax.jit(lambda p: jax.vjp(image, p)[1](c)[0])(p)
    push = jax.jit(lambda p, t: jax.jvp(image, (p,), (t,)))
    for key in range(3):
        t = _random_like(p, key)
        out, tangent = push(p, t)
        forward = float(jnp.vdot(c, tangent))
        assert abs(forward) > least
        assert _inner(pullback, t) == pytest.approx(forward, rel=1e-9), key
    return np.asarray(out)


@pytest.mark.slow
@pytest.mark.parametrize("edges", [0.0])
def test_reverse_equals_forward_through_mirror_and_glass(edges):
    """⟨Jᵀc, t⟩ = ⟨c, J t⟩ for a random cotangent c and random tangents t over all
    parameters (float64, rounding only), and every path the chain follows is exercised:
    the image changes if the depth is cut."""
    s = scene()
    p = s.params

    def image(p):
        return rtjax.render(rtjax.Scene(s.structure, p), depth=DEPTH, edges=edges)

    shallow = np.asarray(rtjax.render(s, depth=1, edges=edges))
    assert np.abs(np.asarray(image(p)) - shallow).max() > 1, "the scene has no path of depth ≥ 2"
    assert_dot_products(image, p, s.structure, least=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("edges, size", [(0.0, 96), (1.0, 40)])
def test_reverse_equals_forward_on_the_sample_deck(edges, size):
    """The same dot-product test on the sample deck, its own depth (10): two mirrors and
    three glass spheres through the checkpointed chain. In the silhouette-aware mode at
    40 px every pixel is traced in the mode, with `render`'s default sub-boxes (16 × 16
    where edges are, in two levels: they change the image), through the grazing hits on
    the inside of mirror and glass silhouettes and the ends of shadow edges' boxes,
    where rounding alone once chose between two paths or derivatives differently in the
    image, its jvp and its vjp (docs/MEASUREMENTS.md, stops 55, 64–66)."""
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        s = rtjax.parse_deck(f.read()).frames[0].scene.resized(size).astype(jnp.float64)
    p = s.params

    def image(p):
        return rtjax.render(rtjax.Scene(s.structure, p), edges=edges)

    out = assert_dot_products(image, p, s.structure, least=1.0)
    if edges:
        one_box = np.asarray(rtjax.render(s, edges=edges, subdivide=0))
        assert np.abs(out - one_box).max() > 0.5, "no pixel of the sample deck is subdivided"


@pytest.mark.slow
def test_reverse_equals_finite_differences_through_mirror_and_glass():
    """The plain mode's gradient along random directions against central differences
    (float64; the quotient first checked stable between h and h/10, as in test_grad)."""
    s = scene()
    p = s.params

    def loss(p):
        image = rtjax.render(rtjax.Scene(s.structure, p), depth=DEPTH)
        return jnp.vdot(jnp.cos(jnp.arange(image.size, dtype=image.dtype)).reshape(image.shape), image)

    grad = jax.jit(jax.grad(loss))(p)
    f = jax.jit(loss)
    for key in range(3):
        t = _random_like(p, 10 + key)

        def quotient(h):
            up = jax.tree_util.tree_map(lambda a, b: a + h * b, p, t)
            down = jax.tree_util.tree_map(lambda a, b: a - h * b, p, t)
            return (float(f(up)) - float(f(down))) / (2 * h)

        fd, fd10 = quotient(1e-6), quotient(1e-7)
        assert fd == pytest.approx(fd10, rel=1e-5), "an edge or kink within the step"
        assert _inner(grad, t) == pytest.approx(fd, rel=1e-5), key


@pytest.mark.slow
def test_reverse_memory_does_not_grow_with_depth():
    """XLA's memory analysis of the compiled gradient of the mean image (the sample deck
    at 96 px): at depth 10 at most twice that at depth 0."""
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        s = rtjax.parse_deck(f.read()).frames[0].scene.resized(96)

    def peak(depth: int) -> int:
        def loss(p):
            return rtjax.render(rtjax.Scene(s.structure, p), depth=depth).mean()

        analysis = jax.jit(jax.grad(loss)).lower(s.params).compile().memory_analysis()
        return analysis.temp_size_in_bytes

    shallow, deep = peak(0), peak(10)
    assert shallow > 0
    assert deep <= 2 * shallow, f"depth 10: {deep / 2**20:.1f} MiB, depth 0: {shallow / 2**20:.1f} MiB"
