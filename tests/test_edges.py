"""The silhouette-aware mode (`render(scene, edges=w)`, rtjax/edges.py) against its
yardstick, a supersampled render (`render(scene, spp=32)`, 32 × 32 samples per pixel),
in float64 on 32 × 32 images (issue 3, "Derivatives you can trust"):

* its image is much closer to the supersampled one than the plain (pixel-centre) image;
* its forward-mode derivative image (jax.jacfwd) with respect to a sphere's centre and
  radius points the same way as the central finite difference of the supersampled
  image (cosine similarity), and its sum over the image (the derivative of the mean
  image) agrees where that sum is well conditioned;
* as the width goes to 0 it is the plain image;
* silhouettes seen in a mirror are handled.

The finite-difference step is h = 0.2 of a pixel's size in the world at the sphere's
distance, which the sums need (they are converged at 32 × 32 samples, within 0.5 % of
128 × 128). Cosines take a finer yardstick, h = 0.05 px at 96 × 96 samples: a box-
filtered pixel's derivative jumps where an edge crosses the pixel's border, and a
central difference averages it over the edge's motion of ±h, which lowers the cosine
by itself (single sphere: 0.997 at h = 0.1 px, 0.993 at 0.2, 0.986 at 0.3, 0.96 at
0.5, whatever the samples per pixel from 16 to 128; the occlusion scene's front sphere,
whose outline runs along a pixel border: 0.974 at 0.2, 0.985 at 0.1 (64 × 64), 0.992 at
0.05 (96 × 96; 0.993 at 128 × 128)).

The numbers quoted in comments were measured with these exact scenes; docs/EDGES.md
tabulates them, with a sweep over sub-pixel placements of the spheres.

Compile cost: one jitted function per scene structure (`_edge_image_and_jacobian`); the
occlusion and shadow scenes share a structure. Nothing here is timed.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rtjax
from conftest import quick_xla
from rtjax import reference
from rtjax.camera import pixel_grid
from rtjax.render import EDGE_CHUNK_MIN

SPP = 32  # the yardstick: 32 × 32 samples per pixel
STEP = 0.2  # finite-difference step, in pixels (world size at the sphere's distance)
FINE = (0.05, 96)  # (step, samples per pixel) of the cosines' yardstick
WIDTH = 1.0  # edge width: the pixel's own box, what supersampling approximates

CAMERA = "eyep 0 -100 0\nrefp 0 0 0\nvang 30 30\nsize 32\nrend x.ras\n"
LIGHT = "plig 0.6 -1 0.8 170 160 150\nelig 0.15\nback 30 40 90\n"

DECKS = {
    # one opaque sphere on a blue background, off-centre by a fraction of a pixel
    "single": ("sphe 1.3 0 -0.7 12\nopaq 0.9 0.6 0.3 0.4 10\n" + LIGHT + CAMERA, 0),
    # a sphere (0) partly hiding a larger one (1) behind it
    "occlusion": (
        "sphe -5.2 -25 3.1 9\nopaq 0.3 0.7 0.9 0.4 10\nsphe 4.4 10 -2.3 15\nopaq 0.9 0.6 0.3 0.4 10\n" + LIGHT + CAMERA,
        0,
    ),
    # a sphere (0) casting its shadow on a floor (a sphere of radius 10⁴), seen from above
    "shadow": (
        "sphe -2.3 0 4.2 7\nopaq 0.3 0.7 0.9 0.4 10\nsphe 0 0 -10012 10000\nopaq 0.8 0.8 0.7 0 1\n"
        "plig 0.5 -0.3 1 170 160 150\nelig 0.15\nback 30 40 90\n"
        + CAMERA.replace("eyep 0 -100 0\nrefp 0 0 0", "eyep 0 -90 45\nrefp 0 0 -6"),
        0,
    ),
    # an opaque sphere (1) outside the field of view, seen only in a mirror (0)
    "mirror": (
        "sphe 0 0 0 16\nmirr\nsphe 23 -16 2.5 8\nopaq 0.9 0.5 0.2 0.3 10\n"
        "plig -0.6 -0.3 0.8 170 160 150\nelig 0.15\nback 30 40 90\n" + CAMERA.replace("vang 30 30", "vang 16 16"),
        2,
    ),
    # an opaque sphere (1) seen only through a glass sphere (0) in front of it
    "glass": (
        "sphe 0 -30 0 14\ntrpa 0.85 1.5 0.2 10\nsphe 4.3 20 2.1 10\nopaq 0.9 0.5 0.2 0.3 10\n" + LIGHT + CAMERA,
        3,
    ),
}

AXES = {"x": 0, "y": 1, "z": 2, "r": 3}


@functools.lru_cache(maxsize=None)
def scene(name: str) -> rtjax.Scene:
    return rtjax.parse_deck(DECKS[name][0]).frames[0].scene.astype(jnp.float64)


def _with(params: rtjax.Params, **leaves) -> rtjax.Params:
    fields = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    fields.update(leaves)
    return rtjax.Params(**fields)


@functools.partial(jax.jit, static_argnames=("structure", "depth", "width"))
def _edge_image_and_jacobian(params, k, structure, depth, width):
    """The silhouette-aware image and its Jacobian (H, W, 3, 4) with respect to sphere
    k's (x, y, z, r) by jax.jacfwd. k is traced: one compilation per structure."""

    def f(v):
        p = _with(params, centers=params.centers.at[k].set(v[:3]), radii=params.radii.at[k].set(v[3]))
        image = rtjax.render(rtjax.Scene(structure, p), depth=depth, edges=width)
        return image, image

    v = jnp.concatenate([params.centers[k], params.radii[k][None]])
    jacobian, image = jax.jacfwd(f, has_aux=True)(v)
    return image, jacobian


@functools.lru_cache(maxsize=None)
def edge_mode(name: str, k: int):
    """The silhouette-aware image and its Jacobian (4, H, W, 3) for sphere k, compiled
    under `quick_xla` (tolerance checks against yardsticks; the compile is what costs,
    and `_edge_image_and_jacobian` is called nowhere else)."""
    s = scene(name)
    with quick_xla():
        image, jacobian = _edge_image_and_jacobian(s.params, k, s.structure, DECKS[name][1], WIDTH)
    return np.asarray(image), np.moveaxis(np.asarray(jacobian), -1, 0)


