"""The renderer against analytic pixels and the independent NumPy reference (rtjax.reference)."""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SCENES, first_hits, scene_from_text

import rtjax
from rtjax import reference

# An 11×11 image whose centre pixel looks exactly at the origin along +y.
CAMERA = """
eyep 0 -100 0
refp 0 0 0
vang 30 30
size 11
rend out.sunimg
"""


def centre(image):
    image = np.asarray(image)
    return image[image.shape[0] // 2, image.shape[1] // 2]


def test_opaque_sphere_lit_from_the_eye():
    """N = V = L at the centre: I = ke·d·L + (1−ke)·d·L + ks·L (cos γ = 1)."""
    deck = "sphe 0 0 0 10\nopaq 0.5 0.25 1 0.2 7\nplig 0 -1 0 200 100 50\nelig 0.3\nback 1 2 3\n" + CAMERA
    img = rtjax.render(scene_from_text(deck))
    d, ks, ke, light = np.array([0.5, 0.25, 1]), 0.2, 0.3, np.array([200, 100, 50])
    expect = ke * d * light + (1 - ke) * d * light + ks * light
    np.testing.assert_allclose(centre(img), np.minimum(expect, 255), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(img)[0, 0], [1, 2, 3])  # corner: background


def test_diffuse_falls_with_cosine():
    """A light at 60° from the normal at the centre pixel: diffuse ∝ cos 60° = ½, no highlight seen."""
    deck = "sphe 0 0 0 10\nopaq 1 1 1 0 1\nplig 0 -1 1.7320508075688772 200 200 200\nelig 0\n" + CAMERA
    c = centre(rtjax.render(scene_from_text(deck).astype(jnp.float64)))
    np.testing.assert_allclose(c, 100.0, rtol=1e-7)  # the deck is read as float32


def test_shadowed_point_gets_ambient_only():
    deck = (
        "sphe 0 0 0 10\nopaq 1 0.5 0.25 0.9 5\n"
        "sphe 0 -30 0 5\nopaq 0 0 0 0 1\n"  # between light and the big sphere's front
        "plig 0 -1 0 200 200 200\nelig 0.25\n"
        "eyep 100 -100 0\nrefp 0 0 0\nvang 30 30\nsize 11\nrend x.ras\n"
    )
    s = scene_from_text(deck)
    # the point (0, -10, 0) faces the light but sits in the small sphere's shadow
    lit = rtjax.render(s.replace(centers=np.array([[0, 0, 0], [0, -30, 40.0]])))
    shadowed = rtjax.render(s)
    ref = reference.render_reference(reference.parse_deck_text(deck)[0], depth=0)
    np.testing.assert_allclose(np.asarray(shadowed), ref, atol=0.05)
    assert not np.allclose(np.asarray(lit), np.asarray(shadowed))


def test_mirror_shows_what_it_reflects():
    """The centre ray meets a mirror head-on and comes back along −y, past the eye, onto
    the +y face of an opaque sphere behind the eye. That face looks at the light (+y),
    but the mirror itself shadows it: ambient only, ke·d·L."""
    deck = (
        "sphe 0 0 0 10\nmirr\nsphe 0 -300 0 50\nopaq 0.2 0.4 0.6 0 1\n"
        "plig 0 1 0 100 100 100\nelig 0.5\nback 0 0 0\n" + CAMERA
    )
    s = scene_from_text(deck)
    np.testing.assert_allclose(centre(rtjax.render(s, depth=1)), 0.5 * np.array([0.2, 0.4, 0.6]) * 100, rtol=1e-5)
    assert np.all(centre(rtjax.render(s, depth=0)) == 0)  # the reflected ray is past the depth: black
    ref = reference.render_reference(reference.parse_deck_text(deck)[0], depth=3)
    np.testing.assert_allclose(np.asarray(rtjax.render(s, depth=3)), ref, atol=0.05)


def test_invisible_glass():
    """kt = 1, n = 1: a glass sphere bends nothing and weighs kt² = 1; with ks = 0 it vanishes."""
    behind = "sphe 0 60 0 30\nopaq 0.3 0.6 0.9 0.5 10\nplig 0 -1 1 255 255 255\nelig 0.2\nback 10 20 30\n"
    with_glass = "sphe 0 0 0 10\ntrpa 1 1 0 1\n" + behind + CAMERA
    a = rtjax.render(scene_from_text(with_glass).astype(jnp.float64), depth=2)
    b = rtjax.render(scene_from_text(behind + CAMERA).astype(jnp.float64))
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-9)


