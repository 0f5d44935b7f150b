"""Numerical extremes (issue: derivatives you can trust): each in a test of its own, the
image and its derivatives with respect to every array leaf finite, float32 and float64,
forward and reverse mode, plain and (where edges matter) silhouette-aware.

Compile time is most of this file's cost (a jvp and a vjp of the silhouette-aware
render take XLA tens of seconds per dtype), so the scenes are built on few structures
(the same sphere kinds, light count, image size, depth and mode), and each structure
is compiled once per dtype and shared through the jit cache:

- one opaque sphere, plain (depth 0);
- glass then opaque (GLASS), depth 3, plain;
- opaque then mirror (MIRROR), depth 2, plain and silhouette-aware. The single sphere's
  silhouette-aware checks run here too, with a mirror behind the eye that no ray
  meets (`behind_the_eye`: the same image, checked), so that the mode's programs are
  compiled for one structure per dtype.

Images are 9 × 7, so that the centre pixel's ray runs exactly along the view (rays
through sphere centres need one).

The derivative checks compile with `jax_disable_most_optimizations` (`conftest.quick_xla`
says why that still checks the same program); the forward renders of
`test_scene_translated_by_1e4` are the optimised build's."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import linearised, quick_xla

import rtjax

SIZE = "size 9\n"  # 9 × 7: pixel (3, 4) is the centre one, its ray exactly along the view


def deck(body: str, camera: str = "eyep 0 -50 0\nrefp 0 0 0\nvang 40 30\n") -> rtjax.Scene:
    return rtjax.parse_deck(body + camera + SIZE + "rend x.ras\n").frames[0].scene


@functools.partial(jax.jit, static_argnames=("structure", "depth", "edges"))
def _image_jvp_vjp(params, tangent, cotangent, structure, depth, edges):
    """The image, J·t and Jᵀ·c for random t and c. A NaN or Inf anywhere in the Jacobian
    reaches J·t or Jᵀ·c (random directions do not cancel it), so these two products
    check every entry in both modes at the cost of one forward and one reverse pass
    (`conftest.linearised`: one program). Jitted by structure: the tests that share a
    structure share one compilation."""
    return linearised(lambda p: rtjax.render(rtjax.Scene(structure, p), depth=depth, edges=edges),
                      params, tangent, cotangent)


def assert_finite_everywhere(scene: rtjax.Scene, depth: int | None = None, edges: float = 0.0):
    depth = scene.structure.default_depth if depth is None else depth
    leaves, treedef = jax.tree_util.tree_flatten(scene.params)
    keys = jax.random.split(jax.random.key(0), len(leaves) + 1)
    for dtype in (jnp.float32, jnp.float64):
        s = scene.astype(dtype)
        tangent = jax.tree_util.tree_unflatten(treedef, [jax.random.normal(k, l.shape, dtype) for k, l in zip(keys, leaves)])
        cotangent = jax.random.normal(keys[-1], (s.structure.height, s.structure.width, 3), dtype)
        with quick_xla():  # valid for finiteness: see conftest.quick_xla; compiled only here
            image, jvp, grads = _image_jvp_vjp(s.params, tangent, cotangent, s.structure, depth, edges)
        name = jnp.dtype(dtype).name
        assert image.dtype == dtype and bool(jnp.all(jnp.isfinite(image))), f"image not finite ({name})"
        assert bool(jnp.all(jnp.isfinite(jvp))), f"forward-mode derivative not finite ({name})"
        bad = {jax.tree_util.keystr(k): int(jnp.sum(~jnp.isfinite(v))) for k, v in jax.tree_util.tree_leaves_with_path(grads)}
        assert not any(bad.values()), f"reverse-mode derivative not finite ({name}): {bad}"
    return image


LIT = "plig 0.3 -1 0.5 200 180 160\nelig 0.2\nback 10 20 30\n"
GLASS_DEPTH = 3  # glass then opaque: every GLASS scene is traced this deep
MIRROR_DEPTH = 2  # opaque then mirror


def glass(glass_sphere: str, material: str, opaque: str = "sphe 0 30 0 10\nopaq 1 0 0 0 1\n") -> rtjax.Scene:
    """A GLASS scene: a glass sphere, then an opaque one (the same structure for all)."""
    return deck(glass_sphere + material + opaque + LIT)


def primary_rays(scene: rtjax.Scene) -> tuple[np.ndarray, np.ndarray]:
    """The eye (3,) and every pixel's unit direction (H·W, 3, row-major) through its
    centre, from the renderer's own camera and the scene's own numbers, in float64."""
    p = scene.params
    _, d = rtjax.camera.primary_rays(p.eye, p.refp, p.vang, scene.structure.width, scene.structure.height, jnp.array([0.5, 0.5]))
    return np.asarray(p.eye, np.float64), np.asarray(d, np.float64).T


def pixel_ray(scene: rtjax.Scene, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
    """Eye and unit direction (float64) of pixel (row, col)'s ray through its centre."""
    eye, d = primary_rays(scene)
    return eye, d[row * scene.structure.width + col]