@functools.lru_cache(maxsize=None)
def supersampled(name: str) -> np.ndarray:
    return np.asarray(rtjax.render(scene(name), depth=DECKS[name][1], spp=SPP))


def plain(name: str) -> np.ndarray:
    return np.asarray(rtjax.render(scene(name), depth=DECKS[name][1]))


def pixel_size(s: rtjax.Scene, k: int) -> float:
    """A pixel's width in the world at sphere k's distance from the eye."""
    p = s.params
    distance = float(jnp.linalg.norm(p.centers[k] - p.eye))
    return 2 * distance * float(jnp.tan(jnp.deg2rad(p.vang[0]) / 2)) / s.structure.width


def supersampled_difference(name: str, k: int, axis: str, step: float = STEP, spp: int = SPP) -> np.ndarray:
    """Central difference of the supersampled image in sphere k's centre axis or radius,
    with a step of `step` pixels and `spp` × `spp` samples per pixel."""
    s = scene(name)
    h = step * pixel_size(s, k)

    def moved(sign):
        if axis == "r":
            return s.replace(radii=s.params.radii.at[k].add(sign * h))
        return s.replace(centers=s.params.centers.at[k, AXES[axis]].add(sign * h))

    up, down = (np.asarray(rtjax.render(moved(sign), depth=DECKS[name][1], spp=spp)) for sign in (1, -1))
    return (up - down) / (2 * h)


def seen_directly(name: str, k: int) -> bool:
    """Does any ray through the image (a 4 × 4 lattice per pixel, and the borders) meet sphere k?"""
    s = scene(name)
    w, h = s.structure.width, s.structure.height
    x, y = np.meshgrid(np.linspace(0, w, 4 * w + 1), np.linspace(0, h, 4 * h + 1))
    o, d = rtjax.camera.rays_through(s.params.eye, s.params.refp, s.params.vang, w, h, jnp.asarray(np.stack([x.ravel(), y.ravel()])))
    f = np.asarray(o) - np.asarray(s.params.centers[k])[:, None]
    b = np.sum(f * np.asarray(d), axis=0)
    return bool(np.any(np.sum(f * f, axis=0) - b**2 < float(s.params.radii[k]) ** 2))


def cosine(a, b) -> float:
    return float(np.sum(a * b) / (np.linalg.norm(a) * np.linalg.norm(b)))


# --------------------------------------------------------------------------------------
# (a) images


# measured mean |image − supersampled| (levels of 255), plain → silhouette-aware (at 32 px
# `render`'s default, 16 × 16 sub-boxes where edges are, narrow highlights too since
# stop 60): single 0.551 → 0.009 (61×), occlusion 0.877 → 0.014 (63×), shadow 1.063 →
# 0.007 (150×), mirror 0.261 → 0.002 (stop 59, without highlights: 0.029, 0.050, 0.015,
# 0.002; 4 × 4 until stop 59: 0.049, 0.087, 0.041, 0.021; one box: 0.074, 0.134, 0.089, 0.037)
@pytest.mark.slow
@pytest.mark.parametrize("name", ["single", "occlusion", "shadow", "mirror"])
def test_image_approaches_the_supersampled_one(name):
    k = 1 if name == "mirror" else 0
    ss = supersampled(name)
    edge, _ = edge_mode(name, k)
    plain_error = np.abs(plain(name) - ss).mean()
    edge_error = np.abs(edge - ss).mean()
    assert plain_error > 0.2, "the scene has no edge to speak of"
    assert edge_error <= plain_error / 4, f"mean error {edge_error:.3f} (plain {plain_error:.3f})"
    assert edge_error < 0.2, f"mean error {edge_error:.3f} levels"


def test_supersampled_yardstick_is_the_independent_reference():
    """The yardstick equals rtjax.reference's independent float64 render (32 × 32
    samples), so its finite differences are those of an independent renderer."""
    frame = reference.parse_deck_text(DECKS["occlusion"][0])[0]
    np.testing.assert_allclose(supersampled("occlusion"), reference.render_reference(frame, depth=0, spp=SPP), atol=1e-4)


# --------------------------------------------------------------------------------------
# (b) derivatives: (scene, sphere, axis) → maximum relative error of the summed
# derivative, or None where the sum nearly cancels. Every cosine is asserted ≥ 0.99 (the
# issue's threshold) against the fine yardstick. The comments give the measured cosine
# (fine yardstick; h = 0.2 px at 32 × 32 in brackets), the summed derivatives (mode / FD at
# 0.2 px, 32 × 32) and |Σ|/Σ|·| of the FD (the sum's conditioning: near 0, the sum is a
# small difference of large terms).