def test_glass_weighs_kt_per_interface():
    deck = "sphe 0 0 0 10\ntrpa 0.5 1 0 1\nback 100 200 40\n" + CAMERA
    s = scene_from_text(deck)
    np.testing.assert_allclose(centre(rtjax.render(s, depth=2)), [25, 50, 10], rtol=1e-6)
    np.testing.assert_allclose(centre(rtjax.render(s, depth=1)), [0, 0, 0])  # second interface past the depth


def test_glass_reflects_its_fresnel_colour_from_outside():
    """`Params.fresnel` E: glass met from outside reflects F·E and passes (1 − F) of its
    transparent colour, F Schlick's reflectance; leaving the ball reflects nothing. n = 1.5
    at the centre pixel (normal incidence, no bending): F = ((n − 1)/(n + 1))² = 0.04. n = 1
    on every pixel (no bending): F = (1 − cos θ)^5, cos θ from NumPy's own ray–sphere
    intersection, so the rim tends to E."""
    back, e = np.array([100.0, 200.0, 40.0]), np.array([60.0, 90.0, 250.0])
    dense = scene_from_text("sphe 0 0 0 10\ntrpa 0.5 1.5 0 1\nback 100 200 40\n" + CAMERA).astype(jnp.float64)
    np.testing.assert_allclose(centre(rtjax.render(dense.replace(fresnel=e), depth=2)), 0.04 * e + 0.96 * 0.25 * back,
                               rtol=1e-12)
    s = scene_from_text("sphe 0 0 0 25\ntrpa 0.5 1 0 1\nback 100 200 40\n" + CAMERA).astype(jnp.float64)
    image = np.asarray(rtjax.render(s.replace(fresnel=e), depth=2))
    index, point, normal = first_hits(s)
    hit = index == 0
    d = np.where(hit[..., None], point - np.asarray(s.params.eye, np.float64), 1)  # the ray to each hit
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    f = np.where(hit, 1 - np.sum(-d * np.where(hit[..., None], normal, 0), -1), 0) ** 5
    expect = np.where(hit[..., None], f[..., None] * e + (1 - f[..., None]) * 0.25 * back, back)
    assert hit.sum() >= 40 and f[hit].max() > 0.05  # rim pixels where F matters
    np.testing.assert_allclose(image, expect, rtol=1e-9)


def test_no_lights_means_black_spheres():
    deck = "sphe 0 0 0 10\nopaq 1 1 1 1 1\nelig 1\nback 9 9 9\n" + CAMERA
    img = np.asarray(rtjax.render(scene_from_text(deck)))
    assert np.all(centre(img) == 0) and np.all(img[0, 0] == 9)


def test_clamped_not_rounded():
    deck = "sphe 0 0 0 10\nopaq 1 1 1 1 1\nplig 0 -1 0 255 255 255\nelig 0\n" + CAMERA
    img = np.asarray(rtjax.render(scene_from_text(deck)))
    assert img.max() == 255.0  # 255·1 + 255·1 clamps
    deck2 = "sphe 0 0 0 10\nopaq 0.5 0.5 0.5 0 1\nplig 0 -1 0 1 1 1\nelig 0\n" + CAMERA
    np.testing.assert_allclose(centre(rtjax.render(scene_from_text(deck2))), 0.5)  # not rounded to 0 or 1


def test_depth_default_and_model_only_what_is_needed():
    opaque = rtjax.parse_deck("sphe 0 0 0 1\nopaq 1 1 1 0 1\n" + CAMERA).frames[0].scene
    mirror = rtjax.parse_deck("sphe 0 0 0 1\nmirr\n" + CAMERA).frames[0].scene
    assert opaque.structure.default_depth == 0
    assert mirror.structure.default_depth == rtjax.DEFAULT_DEPTH
    # an opaque-only scene renders the same whatever depth is asked
    np.testing.assert_array_equal(np.asarray(rtjax.render(opaque, depth=7)), np.asarray(rtjax.render(opaque)))