def first_hit(scene: rtjax.Scene, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
    """Where pixel (row, col)'s ray first meets sphere 0 from outside, and the unit
    normal there (float64)."""
    eye, d = pixel_ray(scene, row, col)
    c, r = np.asarray(scene.params.centers[0], np.float64), float(scene.params.radii[0])
    b = d @ (eye - c)
    t = -b - np.sqrt(b * b - (eye - c) @ (eye - c) + r * r)
    hit = eye + t * d
    return hit, (hit - c) / r


def light(direction: np.ndarray) -> str:
    return "plig {:.17g} {:.17g} {:.17g} 255 255 255\n".format(*direction)


def assert_glass_finite(scene: rtjax.Scene):
    assert scene.structure.kinds == ("trpa", "opaq")
    return assert_finite_everywhere(scene, depth=GLASS_DEPTH)


def assert_mirror_finite(scene: rtjax.Scene, edges: float):
    assert scene.structure.kinds == ("opaq", "mirr")
    return assert_finite_everywhere(scene, depth=MIRROR_DEPTH, edges=edges)


def behind_the_eye(scene: rtjax.Scene) -> rtjax.Scene:
    """A one-sphere scene as a MIRROR one: a mirror behind the eye (on the line from the
    point looked at through the eye, 1.6 times as far, radius a fifth of the distance),
    which no ray from the eye meets and which shadows nothing seen, so the image stays
    the one sphere's (checked here, plain renders)."""
    assert scene.structure.kinds == ("opaq",)
    p = scene.params
    eye, refp = np.asarray(p.eye, np.float64), np.asarray(p.refp, np.float64)
    centre, r = refp + 1.6 * (eye - refp), 0.2 * np.linalg.norm(eye - refp)
    text = rtjax.format_deck(scene, output="x.ras")  # parse → write → parse is the identity
    body, rend = text.rsplit("rend ", 1)
    mirror = "sphe {:.17g} {:.17g} {:.17g} {:.17g}\nmirr\n".format(*centre, r)
    mirrored = rtjax.parse_deck(body + mirror + "rend " + rend).frames[0].scene
    assert mirrored.structure.kinds == ("opaq", "mirr") and np.array_equal(mirrored.params.radii[:1], p.radii)
    # two programs, rounding apart: equal but where a ray is exactly tangent (the point of
    # `test_tangent_ray`), which may land on either side in each
    differ = np.abs(np.asarray(rtjax.render(mirrored, depth=MIRROR_DEPTH)) - np.asarray(rtjax.render(scene))).max(-1) > 1e-3
    assert differ.sum() <= 1, differ
    return mirrored


@pytest.mark.slow
@pytest.mark.parametrize("edges", [0.0, 1.0])
def test_tangent_ray(edges):
    # put the sphere's silhouette exactly on a pixel centre by aligning it with that
    # pixel's ray
    scene = deck("sphe 0 0 0 5\nopaq 1 0.5 0.2 0.3 10\n" + LIT)
    _, d = pixel_ray(scene, 3, 5)  # some pixel's ray
    eye = np.asarray(scene.params.eye)
    # radius = distance from the centre to that ray: the ray is exactly tangent
    r = np.linalg.norm(np.cross(-eye, d))
    scene = scene.replace(radii=np.array([r], np.float32))
    if edges:
        assert_mirror_finite(behind_the_eye(scene), edges=edges)
    else:
        assert_finite_everywhere(scene)


@pytest.mark.slow
def test_total_internal_reflection_onset_and_past_it():
    # The eye inside a glass sphere of n = 1.5, off its centre: a ray from the eye meets
    # the sphere from inside at incidence i, sin i = (distance from the centre to the
    # ray) / r, and is totally reflected where n·sin i > 1 (and again at every later
    # hit inside: the angle is kept). The centre lies 16 units from the eye, 56° off the
    # view axis, so that distance varies across the image, and r puts pixel (3, 4)'s ray
    # at the critical angle itself: the columns on one side leave the glass, those on
    # the other are totally reflected.
    n = 1.5
    centre = np.array([0.0, -50, 0]) + 16 * np.array([-np.sin(np.radians(56)), np.cos(np.radians(56)), 0])

    def scene(r: float) -> rtjax.Scene:
        return glass("sphe {:.17g} {:.17g} {:.17g} {:.17g}\n".format(*centre, r), f"trpa 0.9 {n} 0.2 10\n")

    eye, d = pixel_ray(scene(20.0), 3, 4)
    s = scene(n * np.linalg.norm(np.cross(centre - eye, d)))
    # n·sin i for every pixel, from the scene as parsed (float32 numbers) and its camera
    eye, d = primary_rays(s)
    c, r = np.asarray(s.params.centers[0], np.float64), float(s.params.radii[0])
    assert np.linalg.norm(c - eye) < r - 1  # the eye is inside: every primary ray leaves through the glass
    ratio = n * np.linalg.norm(np.cross(c - eye, d), axis=1) / r
    shape, onset = (s.structure.height, s.structure.width), 3 * s.structure.width + 4  # pixel (3, 4)
    tir = ratio > 1
    assert 10 <= tir.sum() <= ratio.size - 10, ratio.reshape(shape)  # both cases, in many pixels
    assert ratio.max() > 1.1 and ratio.min() < 0.8  # well past the critical angle, and well short of it
    assert abs(ratio[onset] - 1) < 1e-6, ratio[onset]  # and its onset, at pixel (3, 4)
    image = assert_glass_finite(s)
    # the render agrees: past the critical angle a ray never leaves the glass within the
    # depth and shows only the glass's highlight; short of it, it sees the background
    # through the glass (blue 0.9·30 = 27)
    blue = np.asarray(image)[..., 2].reshape(-1)
    assert blue[ratio < 0.999].min() > blue[ratio > 1.001].max() + 5, blue.reshape(shape)


@pytest.mark.slow
def test_n_equal_one():
    # an opaque sphere behind it, seen straight through (no bending at n = 1)
    assert_glass_finite(glass("sphe 0 0 0 10\n", "trpa 0.8 1 0.3 5\n"))


@pytest.mark.parametrize("kt", ["0", "1"])
def test_kt_extremes(kt):
    assert_glass_finite(glass("sphe 0 0 0 10\n", f"trpa {kt} 1.3 0.3 5\n", "sphe 0 30 0 10\nopaq 0 1 0 0.5 3\n"))


def test_ks_zero():
    assert_finite_everywhere(deck("sphe 0 0 0 10\nopaq 1 1 1 0 1\n" + LIT))


@pytest.mark.parametrize("beta", ["1", "10000"])
def test_beta_extremes(beta):
    assert_finite_everywhere(deck(f"sphe 0 0 0 10\nopaq 1 1 1 1 {beta}\n" + LIT))


def test_cos_gamma_zero_exactly():
    # at pixel (2, 5)'s hit point (normal N, V toward the eye), a light L with N·L > 0
    # whose reflection R_L = 2(N·L)N − L is perpendicular to V: cos γ = R_L·V = 0 there
    # (to rounding), the kink of max(cos γ, 0)^β (off the centre pixel, where N ∥ V)
    body = "sphe 0 0 0 10\nopaq 1 1 1 1 7\n"
    hit, n = first_hit(deck(body + LIT), 2, 5)
    v = np.asarray(deck(body + LIT).params.eye, np.float64) - hit
    v /= np.linalg.norm(v)
    reflected = n - (n @ v) * v  # ⟂ V, and R_L·N > 0
    reflected /= np.linalg.norm(reflected)
    lit = 2 * (n @ reflected) * n - reflected
    assert n @ lit > 0.1 and abs((2 * (n @ lit) * n - lit) @ v) < 1e-12
    assert_finite_everywhere(deck(body + light(lit)))


def test_light_grazing_the_surface():
    # N·L = 0 at pixel (3, 4)'s hit point (to rounding): the light is tangent there, and
    # the terminator crosses the image
    body = "sphe 0 0 0 10\nopaq 1 1 1 0.5 3\n"
    _, n = first_hit(deck(body + LIT), 3, 4)
    tangent = np.array([1.0, 0, 0]) - n[0] * n
    assert abs(n @ tangent) < 1e-12
    assert_finite_everywhere(deck(body + light(tangent / np.linalg.norm(tangent))))


def test_light_exactly_behind_the_eye():
    assert_finite_everywhere(deck("sphe 0 0 0 10\nopaq 1 1 1 0.5 3\nplig 0 -1 0 255 255 255\n"))


@pytest.mark.slow
@pytest.mark.parametrize("radius, distance", [("1e-3", "5e-3"), ("1e5", "3e5")])
def test_tiny_and_huge_spheres(radius, distance):
    scene = deck(f"sphe 0 0 0 {radius}\nopaq 1 0.5 0 0.4 10\n" + LIT, f"eyep 0 -{distance} 0\nrefp 0 0 0\nvang 40 30\n")
    image = assert_mirror_finite(behind_the_eye(scene), edges=1.0)
    assert float(image[3, 4, 0]) > 50  # the sphere is seen, lit, at the centre


@pytest.mark.slow
def test_scene_translated_by_1e4():
    body = "sphe {x} 0 0 10\nopaq 1 0.5 0 0.4 10\nsphe {x2} 0 -5 6\nmirr\nplig 0.3 -1 0.5 200 180 160\nelig 0.2\nback 10 20 30\n"
    cam = "eyep {x} -50 10\nrefp {x} 0 0\nvang 40 30\n"
    near = deck(body.format(x=0, x2=14), cam.format(x=0))
    far = deck(body.format(x=10000, x2=10014), cam.format(x=10000))
    assert_mirror_finite(far, edges=0.0)
    # self-intersection stays right: the translated scene looks the same (float64)
    a = np.asarray(rtjax.render(near.astype(jnp.float64), depth=MIRROR_DEPTH))
    b = np.asarray(rtjax.render(far.astype(jnp.float64), depth=MIRROR_DEPTH))
    np.testing.assert_allclose(a, b, atol=1e-6)
    # and in float32, no speckles of self-shadowing: nearly all pixels agree
    a32 = np.asarray(rtjax.render(near, depth=MIRROR_DEPTH))
    b32 = np.asarray(rtjax.render(far, depth=MIRROR_DEPTH))
    assert np.mean(np.abs(a32 - b32).max(-1) < 1) > 0.97


@pytest.mark.slow
def test_eye_inside_an_opaque_sphere():
    image = assert_mirror_finite(behind_the_eye(deck("sphe 0 -50 0 5\nopaq 1 0.5 0.2 0.5 5\n" + LIT)), edges=1.0)
    # inside: only ambient, ke·d·L summed over lights
    np.testing.assert_allclose(np.asarray(image)[3, 4], 0.2 * np.array([1, 0.5, 0.2]) * np.array([200, 180, 160]), rtol=1e-4)


def test_eye_inside_a_glass_sphere():
    assert_glass_finite(glass("sphe 0 -50 0 5\n", "trpa 0.8 1.4 0.3 5\n", "sphe 0 0 0 10\nopaq 1 1 0 0 1\n"))


@pytest.mark.slow
def test_two_spheres_touching():
    scene = deck("sphe -5 0 0 5\nopaq 1 0 0 0.3 5\nsphe 5 0 0 5\nmirr\n" + LIT)
    assert_mirror_finite(scene, edges=1.0)


@pytest.mark.slow
def test_sphere_behind_the_eye():
    scene = deck("sphe 0 -80 0 10\nopaq 1 0 0 0.3 5\nsphe 0 0 0 5\nmirr\n" + LIT)
    image = assert_mirror_finite(scene, edges=1.0)
    assert float(np.asarray(image)[3, 4, 0]) > 0  # seen in the mirror


@pytest.mark.slow
def test_rays_through_sphere_centres():
    # the centre pixel's ray runs exactly through sphere 0's centre (the apex of its
    # outline cone, where the distance to the outline has no rate), and so does the
    # shadow ray from the hit toward the light, through the centre of the mirror behind
    # the eye: each edge lies beyond the box all round (`edges._signed`), not at δ = 0
    scene = deck("sphe 0 0 0 5\nopaq 1 0.5 0.2 0.3 10\nsphe 0 -80 0 10\nmirr\nplig 0 -1 0 200 180 160\nelig 0.2\n"
                 "back 10 20 30\n")
    eye, d = pixel_ray(scene, 3, 4)
    assert np.array_equal(d, [0, 1, 0]) and np.array_equal(eye, [0, -50, 0])  # exactly along the view
    image = assert_mirror_finite(scene, edges=1.0)
    # the box lies on sphere 0 and wholly in the mirror's shadow: ambient alone, ke·d·L
    np.testing.assert_allclose(np.asarray(image)[3, 4], 0.2 * np.array([1, 0.5, 0.2]) * np.array([200, 180, 160]), rtol=1e-6)


@pytest.mark.slow
def test_eye_on_the_z_axis_looking_down():
    scene = deck("sphe 0 0 0 5\nopaq 1 0 0 0.3 5\n" + LIT, "eyep 0 0 50\nrefp 0 0 0\nvang 40 30\n")
    assert_mirror_finite(behind_the_eye(scene), edges=1.0)