CASES = {
    ("single", 0, "x"): None,  # 0.9993 (0.9908); Σ −88.7 / −90.2, |Σ|/Σ|·| = 0.02
    ("single", 0, "y"): 0.05,  # 0.9997 (0.9987); Σ −98.3 / −102.0 (3.7 %), 0.16
    ("single", 0, "z"): None,  # 1.0000 (0.9993); Σ −117.6 / −117.6, 0.02
    # radius: 0.9996 (0.9936); Σ 821.9 / 831.2 (1.1 %; the fine yardstick's 829.4); its
    # channels cancel (R +1881, G +625, B −1634: an orange sphere grows over a blue
    # background, |Σ|/Σ|·| = 0.15), and with one box the sum was 4.99 % off (per channel
    # 1.0 %, 2.1 %, 0.6 %; over 12 sub-pixel placements median 1.9 %, max 6.2 %)
    ("single", 0, "r"): 0.055,
    # occlusion, the front sphere: its right edge runs along a pixel border over the back
    # sphere's highlight (the coarse yardstick's cosine is low there, see the top), and
    # its outline meets the back sphere's at T-junctions
    ("occlusion", 0, "x"): 0.05,  # 0.9954 (0.9743); Σ −961.1 / −959.1 (0.2 %), 0.18
    ("occlusion", 0, "y"): None,  # 0.9997 (0.9974); Σ −119.5 / −125.3 (4.7 %), 0.17 (depth: a small sum)
    ("occlusion", 0, "z"): None,  # 1.0000 (0.9993); Σ −491.7 / −487.4 (0.9 %), 0.09
    ("occlusion", 0, "r"): 0.05,  # 0.9964 (0.9796); Σ 609.5 / 619.3 (1.6 %), 0.10
    # occlusion, the back sphere: its outline ends at T-junctions behind the front sphere
    ("occlusion", 1, "x"): 0.05,  # 1.0000 (0.9987); Σ 564.3 / 566.9 (0.5 %), 0.20
    ("occlusion", 1, "y"): 0.05,  # 0.9997 (0.9997); Σ −126.3 / −127.4 (0.8 %), 0.20
    ("occlusion", 1, "z"): None,  # 1.0000 (0.9904); Σ 113.3 / 113.8, 0.03
    ("occlusion", 1, "r"): 0.05,  # 1.0000 (0.9926); Σ 778.4 / 783.2 (0.6 %), 0.19
    # shadow: the occluder's silhouette and its shadow's edge on the floor move together
    ("shadow", 0, "x"): None,  # 1.0000 (0.9991); Σ −29.1 / −38.0, 0.01 (cancels)
    ("shadow", 0, "y"): 0.05,  # 1.0000 (0.9999); Σ 305.1 / 308.1 (1.0 %), 0.11
    ("shadow", 0, "z"): None,  # 1.0000 (0.9991); Σ −84.0 / −72.7, 0.02
    ("shadow", 0, "r"): 0.05,  # 1.0000 (0.9980); Σ −4587.5 / −4593.1 (0.1 %), 0.78
}


@pytest.mark.slow
@pytest.mark.parametrize("name, k, axis", list(CASES), ids=[f"{n}-sphere{k}-{a}" for n, k, a in CASES])
def test_derivative_approaches_the_supersampled_finite_difference(name, k, axis):
    max_sum_error = CASES[(name, k, axis)]
    _, jacobian = edge_mode(name, k)
    ad = jacobian[AXES[axis]]
    assert np.all(np.isfinite(ad))
    c = cosine(ad, supersampled_difference(name, k, axis, *FINE))
    assert c >= 0.99, f"cosine similarity {c:.4f} < 0.99"
    fd = supersampled_difference(name, k, axis)
    if max_sum_error is not None:
        error = abs(ad.sum() - fd.sum()) / abs(fd.sum())
        assert error <= max_sum_error, f"summed derivative {ad.sum():.1f} vs {fd.sum():.1f}: {error:.3%}"
    # each colour channel's summed derivative, where that sum is well conditioned
    for ch in range(3):
        if abs(fd[..., ch].sum()) >= 0.5 * np.abs(fd[..., ch]).sum():
            error = abs(ad[..., ch].sum() - fd[..., ch].sum()) / abs(fd[..., ch].sum())
            assert error <= 0.05, f"channel {ch}: summed derivative {ad[..., ch].sum():.1f} vs {fd[..., ch].sum():.1f}"


@pytest.mark.slow
def test_plain_derivative_misses_the_edge_terms():
    """Why the mode exists: on the single sphere the plain render's radius derivative
    (pixel centres, no silhouette term) is far from the supersampled one."""
    s = scene("single")
    jac = jax.jacfwd(lambda r: rtjax.render(s.replace(radii=r), depth=0))(s.params.radii)[..., 0]
    fd = supersampled_difference("single", 0, "r")
    assert cosine(np.asarray(jac), fd) < 0.6
    _, jacobian = edge_mode("single", 0)
    assert cosine(jacobian[AXES["r"]], fd) > 0.99