def test_compiled_graph_follows_the_structure():
    """No Snell's law without glass, no shadow rays without lights, no chain without mirrors."""
    from rtjax.render import render_image, resolve_options

    def jaxpr_text(deck):
        s = rtjax.parse_deck(deck + CAMERA).frames[0].scene
        options = resolve_options(s, None, 1, None, 0.0, 1 << 17)
        return str(jax.make_jaxpr(lambda p: render_image(s.structure, p, options))(s.params))

    opaque = jaxpr_text("sphe 0 0 0 1\nopaq 1 1 1 0 1\n")
    assert "cond" not in opaque and "sqrt" in opaque
    lit = jaxpr_text("sphe 0 0 0 1\nopaq 1 1 1 0.5 2\nplig 1 1 1 9 9 9\n")
    mirror = jaxpr_text("sphe 0 0 0 1\nmirr\nplig 1 1 1 9 9 9\n")
    glass = jaxpr_text("sphe 0 0 0 1\ntrpa 0.9 1.5 0 1\nplig 1 1 1 9 9 9\n")
    assert "cond" in mirror and "cond" in glass
    # refraction adds η: a division by the index; shadow rays add a product over spheres
    assert glass.count("div") > mirror.count("div")
    assert lit.count("reduce_prod") > opaque.count("reduce_prod")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ex2s3.dat", "level1_opaque.dat", "level2_mirrors.dat", "level3_glass.dat"])
def test_matches_reference_on_scene_decks(name):
    """Quantised pixels within 2 levels of the float64 reference on ≥ 99.5 % of pixels."""
    path = os.path.join(SCENES, name)
    with open(path) as f:
        text = f.read()
    frame = reference.parse_deck_text(text)[0]
    scale = 0.5 if name != "ex2s3.dat" else 1.0
    frame.size = int(frame.size * scale)
    ref = reference.quantize(reference.render_reference(frame, depth=10))
    scene = rtjax.load_deck(path).frames[0].scene.resized(frame.size)
    ours = rtjax.images.to_uint8(rtjax.render(scene, depth=10))
    assert ours.shape == ref.shape
    off = np.abs(ours.astype(int) - ref.astype(int)).max(axis=-1)
    assert np.mean(off <= 2) >= 0.995, f"{np.mean(off <= 2):.4f} within 2 levels"
    assert np.mean(off == 0) >= 0.95


def test_float32_matches_float64():
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        scene = rtjax.parse_deck(f.read()).frames[0].scene.resized(100)
    a = np.asarray(rtjax.render(scene))
    b = np.asarray(rtjax.render(scene, dtype="float64"))
    assert a.dtype == np.float32 and b.dtype == np.float64
    off = np.abs(a - b).max(axis=-1)
    assert np.mean(off < 0.5) > 0.995 and np.median(off) < 1e-3


def test_supersampling_matches_reference():
    deck = "sphe 0 0 0 30\nopaq 1 0.5 0 0.3 10\nplig 1 -1 1 255 255 255\nelig 0.2\nback 0 0 100\n" + CAMERA.replace("size 11", "size 13")
    ours = np.asarray(rtjax.render(scene_from_text(deck).astype(jnp.float64), spp=3))
    ref = reference.render_reference(reference.parse_deck_text(deck)[0], spp=3)
    np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_tiles_do_not_change_the_image():
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        scene = rtjax.parse_deck(f.read()).frames[0].scene.resized(60).astype(jnp.float64)
    whole = np.asarray(rtjax.render(scene))
    tiled = np.asarray(rtjax.render(scene, tile=500))  # 8 tiles, the last one padded
    np.testing.assert_allclose(whole, tiled, atol=1e-9)


def test_tiles_past_the_count_are_skipped_and_the_others_differentiate_as_one():
    """`trace.tiled(..., count=k)` (the silhouette mode's chunks of chosen pixels): tiles
    holding rays before k run, later ones give zeros; values, jvp and vjp of the first
    k rays are those of the untiled function (reverse mode through the checkpointed,
    skipped tiles)."""
    from rtjax.trace import tiled

    def fn(a, b):  # per ray: (3, P) and (P,) outputs
        return a * jnp.sin(b), jnp.sum(a * a, axis=0) + b

    a = jnp.linspace(-1, 2, 30).reshape(3, 10)
    b = jnp.linspace(0.3, 1.1, 10)
    count = 5  # tiles of 4: rays 0–7 traced, 8–9 skipped
    out = tiled(fn, 4, a, b, count=count)
    ref = fn(a, b)
    for o, r in zip(out, ref):
        np.testing.assert_allclose(o[..., :8], r[..., :8], rtol=1e-12)
        assert np.all(np.asarray(o[..., 8:]) == 0)
    ta, tb = jnp.cos(a), jnp.sin(3 * b)
    for o, r in zip(jax.jvp(lambda a, b: tiled(fn, 4, a, b, count=count), (a, b), (ta, tb))[1], jax.jvp(fn, (a, b), (ta, tb))[1]):
        np.testing.assert_allclose(o[..., :count], r[..., :count], rtol=1e-12)

    def first(f):
        return lambda a, b: sum(jnp.sum(o[..., :count] ** 2) for o in f(a, b))

    got = jax.grad(first(lambda a, b: tiled(fn, 4, a, b, count=count)), argnums=(0, 1))(a, b)
    for g, r in zip(got, jax.grad(first(fn), argnums=(0, 1))(a, b)):
        np.testing.assert_allclose(g, r, rtol=1e-12)