@pytest.mark.slow
def test_reverse_mode_agrees_with_forward_mode():
    """jax.grad of the mean silhouette-aware image equals the mean of its jacfwd columns
    (the mode's edge terms reach both modes of differentiation alike)."""
    s = scene("occlusion")

    def mean_image(p):
        return rtjax.render(rtjax.Scene(s.structure, p), depth=0, edges=WIDTH).mean()

    with quick_xla():  # a tolerance check; this program is compiled only here
        grad = jax.jit(jax.grad(mean_image))(s.params)
    for k in (0, 1):
        _, jacobian = edge_mode("occlusion", k)
        forward = jacobian.reshape(4, -1).mean(axis=1)
        reverse = np.append(np.asarray(grad.centers[k]), float(grad.radii[k]))
        np.testing.assert_allclose(reverse, forward, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------------------
# (c) the width going to 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["occlusion", "shadow", "mirror"])
def test_vanishing_width_gives_the_plain_image(name):
    s = scene(name)
    np.testing.assert_allclose(np.asarray(rtjax.render(s, depth=DECKS[name][1], edges=1e-4, subdivide=0)), plain(name), rtol=0, atol=1e-9)


# --------------------------------------------------------------------------------------
# (d) a silhouette seen in a mirror


# sphere 1 lies outside the field of view: all its derivative comes through the mirror.
# Measured cosines 0.9993, 0.9991, 0.9978, 0.9968 (x, y, z, r; 16 × 16 sub-boxes where
# edges are, the default here; 4 × 4: 0.9959, 0.9927, 0.9922, 0.9944); asserted at 0.98
# (the brief asked 0.95). Summed derivatives are not asserted: Σ 159.4 / 162.8 (x,
# 2.1 %), 76.8 / 81.1 (y, 5.3 %), −193.4 / −193.8 (z, 0.2 %), −297.1 / −304.2 (r, 2.3 %)
# (4 × 4: 5.6 %, 3.3 %, 11.6 %, 10.8 %: the reflected outline's curvature within a pixel).
@pytest.mark.slow
@pytest.mark.parametrize("axis", ["x", "y", "z", "r"])
def test_silhouette_seen_in_a_mirror(axis):
    _, jacobian = edge_mode("mirror", 1)
    fd = supersampled_difference("mirror", 1, axis)
    assert not seen_directly("mirror", 1), "sphere 1 must be out of view (seen only in the mirror)"
    c = cosine(jacobian[AXES[axis]], fd)
    assert c >= 0.98, f"cosine similarity {c:.4f}"


# --------------------------------------------------------------------------------------
# (e) a silhouette seen through glass


# sphere 1 lies wholly behind the glass sphere (its angular radius 0.083 rad inside the
# glass sphere's 0.20): its outline is seen refracted. Measured cosines 0.9983, 0.9995,
# 0.9995, 0.9972 (x, y, z, r; 16 × 16 sub-boxes where edges are, the default here; 4 × 4:
# 0.9953, 0.9972, 0.9964, 0.9948); summed derivatives Σ −995.5 / −997.1 (x, 0.2 %),
# 262.9 / 261.7 (y, 0.5 %), −1129.9 / −1129.8 (z, 0.0 %); r's sum cancels (|Σ|/Σ|·| = 0.02).
@pytest.mark.slow
@pytest.mark.parametrize("axis", ["x", "y", "z", "r"])
def test_silhouette_seen_through_glass(axis):
    s = scene("glass")
    p = np.asarray(s.params.centers), np.asarray(s.params.radii), np.asarray(s.params.eye)
    (c0, c1), (r0, r1), eye = p[0], p[1], p[2]
    behind = np.arcsin(r1 / np.linalg.norm(c1 - eye)) + np.arccos(np.dot(c1 - eye, c0 - eye) / np.linalg.norm(c1 - eye) / np.linalg.norm(c0 - eye))
    assert behind < np.arcsin(r0 / np.linalg.norm(c0 - eye)), "sphere 1 must be seen only through the glass"
    _, jacobian = edge_mode("glass", 1)
    fd = supersampled_difference("glass", 1, axis)
    ad = jacobian[AXES[axis]]
    c = cosine(ad, fd)
    assert c >= 0.99, f"cosine similarity {c:.4f}"
    if axis in "xz":
        assert abs(ad.sum() - fd.sum()) <= 0.05 * abs(fd.sum())


def test_critical_boundary_is_where_the_reference_turns_to_total_internal_reflection():
    """`edges.critical_terms`: a fan of rays from a point inside a glass sphere (n = 1.5),
    8 units off the centre of a sphere of radius 10, one sample step a 1/200 rad turn:
    the signed distance to the boundary of total internal reflection at their exit is
    positive exactly where the reference's Snell's law has no solution there, and near
    the boundary it is the rays' offset from it in steps (sin φ = (r/n)/8: the offset
    from the centre at which k crosses 0)."""
    from rtjax import edges

    c, r, n, step = np.zeros(3), 10.0, 1.5, 1 / 200
    phi = np.pi / 4 + step * np.arange(101)
    d = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)])
    o = np.broadcast_to(np.array([8.0, 0, 0])[:, None], d.shape)
    turn = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)]) * step
    still = np.zeros_like(d)
    df = edges.Differentials(*(jnp.asarray(a) for a in (still, turn, still, still)))
    centre = jnp.asarray(np.broadcast_to(c[:, None], d.shape))
    delta = np.asarray(edges.critical_terms(jnp.asarray(o), jnp.asarray(d), df, centre, r, n)[0])
    # the exit, and Snell's law there as the reference has it
    b = np.sum((o - c[:, None]) * d, 0)
    t = -b + np.sqrt(b**2 - np.sum((o - c[:, None]) ** 2, 0) + r**2)
    normal = (o + t * d - c[:, None]) / r
    _, tir = reference.refract(d.T, -normal.T, np.full(phi.size, n))
    assert 20 < tir.sum() < 80  # both sides in the fan
    np.testing.assert_array_equal(delta > 0, tir)
    offset = (phi - np.arcsin(r / n / 8)) / step
    near = np.abs(offset) < 2
    np.testing.assert_allclose(delta[near], offset[near], atol=0.02)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_critical_boundary_is_finite_at_its_singular_rays(dtype):
    """`edges.critical_terms` and its derivatives in the sphere (centre, radius, index) and
    the rays are finite where a ray passes through the centre (no direction to the
    boundary: δ is `FAR`, not a division by 0) and exactly on the boundary (δ = 0)."""
    from rtjax import edges

    r, n = 10.0, 1.5
    o = jnp.asarray([[0.0, -5.0], [0.0, r / n], [0.0, 0.0]], dtype)  # columns: the centre; r/n off it
    d = jnp.asarray([[1.0, 1.0], [0.0, 0.0], [0.0, 0.0]], dtype)
    turn = jnp.asarray([[0.0, 0.0], [0.01, 0.01], [0.0, 0.0]], dtype)
    still = jnp.zeros_like(o)

    def terms(c, radius, ior, o):
        df = edges.Differentials(still, turn, still, still)
        return edges.critical_terms(o, d, df, jnp.broadcast_to(c[:, None], o.shape), radius, ior)

    args = (jnp.zeros(3, dtype), jnp.asarray(r, dtype), jnp.asarray(n, dtype), o)
    (delta, nx, ny), tangents = jax.jvp(terms, args, tuple(jnp.ones_like(a) for a in args))
    assert abs(float(delta[0])) == edges.FAR and abs(float(delta[1])) < 1e-5
    grads = jax.grad(lambda *a: sum(jnp.sum(t) for t in terms(*a)), argnums=(0, 1, 2, 3))(*args)
    for a in (delta, nx, ny, *tangents, *grads):
        assert bool(jnp.all(jnp.isfinite(a))), a


@pytest.mark.slow
def test_boundary_of_total_internal_reflection_in_float32_is_where_float64_has_it():
    """The eye inside a glass ball (`tests/edge_scenes.py`'s inside: the boundary of total
    internal reflection crosses the image), `render`'s default 16 × 16 sub-boxes: the
    float32 image is the float64 one to within 0.1 levels. Snell's k within
    `trace.CRITICAL_BAND` of 0 counts as 0, which moves the boundary by the band over
    k's rate: a band of 1e-4 moved it across sub-box centres, 0.35 levels off."""
    from edge_scenes import DECKS

    text, depth = DECKS["inside"]
    s = rtjax.parse_deck(text).frames[0].scene
    with quick_xla(clear=True):
        f32, f64 = (np.asarray(rtjax.render(s.astype(dt), depth=depth, edges=1.0), np.float64)
                    for dt in (jnp.float32, jnp.float64))
    assert np.abs(f32 - f64).max() < 0.1


# --------------------------------------------------------------------------------------
# (f) the blend's parts (`edge_samples`), what fitting at pixel centres uses


def _pixel_centres(s: rtjax.Scene):
    """(H·W, 2) pixel centres, row-major as `render` lays pixels out."""
    return np.asarray(pixel_grid(s.structure.width, s.structure.height, jnp.array([0.5, 0.5]))).T


@pytest.mark.parametrize("name", ["occlusion", "shadow"])
def test_parts_centre_is_the_plain_colour_and_sides_straddle_it(name):
    s = scene(name)
    depth = DECKS[name][1]
    e = rtjax.edge_samples(s, _pixel_centres(s), depth=depth, edges=WIDTH)
    flat = plain(name).reshape(-1, 3)
    # values at pixel centres, shadow edges included (sharp)
    np.testing.assert_allclose(np.asarray(e.centre), flat, rtol=0, atol=1e-9)
    x, inside, outside = np.asarray(e.x), np.asarray(e.inside), np.asarray(e.outside)
    edge = x != 0
    assert 20 < edge.sum() < flat.shape[0] // 4
    np.testing.assert_allclose(inside[~edge], flat[~edge], rtol=0, atol=1e-9)
    np.testing.assert_allclose(outside[~edge], flat[~edge], rtol=0, atol=1e-9)
    assert np.abs(x[edge]).max() < 1  # edges are searched within one box width
    # the centre's colour is the one traced on its own side (x > 0: the edge sphere's)
    own = np.where(edge[:, None] & (x[:, None] > 0), inside, outside)
    other = np.where(x[:, None] > 0, outside, inside)
    sharp = edge & (np.abs(inside - outside).max(1) > 40)
    assert sharp.sum() > 10
    assert np.all(np.abs(own - flat).max(1)[sharp] < np.abs(other - flat).max(1)[sharp])


def test_parts_flip_the_nearest_shadow_edge():
    """On the floor (no silhouette), `flipped` is the centre's colour across its nearest
    shadow edge: the floor's ambient colour ke·d·L where the centre is lit, and the lit
    colour (the floor rendered without the occluder) where it is in shadow; every floor
    pixel whose centre changes side when the shadow moves by a fraction of a pixel had
    that edge within reach, and its distance to it is what the move needed."""
    s = scene("shadow")
    xy = _pixel_centres(s)
    e = rtjax.edge_samples(s, xy, edges=WIDTH)
    centre, flipped, sx = np.asarray(e.centre), np.asarray(e.flipped), np.asarray(e.shadow_x)
    # every floor pixel's centre: its sphere, from the plain hit test
    o, d = rtjax.camera.rays_through(s.params.eye, s.params.refp, s.params.vang, 32, 32, jnp.asarray(xy.T))
    on_floor = np.asarray(rtjax.spheres.nearest(o, d, s.params.centers, s.params.radii, jnp.full(1024, -1), 1e-6, False)[1]) == 1
    floor = on_floor & (np.asarray(e.x) == 0)
    near = floor & (sx < 1)
    lit = near & (centre.sum(1) > flipped.sum(1) + 30)
    dark = near & (flipped.sum(1) > centre.sum(1) + 30)
    assert lit.sum() > 5 and dark.sum() > 5
    ambient = 0.15 * np.array([0.8, 0.8, 0.7]) * np.array([170, 160, 150])
    np.testing.assert_allclose(flipped[lit], np.broadcast_to(ambient, flipped[lit].shape), atol=1e-9)
    away = s.replace(centers=s.params.centers.at[0, 0].add(1e3))  # the occluder far out of view: no shadow
    no_shadow = np.asarray(rtjax.render_samples(away, xy))
    np.testing.assert_allclose(flipped[dark], no_shadow[dark], atol=1e-9)
    np.testing.assert_allclose(flipped[sx == np.inf], centre[sx == np.inf], atol=1e-9)  # no edge within reach
    assert np.all((sx >= 0) & ((sx < 1) | (sx == np.inf)))
    # move the occluder by 0.9 of a pixel's size, along x and along y: the floor pixels
    # whose centres change side had that edge within reach, and take the flipped colour
    for axis in (0, 1):
        moved = s.replace(centers=s.params.centers.at[0, axis].add(0.9 * pixel_size(s, 0)))
        after = np.asarray(rtjax.render_samples(moved, xy))
        changed = floor & (np.abs(after - centre).max(1) > 30)
        assert changed.sum() >= 5
        assert np.all(sx[changed] < 1)
        np.testing.assert_allclose(flipped[changed], after[changed], atol=1e-9)


def test_parts_need_the_silhouette_mode():
    s = scene("single")
    with pytest.raises(rtjax.RtjaxError, match="edges"):
        rtjax.edge_samples(s, _pixel_centres(s), edges=0)


# --------------------------------------------------------------------------------------
# (g) whole images: `render` spends the mode near edges only (`render.image_edges`)
#
# Above `EDGE_CHUNK_MIN` pixels, `render(edges=w)` traces every pixel plainly, hashing
# each chain's hits and shadows into a key, and traces again in the mode only the
# pixels whose neighbourhood of keys is not uniform. Below, every pixel is traced in the
# mode (as in the sections above). These scenes at 96 × 96 pixels are above.

BIG = 96


def big(name: str) -> rtjax.Scene:
    s = scene(name).resized(BIG)
    assert s.structure.width * s.structure.height > EDGE_CHUNK_MIN
    return s