def test_bad_render_options():
    s = scene_from_text("sphe 0 0 0 1\nopaq 1 1 1 0 1\n" + CAMERA)
    for kw in (dict(spp=0), dict(spp=2.5), dict(depth=-1), dict(dtype="int32"), dict(tile=0)):
        with pytest.raises(rtjax.RtjaxError):
            rtjax.render(s, **kw)
    for kw, message in ((dict(edges=1.0, subdivide=5), r"subdivide \(halvings of the box\) must be a whole number in \[0, 4\], not 5"),
                        (dict(edges=1.0, subdivide=1.5), "not 1.5"), (dict(edges=1.0, subdivide=-1), "not -1"),
                        (dict(subdivide=2), r"subdivide needs the silhouette-aware mode \(edges > 0\)")):
        for rendered in (rtjax.render, functools.partial(rtjax.render_samples, xy=np.ones((1, 2)))):
            with pytest.raises(rtjax.RtjaxError, match=message):
                rendered(s, **kw)
    for xy in (np.zeros((0, 2)), np.zeros(5), np.zeros((5, 3))):  # no positions was a ZeroDivisionError
        for sampled in (rtjax.render_samples, functools.partial(rtjax.edge_samples, edges=1.0)):
            with pytest.raises(rtjax.RtjaxError, match=r"xy must have shape \(K, 2\) with K ≥ 1"):
                sampled(s, xy)


def test_subdivide_defaults_to_sub_boxes_in_small_images():
    """`subdivide=None` (the default of `render` and the batched renders) resolves to
    16 × 16 sub-boxes where edges are (4 halvings: `trace.sub_box_levels`) in the
    silhouette-aware mode on images of at most 4,096 pixels, where a pixel often holds
    several edges, with mirrors and glass or without; to one box on larger images and
    without the mode; a given value is kept."""
    from rtjax.render import resolve_options

    def halvings(scene, edges=1.0, depth=None, subdivide=None):
        return resolve_options(scene, depth, 1, None, edges, None, subdivide).subdivide

    mirror = scene_from_text("sphe 0 0 0 10\nmirr\nsphe 0 30 0 5\nopaq 1 1 1 0 1\nplig 0 -1 0 200 100 50\n" + CAMERA)
    opaque = scene_from_text("sphe 0 0 0 10\nopaq 1 1 1 0 1\nplig 0 -1 0 200 100 50\n" + CAMERA)
    assert halvings(mirror) == 4 == halvings(mirror.resized(64))  # 11 × 11, 64 × 64 pixels
    assert halvings(mirror, depth=0) == halvings(opaque) == halvings(opaque.resized(64)) == 4
    assert halvings(mirror.resized(65)) == halvings(opaque.resized(65)) == 0  # 65 × 65 > 4096
    assert halvings(mirror, edges=0.0) == halvings(opaque, edges=0.0) == 0
    assert halvings(mirror, subdivide=0) == 0 and halvings(mirror, subdivide=True) == 1
    assert halvings(mirror.resized(200), subdivide=3) == 3
    # the default is that value's program: the same options key the same compiled render
    assert resolve_options(mirror, None, 1, None, 1.0, None, None) == resolve_options(mirror, None, 1, None, 1.0, None, 4)


def test_scene_changes_keep_the_structure():
    """`Scene.replace` takes arrays of the scene's own shapes (its structure fixes the
    number of spheres and lights: a (3, 3) centres array for one sphere rendered three
    spheres' worth of nothing it described); `resized` refuses an empty image; a field
    not set (occlusion) can be set and cleared."""
    s = scene_from_text("sphe 0 0 0 1\nopaq 1 1 1 0 1\n" + CAMERA)
    with pytest.raises(rtjax.RtjaxError, match=r"centers has shape \(3, 3\); this scene's is \(1, 3\)"):
        s.replace(centers=np.zeros((3, 3)))
    with pytest.raises(rtjax.RtjaxError, match="at least 1 pixel a side"):
        s.resized(0)
    moved = s.replace(centers=[[0.0, 1.0, 0.0]], ke=0.5, occlusion=[1.0])
    assert moved.params.centers.shape == (1, 3) and float(moved.params.ke) == 0.5
    assert moved.replace(occlusion=None).params.occlusion is None
    assert s.resized(5).structure.width == 5