@functools.lru_cache(maxsize=None)
def every_pixel_in_the_mode(name: str, subdivide: int = 0) -> np.ndarray:
    """`big(name)` traced in the mode at every pixel centre (`render_samples`), (H·W, 3),
    compiled under `quick_xla`: the whole-image tests' yardstick, kept for the module
    (the glass scene's serves two tests)."""
    s = big(name)
    with quick_xla(clear=True):
        return np.asarray(rtjax.render_samples(s, _pixel_centres(s), depth=DECKS[name][1], edges=WIDTH,
                                               subdivide=subdivide))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_coverage_is_the_share_of_the_box_inside_the_edge(dtype):
    """`edges.coverage` against the share of a 400 × 400 grid of points in the unit box
    on the edge's inner side, over edge directions and distances (across the box and
    past it): within the grid's resolution, and within [0, 1] exactly, where rounding
    put the formula just past 1 at the end of its support (a visibility 1 − α a rounding
    error below 0, which dropped a zero colour channel's derivative at the clamp)."""
    from rtjax import edges

    angles = np.linspace(0, 2 * np.pi, 37)[:-1] + 0.1  # normals' components ≥ `_MIN_COMPONENT`
    x = np.linspace(-0.8, 0.8, 33)
    a, b = (np.repeat(f(angles), x.size) for f in (np.cos, np.sin))
    xs = np.tile(x, angles.size)
    alpha = np.asarray(edges.coverage(*(jnp.asarray(v, dtype) for v in (xs, a, b))))
    u = (np.arange(400) + 0.5) / 400 - 0.5
    uu, vv = (g.ravel() for g in np.meshgrid(u, u))
    share = ((a[:, None] * uu + b[:, None] * vv) > -xs[:, None]).mean(axis=1)
    np.testing.assert_allclose(alpha, share, atol=4e-3)
    assert alpha.min() >= 0 and alpha.max() <= 1
    ends = np.asarray(edges.coverage(jnp.asarray(np.abs(a) + np.abs(b), dtype) / 2, jnp.asarray(a, dtype),
                                     jnp.asarray(b, dtype)))
    assert ends.max() <= 1 and ends.min() > 1 - 1e-5


@pytest.mark.parametrize("halvings", [1, 2, 3])
def test_sub_boxes_tile_the_box(halvings):
    """`subdivide`'s k × k sub-boxes (k = 2^halvings): their centres are those of the
    cells of a k × k grid over the box (offsets in boxes from its centre), each once."""
    k = 2**halvings
    offsets = np.array(rtjax.trace.sub_box_offsets(halvings))
    cells = (np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="xy"), -1).reshape(-1, 2) + 0.5) / k - 0.5
    np.testing.assert_array_equal(offsets, cells)
    assert len({tuple(o) for o in offsets}) == k * k


def sub_box_centres(centres, box: float = 1.0) -> np.ndarray:
    """(K·16, 2) the centres of the 4 × 4 sub-boxes of the boxes `box` pixels wide centred
    at `centres` (K, 2), each box's sub-boxes next to one another, as `render` lays them."""
    return (centres[:, None, :] + box * np.array(rtjax.trace.sub_box_offsets(2))).reshape(-1, 2)


def test_sub_box_levels_reach_the_halvings():
    """Beyond 4 × 4 the sub-boxes come in two levels, the second dividing only the first
    level's sub-boxes that an edge may cross."""
    assert [rtjax.trace.sub_box_levels(h) for h in range(5)] == [(0,), (1,), (2,), (2, 1), (2, 2)]


@pytest.mark.slow
def test_two_levels_of_sub_boxes_are_the_mean_of_their_boxes():
    """`subdivide=4` on pixels the single sphere's outline crosses: each pixel is the mean
    of its 4 × 4 sub-boxes, each of which, where the outline may cross it (within
    `edges.CROSSING` of a box from its centre), is the mean of its own 4 × 4; built here
    from one-box renders of those boxes at their centres (`render_samples`, boxes of ¼
    and 1/16 px) and the outline's distance from them (`edge_samples`). `subdivide=2` is
    the mean of the first level alone. (The renderer moves the sub-boxes' rays along the
    pixel's ray differentials, the samples here go through the camera: rounding and
    second order apart, the same rays.)"""
    s = scene("single")
    with quick_xla():  # a tolerance check (0.05 levels); the compile is what costs
        image = {h: np.asarray(rtjax.render(s, edges=WIDTH, subdivide=h)) for h in (2, 4)}
        plain_image = plain("single")
        rows, cols = np.nonzero(np.abs(image[2] - plain_image).max(axis=-1) > 5)  # pixels an edge crosses
        pick = np.linspace(0, len(rows) - 1, 12).astype(int)
        pixels = np.stack([cols[pick] + 0.5, rows[pick] + 0.5], axis=-1)  # (12, 2) centres
        centres = sub_box_centres(pixels)  # (12·16, 2)
        a = np.asarray(rtjax.render_samples(s, centres, step=0.25, edges=WIDTH)).reshape(12, 16, 3)
        edge = {w: rtjax.edge_samples(s, centres, step=0.25, edges=w) for w in (WIDTH, 2 * WIDTH)}
        has_edge = {w: np.any(np.asarray(e.inside) != np.asarray(e.outside), axis=-1).reshape(12, 16) for w, e in edge.items()}
        crossed = has_edge[WIDTH] & (np.abs(np.asarray(edge[WIDTH].x)).reshape(12, 16) < rtjax.edges.CROSSING)
        # within two boxes of the outline but not crossed: divided again or not (the rim's rule
        # bounds its distance from below), so the pixel may take either colour of such a box
        either = has_edge[2 * WIDTH] & ~crossed
        fine = sub_box_centres(centres, 0.25)
        b = np.asarray(rtjax.render_samples(s, fine, step=1 / 16, edges=WIDTH)).reshape(12, 16, 16, 3).mean(axis=2)
    assert 0 < crossed.sum() < crossed.size
    np.testing.assert_allclose(image[2][rows[pick], cols[pick]], a.mean(axis=1), atol=0.05)
    expected = np.where(crossed[..., None], b, a).mean(axis=1)
    slack = (either[..., None] * np.abs(b - a)).sum(axis=1) / 16
    assert np.all(np.abs(image[4][rows[pick], cols[pick]] - expected) <= slack + 0.05)
    assert np.abs(expected - a.mean(axis=1)).max() > 0.1  # the second level changed something


def sphere_samples(s: rtjax.Scene, k: int):
    """8 × 8 rays a pixel: which meet sphere k first, and there N·L and cos γ = R_L·V for
    the first light (`shading.phong_angles`), each (h, 8, w, 8)."""
    p, w, h = s.params, s.structure.width, s.structure.height
    u = (np.arange(8) + 0.5) / 8
    x, y = np.meshgrid(np.arange(w)[:, None] + u, np.arange(h)[:, None] + u)  # (h·8, w·8)
    o, d = rtjax.camera.rays_through(p.eye, p.refp, p.vang, w, h, jnp.asarray(np.stack([x.ravel(), y.ravel()])))
    t, index, _ = rtjax.spheres.nearest(o, d, p.centers, p.radii, jnp.full(x.size, -1), 1e-6, False)
    met = (np.asarray(index) == k) & np.isfinite(np.asarray(t))
    t, d = np.where(met, np.asarray(t), 0), np.asarray(d)  # rays that meet nothing: any point
    normal = (np.asarray(o) + t * d - np.asarray(p.centers[k])[:, None]) / float(p.radii[k])
    light = np.asarray(p.light_dirs[0]) / np.linalg.norm(np.asarray(p.light_dirs[0]))
    nl = light @ normal
    cos_g = np.einsum("ip,ip->p", 2 * nl * normal - light[:, None], -d / np.linalg.norm(d, axis=0))
    return tuple(a.reshape(h, 8, w, 8) for a in (met, nl, cos_g))


def assert_pixels_are_their_sub_boxes(s: rtjax.Scene, k: int, rows, cols):
    """With `subdivide=2` the pixels (rows, cols) are each the mean of their 4 × 4
    sub-boxes (one-box renders at their centres), image and the derivative in sphere
    k's radius, where one box (`subdivide=0`) is off by over a level in both."""
    assert len(rows) >= 4

    def grown(v):
        return s.replace(radii=s.params.radii.at[k].add(v))

    def pixels(subdivide):
        return jax.jvp(lambda v: rtjax.render(grown(v), edges=WIDTH, subdivide=subdivide)[rows, cols], (0.0,), (1.0,))

    centres = sub_box_centres(np.stack([cols + 0.5, rows + 0.5], -1))
    with quick_xla():  # a tolerance check (0.05 levels); the compile is what costs
        boxes = jax.jvp(lambda v: rtjax.render_samples(grown(v), centres, step=0.25, edges=WIDTH), (0.0,), (1.0,))
        (image, tangent), (one, one_tangent) = pixels(2), pixels(0)
    mean, mean_tangent = (np.asarray(a).reshape(len(rows), 16, 3).mean(axis=1) for a in boxes)
    np.testing.assert_allclose(image, mean, atol=0.05)
    np.testing.assert_allclose(tangent, mean_tangent, atol=0.05)
    assert np.abs(np.asarray(one) - mean).max() > 1 and np.abs(np.asarray(one_tangent) - mean_tangent).max() > 1


@pytest.mark.slow
def test_boxes_a_terminator_crosses_are_subdivided():
    """The occlusion scene's back sphere, where its terminator (N·L = 0) crosses pixels
    that no outline does (found here by 8 × 8 rays a pixel meeting the sphere, N·L
    changing sign among them): shading is continuous there but far from linear, so such
    pixels get sub-boxes too (`assert_pixels_are_their_sub_boxes`)."""
    s, k = scene("occlusion"), 1
    met, nl, _ = sphere_samples(s, k)
    rows, cols = np.nonzero(met.all(axis=(1, 3)) & (nl.max(axis=(1, 3)) > 0) & (nl.min(axis=(1, 3)) < 0))
    assert_pixels_are_their_sub_boxes(s, k, rows, cols)


@pytest.mark.slow
def test_boxes_a_small_highlight_lies_in_are_subdivided():
    """The occlusion scene's front sphere with a sharp highlight (β = 60: a lobe a few
    pixels wide, found here by 8 × 8 rays a pixel meeting the sphere, lit, and some with
    cos γ^β > 0.1): shading is smooth there but far from linear across a pixel, so such
    pixels get sub-boxes (`edges.near_highlight`, `assert_pixels_are_their_sub_boxes`;
    the terminator test's scene, so that the two share their compiled renders)."""
    s, k = scene("occlusion"), 0
    s = s.replace(beta=s.params.beta.at[k].set(60.0))
    met, nl, cos_g = sphere_samples(s, k)
    lobe = np.clip(cos_g, 0, 1) ** 60
    rows, cols = np.nonzero((met & (nl > 0)).all(axis=(1, 3)) & (lobe.max(axis=(1, 3)) > 0.1))
    assert_pixels_are_their_sub_boxes(s, k, rows, cols)


@pytest.mark.slow
def test_more_sub_boxes_than_pixels_approach_the_supersampled_image():
    """Issue 21's held-out-like scene (a mirror and a glass sphere over a floor) at 5 × 5
    pixels, so that 8 × 8 sub-boxes (`subdivide=3`) outnumber the image's pixels: the
    image is finite, and its distance from the reference's 16 × 16-supersampled one
    falls as the boxes shrink (measured 4.01, 2.47, 1.76 levels for 1, 2 × 2, 8 × 8)."""
    from edge_scenes import DECKS as CHAIN_DECKS  # issue 21's scenes, not this module's DECKS

    text = CHAIN_DECKS["heldout"][0].replace("size 48", "size 5")
    s = rtjax.parse_deck(text).frames[0].scene.astype(jnp.float64)
    supersampled = reference.render_reference(reference.parse_deck_text(text)[0], depth=6, spp=16)
    errors = []
    for halvings in (0, 1, 3):
        with quick_xla():  # an approach to the reference, not bits
            image = np.asarray(rtjax.render(s, depth=6, edges=1.0, subdivide=halvings))
        assert image.shape == (5, 5, 3) and np.isfinite(image).all()
        errors.append(np.abs(image - supersampled).mean())
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.5 * errors[0], errors


def test_edge_pixels_are_those_beside_a_change_of_key():
    keys = np.full((12, 16), 7, np.uint32)  # the lattice and a ring `reach` wide around it
    keys[:, 9:] = 8  # a vertical edge between columns 8 and 9
    keys[5, 3] = 9  # a feature one sample across
    for reach in (1, 2):
        expected = np.zeros(keys.shape, bool)
        expected[:, 9 - reach:9 + reach] = True
        expected[5 - reach:5 + reach + 1, 3 - reach:3 + reach + 1] = True
        inner = expected[reach:-reach, reach:-reach]
        np.testing.assert_array_equal(np.asarray(rtjax.edges.edge_pixels(jnp.asarray(keys), reach)), inner)


def test_every_pixel_an_outline_crosses_is_chosen():
    """The single sphere at 96 × 96: the pixels whose box its outline crosses (some of
    9 × 9 rays spread over the box meet the sphere and some miss it, by an independent
    NumPy ray–sphere test) are all chosen, and few others are."""
    s = big("single")
    w, h = s.structure.width, s.structure.height
    ring = pixel_grid(w + 2, h + 2, jnp.array([-0.5, -0.5]))
    keys = rtjax.trace.trace(s.structure, s.params, *rtjax.camera.rays_through(
        s.params.eye, s.params.refp, s.params.vang, w, h, ring), 0, keyed=True).key
    near = np.asarray(rtjax.edges.edge_pixels(keys.reshape(h + 2, w + 2), 1))
    u = (np.arange(9) + 0.5) / 9
    sub = np.stack(np.meshgrid(u, u, indexing="xy"), -1).reshape(-1, 2)
    corner = np.stack(np.meshgrid(np.arange(w), np.arange(h), indexing="xy"), -1).reshape(-1, 1, 2)
    xy = (corner + sub).reshape(-1, 2)
    o, d = (np.asarray(a) for a in rtjax.camera.rays_through(s.params.eye, s.params.refp, s.params.vang, w, h, jnp.asarray(xy.T)))
    f = o - np.asarray(s.params.centers[0])[:, None]
    b = np.sum(f * d, axis=0)
    meets = (np.sum(f * f, axis=0) - b**2 < float(s.params.radii[0]) ** 2).reshape(h, w, -1)
    crossed = meets.any(-1) & ~meets.all(-1)
    assert crossed.sum() > 100
    assert near[crossed].all()
    assert near.sum() < 3 * crossed.sum()  # the outline's neighbours and the terminator (measured 444 for 154)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["occlusion", "shadow", "glass"])  # (single: within occlusion; mirror: glass reflects too)
def test_whole_image_is_every_pixel_traced_in_the_mode(name):
    """At 96 × 96 the chosen pixels hold every edge: the image equals the mode traced
    at every pixel centre (`render_samples`), to rounding."""
    s = big(name)
    depth = DECKS[name][1]
    with quick_xla(clear=True):  # an agreement of two programs, not bits; the compile is what costs
        whole = np.asarray(rtjax.render(s, depth=depth, edges=WIDTH)).reshape(-1, 3)
        centres = np.asarray(rtjax.render(s, depth=depth)).reshape(-1, 3)
    np.testing.assert_allclose(whole, every_pixel_in_the_mode(name), rtol=0, atol=1e-9)
    assert np.abs(whole - centres).max() > 20  # edges blended


@pytest.mark.slow
def test_whole_image_with_sub_boxes_is_every_pixel_traced_in_the_mode():
    """The same with 2 × 2 sub-boxes (`subdivide`): the
    whole image's chunks subdivide the pixels that every pixel's trace does, and the
    sub-boxes change the glass scene's image."""
    s = big("glass")
    depth = DECKS["glass"][1]
    with quick_xla(clear=True):  # an agreement of two programs, not bits; the compile is what costs
        whole = np.asarray(rtjax.render(s, depth=depth, edges=WIDTH, subdivide=True)).reshape(-1, 3)
    every, one_box = every_pixel_in_the_mode("glass", 1), every_pixel_in_the_mode("glass")
    np.testing.assert_allclose(whole, every, rtol=0, atol=1e-9)
    assert np.abs(every - one_box).max() > 0.5  # measured 0.99


@pytest.mark.slow
def test_whole_image_derivatives_are_every_pixel_traced_in_the_mode():
    """The shadow scene at 96 × 96: the Jacobian of the image with respect to the
    occluder's centre and radius (jacfwd) equals that of the mode traced at every pixel,
    and reverse mode (the chosen pixels' chunks recomputed, `trace.tiled`) agrees."""
    s = big("shadow")
    xy = _pixel_centres(s)

    def colours(v, whole):
        p = _with(s.params, centers=s.params.centers.at[0].set(v[:3]), radii=s.params.radii.at[0].set(v[3]))
        sc = rtjax.Scene(s.structure, p)
        if whole:
            return rtjax.render(sc, depth=0, edges=WIDTH).reshape(-1, 3)
        return rtjax.render_samples(sc, xy, depth=0, edges=WIDTH)

    v = jnp.concatenate([s.params.centers[0], s.params.radii[0][None]])
    with quick_xla(clear=True):  # compile time; these are checks of agreement, not bits
        whole = np.asarray(jax.jit(jax.jacfwd(lambda v: colours(v, True)))(v))
        every = np.asarray(jax.jit(jax.jacfwd(lambda v: colours(v, False)))(v))
        grad = np.asarray(jax.jit(jax.grad(lambda v: colours(v, True).mean()))(v))
    assert np.abs(every).max() > 100
    np.testing.assert_allclose(whole, every, rtol=0, atol=1e-6)
    np.testing.assert_allclose(grad, whole.reshape(-1, 4).mean(0), rtol=1e-9, atol=1e-12)
