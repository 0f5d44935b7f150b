"""Level 4, texture-mapped spheres (`tmap`, DECK.md §4).

(u, v) = (atan2(p_y, p_x)/(2π) + ½, acos(p_z)/π) for the outward unit normal p; the
texel there, bilinear between texel centres ((x + ½)/w, (y + ½)/h), columns wrapping,
rows clamped, divided by 255, is the diffuse colour d of the opaque formula.

Most tests use `elig 1` and `ks 0`: the opaque formula is then I = d·L exactly
(the ambient term is ke·d·L and the diffuse one carries 1 − ke = 0), so with a light
of 255 a pixel shows the texel value itself, whatever the geometry.

The checks are tolerances and the compile is most of their cost: the module runs under
XLA's quick build (`conftest.quick_build`, which says why that checks the same program).
"""

from __future__ import annotations

import importlib.util
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, SCENES

import rtjax
from rtjax import reference
from rtjax.images import load_image, save_image, to_uint8
from rtjax.sunraster import write_sunraster
from rtjax.textures import bilinear, fast_atan2, sphere_uv, texture_colour, textured_diffuse

pytestmark = pytest.mark.usefixtures("quick_build")

# --------------------------------------------------------------------------------------
# A texture whose texels encode their own coordinates: R = 10 + 30x, G = 20 + 40y, B = 5x².
# B is not linear in x, so the seam (columns 7 and 0) and the middle (3 and 4) differ.
W, H = 8, 4


def coord_texture(w=W, h=H) -> np.ndarray:
    y, x = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return np.stack([10 + 30 * x, 20 + 40 * y, 5 * x * x], axis=-1).astype(np.float64)


def expected(x: float, y: float, w=W, h=H) -> np.ndarray:
    """The bilinear value at texture coordinates x = u·w − ½, y = v·h − ½, written out."""
    t = coord_texture(w, h)
    y = min(max(y, 0.0), h - 1.0)
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0
    c0, c1 = x0 % w, (x0 + 1) % w
    r0, r1 = y0, min(y0 + 1, h - 1)
    return (1 - fy) * ((1 - fx) * t[r0, c0] + fx * t[r0, c1]) + fy * ((1 - fx) * t[r1, c0] + fx * t[r1, c1])


def unit(lon_deg: float, colat_deg: float) -> np.ndarray:
    lon, colat = np.radians(lon_deg), np.radians(colat_deg)
    return np.array([np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon), np.cos(colat)])


# point name → (unit p, expected value in 0..255)
KNOWN = {
    # north pole: v = 0, the top row (clamped); longitude undefined, u = ½ (atan2(0, 0) = 0)
    "north pole": (np.array([0.0, 0.0, 1.0]), [115.0, 20.0, (45 + 80) / 2]),
    # south pole: the bottom row
    "south pole": (np.array([0.0, 0.0, -1.0]), [115.0, 140.0, (45 + 80) / 2]),
    # the seam (−x): u = 0 ≡ 1, halfway between the last column and the first
    "seam": (np.array([-1.0, 0.0, 0.0]), [(220 + 10) / 2, 80.0, (245 + 0) / 2]),
    "seam, y = −0": (np.array([-1.0, -0.0, 0.0]), [(220 + 10) / 2, 80.0, (245 + 0) / 2]),
    # +x on the equator: u = ½, v = ½
    "+x": (np.array([1.0, 0.0, 0.0]), [(100 + 130) / 2, 80.0, (45 + 80) / 2]),
    # −y: u = ¼ (x = 1.5), +y: u = ¾ (x = 5.5)
    "-y": (np.array([0.0, -1.0, 0.0]), [(40 + 70) / 2, 80.0, (5 + 20) / 2]),
    "+y": (np.array([0.0, 1.0, 0.0]), [(160 + 190) / 2, 80.0, (125 + 180) / 2]),
    # the centre of texel (x, y) = (2, 1): u = 2.5/8, v = 1.5/4, the texel itself
    "texel (2, 1)": (unit(360 * 2.5 / 8 - 180, 180 * 1.5 / 4), [70.0, 60.0, 20.0]),
    # between the pole and the first row's centres (v < ½/h): rows clamp, row 0 only
    "near the pole": (unit(360 * 6.25 / 8 - 180, 180 * 0.2 / 4), [10 + 30 * 5.75, 20.0, 0.25 * 125 + 0.75 * 180]),
}


@pytest.mark.parametrize("name", list(KNOWN))
def test_known_points_read_their_texels(name):
    p, value = KNOWN[name]
    got = np.asarray(jax.jit(texture_colour)(jnp.asarray(coord_texture()), jnp.asarray(p)[:, None]))[:, 0] * 255
    np.testing.assert_allclose(got, value, rtol=0, atol=1e-9)
    # the reference agrees (it is the yardstick of the render tests)
    np.testing.assert_allclose(reference.sample_texture(coord_texture(), p[None])[0] * 255, value, atol=1e-9)


def test_uv_conventions():
    p = jnp.asarray(np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [0, 1, 0], [-1, 1e-12, 0], [-1, -1e-12, 0]], float).T)
    u, v = (np.asarray(a) for a in sphere_uv(p))
    np.testing.assert_allclose(v, [0, 1, 0.5, 0.5, 0.5, 0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose(u[2:], [0.5, 0.25, 0.75, 1, 0], atol=1e-9)
    # v is acos(p_z)/π for any unit p, and (u, v) do not depend on |p|
    rng = np.random.default_rng(0)
    q = rng.normal(size=(3, 50))
    qn = q / np.linalg.norm(q, axis=0)
    u1, v1 = sphere_uv(jnp.asarray(qn))
    u2, v2 = sphere_uv(jnp.asarray(3.7 * qn))
    np.testing.assert_allclose(np.asarray(v1), np.arccos(qn[2]) / np.pi, atol=1e-12)
    np.testing.assert_allclose(np.asarray(u1), np.arctan2(qn[1], qn[0]) / (2 * np.pi) + 0.5, atol=1e-12)
    np.testing.assert_allclose(np.asarray(u2), np.asarray(u1), atol=1e-12)
    np.testing.assert_allclose(np.asarray(v2), np.asarray(v1), atol=1e-12)


def test_fast_atan2_in_float32():
    """float32 angles come from a polynomial: within 3e-7 rad of atan2 (u within 5e-8,
    far below a texel), exact at the axes, finite derivatives everywhere (also at 0, 0)."""
    rng = np.random.default_rng(6)
    y = np.concatenate([rng.normal(size=20000), rng.normal(size=100) * 1e-30, [0, 0, 1, -1, 1, 0, -0.0, 3, -3]])
    x = np.concatenate([rng.normal(size=20000), rng.normal(size=100) * 1e-30, [0, 1, 0, 0, -1, -1, -1, 3, -3]])
    got = np.asarray(jax.jit(fast_atan2)(jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32)), float)
    want = np.arctan2(y.astype(np.float32).astype(float), x.astype(np.float32).astype(float))
    off = np.abs(got - want)
    off = np.minimum(off, 2 * np.pi - off)  # ±π on the branch cut is the same angle
    assert off.max() < 3e-7
    np.testing.assert_allclose(got[-9:-3], [0, 0, np.pi / 2, -np.pi / 2, np.pi * 3 / 4, np.pi], atol=3e-7)
    g = jax.jit(jax.vmap(jax.grad(fast_atan2, argnums=(0, 1))))(jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32))
    assert all(np.all(np.isfinite(np.asarray(a))) for a in g)
    r2 = x[:20000] ** 2 + y[:20000] ** 2
    np.testing.assert_allclose(np.asarray(g[0])[:20000] * r2, x[:20000], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(g[1])[:20000] * r2, -y[:20000], rtol=1e-5, atol=1e-6)


def test_bilinear_between_texel_centres():
    rng = np.random.default_rng(1)
    for h, w in ((3, 5), (4, 8), (1, 1), (2, 7)):
        t = rng.uniform(0, 255, size=(h, w, 3))
        t_coord = None
        x = rng.uniform(-0.5, w - 0.5, 40)
        y = rng.uniform(-0.5, h - 0.5, 40)
        x[:3], y[:3] = [-0.5, w - 0.5, 0.0], [-0.5, h - 0.5, 0.0]  # the seam, both poles, a centre
        got = np.asarray(jax.jit(bilinear)(jnp.asarray(t), jnp.asarray((x + 0.5) / w), jnp.asarray((y + 0.5) / h)))
        for k in range(len(x)):
            yc = min(max(y[k], 0), h - 1)
            x0, y0 = int(np.floor(x[k])), int(np.floor(yc))
            fx, fy = x[k] - x0, yc - y0
            r1 = min(y0 + 1, h - 1)
            want = (1 - fy) * ((1 - fx) * t[y0, x0 % w] + fx * t[y0, (x0 + 1) % w]) + fy * (
                (1 - fx) * t[r1, x0 % w] + fx * t[r1, (x0 + 1) % w]
            )
            np.testing.assert_allclose(got[k], want, atol=1e-9)
        del t_coord
    # at texel centres, the texel itself
    t = rng.uniform(0, 255, size=(3, 5, 3))
    yy, xx = np.meshgrid(np.arange(3), np.arange(5), indexing="ij")
    got = np.asarray(bilinear(jnp.asarray(t), jnp.asarray((xx.ravel() + 0.5) / 5), jnp.asarray((yy.ravel() + 0.5) / 3)))
    np.testing.assert_allclose(got, t.reshape(-1, 3), atol=1e-9)


def test_several_textures_in_one_pass_match_one_at_a_time():
    rng = np.random.default_rng(2)
    textures = [jnp.asarray(rng.uniform(0, 255, size=s + (3,))) for s in ((3, 5), (4, 8), (7, 2), (1, 1))]
    p = jnp.asarray(rng.normal(size=(3, 200)))
    which = rng.integers(-1, 4, size=200)
    d = rng.uniform(size=(3, 200))
    got = np.asarray(jax.jit(textured_diffuse)(textures, jnp.asarray(which, jnp.int32), p, jnp.asarray(d)))
    want = d.copy()
    for i, t in enumerate(textures):
        want[:, which == i] = np.asarray(jax.jit(texture_colour)(t, p))[:, which == i]
    np.testing.assert_allclose(got, want, atol=1e-12)


# --------------------------------------------------------------------------------------
# Decks with textures (files in a temporary folder). Compiling a render costs seconds
# here, so tests share scene structures and vary only parameters where they can.


def write_deck(folder, text, name="deck.dat"):
    path = os.path.join(folder, name)
    with open(path, "w") as f:
        f.write(text)
    return path


@pytest.fixture(scope="module")
def tex_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("textures")
    write_sunraster(d / "coord.sunimg", coord_texture().astype(np.uint8))
    save_image(d / "coord.png", coord_texture())
    rng = np.random.default_rng(3)
    for name, shape in (("a.sunimg", (3, 5)), ("b.ras", (16, 8)), ("c.sunimg", (7, 2))):
        write_sunraster(d / name, rng.integers(0, 256, size=shape + (3,), dtype=np.uint8))
    save_image(d / "odd.png", rng.integers(0, 256, size=(3, 5, 3), dtype=np.uint8))
    write_sunraster(d / "odd.sunimg", load_image(d / "odd.png").astype(np.uint8))
    return d


# One textured sphere at the origin, one light; 23 × 17 pixels, the centre pixel (8, 11)
# looks exactly at refp. Shared by the known-point, parameter and derivative tests.
ONE = (
    "sphe 0 0 0 10\ntmap coord.sunimg\nplig 0.2 -0.3 1 255 255 255\nelig 1\n"
    "eyep 0 -100 0\nrefp 0 0 0\nvang 24 18\nsize 23\nrend out.sunimg\n"
)


@pytest.fixture(scope="module")
def one(tex_dir) -> rtjax.Scene:
    scene = rtjax.load_deck(write_deck(tex_dir, ONE, "one.dat")).frames[0].scene.astype(jnp.float64)
    assert (scene.structure.height, scene.structure.width) == (17, 23)
    return scene


def centre(img):
    img = np.asarray(img)
    return img[img.shape[0] // 2, img.shape[1] // 2]


# eye direction → the point of the unit sphere the centre pixel sees (p = eye/|eye|)
VIEWS = {
    "north pole": "0 0 100",
    "south pole": "0 0 -100",
    "seam": "-100 0 0",
    "+x": "100 0 0",
    "-y": "0 -100 0",
    "+y": "0 100 0",
}


def eye(name):
    return np.array(VIEWS[name].split(), float)


def on_row(value, row, tol=1e-6):
    """Is `value` the colour of the coordinate texture's row `row`, interpolated between
    two neighbouring columns (wrapping) at SOME longitude?"""
    t = coord_texture()[row]
    for c in range(W):
        a, b = t[c], t[(c + 1) % W]
        f = np.clip(np.dot(value - a, b - a) / np.dot(b - a, b - a), 0, 1)
        if np.max(np.abs(a + f * (b - a) - value)) < tol:
            return True
    return False


def test_known_points_in_a_render(one):
    """A sphere at the origin seen head-on from six directions: the centre pixel is the
    texel value at p = eye/|eye| (elig 1, ks 0, L = 255: I = d·255).

    At a pole longitude is undefined: a rendered hit lies within rounding of the pole,
    at an arbitrary longitude, so the pixel is the top (bottom) row's colour at some u."""
    for name in VIEWS:
        got = centre(rtjax.render(one.replace(eye=eye(name))))
        if "pole" in name:
            assert got[1] == pytest.approx(KNOWN[name][1][1], abs=1e-6), name
            assert on_row(got, 0 if name == "north pole" else H - 1), (name, got)
        else:
            np.testing.assert_allclose(got, KNOWN[name][1], atol=1e-6, err_msg=name)


def test_texels_are_parameters(one):
    """The image is linear in the texels (a texture can be fitted): half the texels,
    half the image (no specular term here)."""
    scene = one.replace(ke=0.3)
    t = np.asarray(scene.params.textures[0])
    img = np.asarray(rtjax.render(scene))
    half = np.asarray(rtjax.render(scene.replace(textures=(t / 2,))))
    on = np.any(img > 0, axis=-1)
    assert 50 < on.sum() < on.size
    np.testing.assert_allclose(half[on], img[on] / 2, atol=1e-9)


def test_sun_raster_and_png_textures_give_the_same_image(tex_dir):
    np.testing.assert_array_equal(load_image(tex_dir / "odd.png"), load_image(tex_dir / "odd.sunimg"))
    np.testing.assert_array_equal(load_image(tex_dir / "coord.png"), load_image(tex_dir / "coord.sunimg"))
    deck = (
        "sphe 0 0 0 10\ntmap {a} 0.3 12\nsphe 14 6 -4 5\ntmap {b}\nplig 1 -2 1.5 250 240 230\nelig 0.2\nback 5 10 40\n"
        "eyep 10 -60 25\nrefp 3 0 0\nvang 40 30\nsize 24\nrend out.sunimg\n"
    )
    images = []
    for ext in ("sunimg", "png"):
        text = deck.format(a=f"odd.{ext}", b=f"coord.{ext}")
        images.append(to_uint8(rtjax.render(rtjax.load_deck(write_deck(tex_dir, text, f"{ext}.dat")).frames[0].scene)))
    np.testing.assert_array_equal(images[0], images[1])
    assert len(np.unique(images[0].reshape(-1, 3), axis=0)) > 30  # textured, not flat


def compare_with_reference(path, depth=None, min_within=0.99, text=None, scene=None):
    """Our quantised render against the reference's: ≥ `min_within` of the pixels within
    2 levels. `text` (optional) replaces the file's deck text, textures still read
    relative to the file's folder; `scene` (optional) is what we render instead of it."""
    if text is None:
        with open(path) as f:
            text = f.read()
    folder = os.path.dirname(os.path.abspath(path))
    frame = reference.parse_deck_text(text, folder)[0]
    if scene is None:
        scene = rtjax.parse_deck(text, os.path.basename(path), folder, load_image).frames[0].scene
    ref = reference.quantize(reference.render_reference(frame, depth=rtjax.DEFAULT_DEPTH if depth is None else depth))
    ours = to_uint8(rtjax.render(scene, depth=depth))
    assert ours.shape == ref.shape
    off = np.abs(ours.astype(int) - ref.astype(int)).max(axis=-1)
    assert np.mean(off <= 2) >= min_within, f"{np.mean(off <= 2):.4f} within 2 levels"
    return ours, ref


def test_several_textures_of_different_sizes_in_one_scene(tex_dir):
    """Four textured spheres, three sizes (one texture used twice), against the reference;
    each sphere's −y point (u = ¼, v = ½) seen head-on with ke = 1 is its own texture's."""
    deck = (
        "sphe -12 0 0 5\ntmap a.sunimg\n"
        "sphe 0 0 0 5\ntmap b.ras 0.4 20\n"
        "sphe 12 0 0 5\ntmap c.sunimg\n"
        "sphe 0 0 12 5\ntmap a.sunimg 0.2 5\n"
        "sphe 0 10 -1000 990\nopaq 0.6 0.7 0.8 0 1\n"
        "plig -1 -2 3 255 255 255\nelig 0.3\nback 10 20 30\n"
        "eyep 4 -70 20\nrefp 0 0 3\nvang 50 39\nsize 33\nrend out.sunimg\n"
    )
    path = write_deck(tex_dir, deck, "four.dat")
    scene = rtjax.load_deck(path).frames[0].scene
    assert scene.structure.texture_shapes == ((3, 5), (16, 8), (7, 2), (3, 5))
    assert (scene.structure.height, scene.structure.width) == (25, 33)
    compare_with_reference(path)
    flat = scene.replace(ke=1.0, ks=np.zeros(5), light_colors=np.array([[255.0, 255, 255]]))
    for i, (cx, cz) in enumerate(((-12, 0), (0, 0), (12, 0), (0, 12))):
        s = flat.replace(eye=np.array([cx, -100.0, cz]), refp=np.array([cx, 0.0, cz]))
        tx = np.asarray(s.params.textures[i])
        want = reference.sample_texture(tx, np.array([[0.0, -1, 0]]))[0] * 255
        np.testing.assert_allclose(centre(rtjax.render(s)), want, atol=2e-3, err_msg=f"sphere {i}")


def test_level4_deck_matches_reference():
    """The repository's Level 4 deck (textures made by scripts/make_textures.py), at 1/4 size."""
    path = os.path.join(SCENES, "level4_textures.dat")
    s = rtjax.load_deck(path).frames[0].scene.structure
    assert s.kinds.count("tmap") >= 2 and len(set(s.texture_shapes)) >= 2
    with open(path) as f:
        text = f.read()
    assert "size 320" in text
    compare_with_reference(path, depth=4, text=text.replace("size 320", "size 80"))


def test_textured_spheres_cast_shadows(tex_dir):
    """The floor under a textured sphere is in its full shadow (S = 0: ambient only);
    moved away, the sphere casts none there."""
    floor = "sphe 0 0 -1000 1000\nopaq 0.8 0.7 0.6 0 1\n"
    ball = "sphe 0 0 8 6\n{}\n"
    rest = "plig 0.3 0.2 1 255 255 255\nelig 0.2\nback 0 0 50\neyep 0 -60 40\nrefp 0 0 3\nvang 40 40\nsize 24\nrend o.sunimg\n"
    path = write_deck(tex_dir, floor + ball.format("tmap coord.sunimg") + rest, "shadow.dat")
    scene = rtjax.load_deck(path).frames[0].scene
    a = np.asarray(rtjax.render(scene))
    c = np.asarray(rtjax.render(scene.replace(centers=np.array([[0, 0, -1000], [0, 0, 5000.0]]))))  # the ball far above
    # where the ball itself is seen: the reference's render of the ball alone, fully lit
    alone = reference.parse_deck_text(ball.format("opaq 1 1 1 0 1") + rest.replace("elig 0.2", "elig 1"))[0]
    on_ball = reference.render_reference(alone, depth=0)[..., 0] > 1
    assert 10 <= on_ball.sum() <= 0.5 * on_ball.size
    shadow = ~on_ball & np.any(np.abs(a - c) > 1e-3, axis=-1)  # floor pixels the ball changes
    assert shadow.sum() >= 10
    np.testing.assert_allclose(a[shadow], np.broadcast_to(0.2 * np.array([0.8, 0.7, 0.6]) * 255, a[shadow].shape), atol=1e-3)
    compare_with_reference(path, scene=scene)


def test_textured_spheres_appear_in_mirrors_and_through_glass(tex_dir):
    """The centre ray meets a mirror head-on, comes back along −y past the eye and meets
    a textured sphere at its +y point (u = ¾, v = ½); through a glass sphere (n = 1,
    kt = 0.5, ks = 0) the same texel shows at kt² = ¼. One structure, spheres moved."""
    deck = (
        "sphe 0 -300 0 50\ntmap coord.sunimg\nsphe 0 0 0 10\nmirr\nsphe 0 500 500 10\ntrpa 0.5 1 0 1\n"
        "plig 0 0 1 255 255 255\nelig 1\nback 0 0 0\neyep 0 -100 0\nrefp 0 0 0\nvang 20 20\nsize 11\nrend o.sunimg\n"
    )
    path = write_deck(tex_dir, deck, "mirror.dat")
    scene = rtjax.load_deck(path).frames[0].scene
    mirror = scene.astype(jnp.float64)
    np.testing.assert_allclose(centre(rtjax.render(mirror, depth=2)), KNOWN["+y"][1], atol=1e-6)
    glass = mirror.replace(centers=np.array([[0, -300, 0], [0, 500, 500], [0, 0, 0.0]]), eye=np.array([0, 100, 0.0]))
    np.testing.assert_allclose(centre(rtjax.render(glass, depth=2)), 0.25 * np.array(KNOWN["+y"][1]), atol=1e-6)
    compare_with_reference(path, depth=2, scene=mirror)


def test_missing_or_unreadable_texture_is_a_deck_error(tex_dir, monkeypatch):
    missing = write_deck(tex_dir, "# a deck\nsphe 0 0 0 1\ntmap sub/nope.sunimg\n" + ONE[ONE.index("plig") :], "missing.dat")
    with pytest.raises(rtjax.DeckError) as e:
        rtjax.load_deck(missing)
    msg = str(e.value)
    assert msg.startswith("missing.dat:3:") and "sub/nope.sunimg" in msg
    (tex_dir / "junk.sunimg").write_bytes(b"\x59\xa6\x6a\x95 not a raster")
    junk = write_deck(tex_dir, "sphe 0 0 0 1\nopaq 1 1 1 0 1\nsphe 0 0 3 1\ntmap junk.sunimg 0.5 3\n" + ONE[ONE.index("plig") :], "junk.dat")
    with pytest.raises(rtjax.DeckError) as e:
        rtjax.load_deck(junk)
    assert str(e.value).startswith("junk.dat:4:") and "junk.sunimg" in str(e.value)
    # textures are found relative to the deck's folder, not the working directory
    monkeypatch.chdir(ROOT)
    assert rtjax.load_deck(os.path.join(tex_dir, "one.dat")).frames[0].scene.structure.texture_shapes == ((H, W),)


def test_scenes_without_textures_compile_no_texture_code(tex_dir):
    """The texture code's marks in the traced render: atan2 (float64; float32 uses a
    polynomial), and floor and rem (the bilinear lookup) in both."""

    def jaxpr(scene, dtype):
        scene = scene.astype(dtype)
        return str(jax.make_jaxpr(lambda p: rtjax.render(rtjax.Scene(scene.structure, p)))(scene.params))

    def marks(text):
        return {m for m in ("atan2", "floor", "rem") if re.search(rf"= {m}\b", text)}

    rest = "plig 1 -1 1 200 200 200\nelig 0.2\neyep 0 -30 0\nrefp 0 0 0\nvang 20 20\nsize 5\nrend o.sunimg\n"
    plain = rtjax.load_deck(write_deck(tex_dir, "sphe 0 0 0 5\nopaq 1 0 0 0.3 9\nsphe 7 3 0 2\nopaq 0 1 0 0 1\n" + rest, "p.dat")).frames[0].scene
    textured = rtjax.load_deck(write_deck(tex_dir, "sphe 0 0 0 5\ntmap coord.sunimg 0.3 9\nsphe 7 3 0 2\nopaq 0 1 0 0 1\n" + rest, "t.dat")).frames[0].scene
    assert marks(jaxpr(plain, jnp.float64)) == marks(jaxpr(plain, jnp.float32)) == set()
    assert marks(jaxpr(textured, jnp.float64)) == {"atan2", "floor", "rem"}
    assert marks(jaxpr(textured, jnp.float32)) == {"floor", "rem"}


# --------------------------------------------------------------------------------------
# Derivatives (float64; conftest enables x64)


def test_texture_lookup_derivatives_are_finite_at_poles_and_seam():
    """jacfwd and jacrev of the lookup in the point and in the texels, at both poles, on
    the seam (y = +0 and −0) and at p = 0 (a lane whose colour is discarded)."""
    names = ["north pole", "south pole", "seam", "seam, y = −0", "+x"]
    p0 = jnp.asarray(np.stack([KNOWN[n][0] for n in names] + [np.zeros(3)], axis=1))
    t0 = jnp.asarray(coord_texture())
    which = jnp.zeros(p0.shape[1], jnp.int32)

    def f(p, t):
        return textured_diffuse((t,), which, p, jnp.zeros_like(p))

    jf = jax.jit(jax.jacfwd(f, argnums=(0, 1)))(p0, t0)
    jr = jax.jit(jax.jacrev(f, argnums=(0, 1)))(p0, t0)
    for a, b in zip(jf, jr):
        assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert np.abs(np.asarray(jf[1])).sum() > 0
    # on the seam the longitude derivative is the ordinary one: d u / d p_y = −1/(2π) at
    # p = (−1, 0, 0), and R jumps from column 7 (220) to column 0 (10) across it: 8·210
    # per unit of u, so d R / d p_y = 8·210/(2π) per 255
    jp = np.asarray(jf[0])  # (3, P, 3, P)
    for k in (2, 3):
        assert jp[0, k, 1, k] == pytest.approx(8 * 210 / (2 * np.pi) / 255, rel=1e-9)


@pytest.mark.parametrize("where", ["north pole", "seam"])
def test_render_derivatives_are_finite_at_poles_and_seam(one, where):
    """The centre pixel hits the pole / the seam: grad and jacfwd in the centre, radius
    and texels of the textured sphere are finite, and those in the texels nonzero."""
    scene = one.replace(eye=eye(where), ke=0.3, ks=np.array([0.3]), beta=np.array([7.0]))
    s, p = scene.structure, scene.params

    def img(c, r, t):
        return rtjax.render(rtjax.Scene(s, p).replace(centers=c, radii=r, textures=(t,)))

    args = (p.centers, p.radii, p.textures[0])
    g = jax.grad(lambda *a: jnp.sum(img(*a)[8, 11]), argnums=(0, 1, 2))(*args)
    assert all(np.all(np.isfinite(x)) for x in g)
    assert np.abs(g[2]).sum() > 0
    j = jax.jacfwd(img, argnums=(0, 1, 2))(*args)
    assert all(np.all(np.isfinite(x)) for x in j)
    assert all(np.abs(np.asarray(x)).sum() > 0 for x in j)


def test_gradients_match_finite_differences(one):
    """float64: the derivative of a weighted sum of interior pixels (no silhouette, no
    shadow edge) in the texels and in the textured sphere's centre and radius, against
    central differences; forward mode (jacfwd) agrees with reverse mode (grad)."""
    scene = one.replace(centers=np.array([[0.31, 0.17, -0.23]]), ke=0.25, eye=np.array([3, -45, 11.0]), light_dirs=np.array([[0.6, -1, 0.8]]))
    s, p = scene.structure, scene.params
    base = np.asarray(rtjax.render(scene))
    inside = np.zeros(base.shape[:2], bool)
    inside[4:13, 7:16] = True  # well inside the disc (radius ≈ 9 px here)
    assert np.all(np.any(base[inside] != base[0, 0], axis=-1))
    wts = jnp.asarray(np.random.default_rng(4).uniform(size=base.shape) * inside[..., None])

    def loss(c, r, t):
        return jnp.sum(wts * rtjax.render(rtjax.Scene(s, p).replace(centers=c, radii=r, textures=(t,))))

    args = [p.centers, p.radii, p.textures[0]]
    grads = jax.grad(loss, argnums=(0, 1, 2))(*args)
    jac = jax.jacfwd(loss, argnums=(0, 1, 2))(*args)
    rng = np.random.default_rng(5)
    for i, h in ((0, 1e-5), (1, 1e-5), (2, 1e-3)):
        np.testing.assert_allclose(np.asarray(jac[i]), np.asarray(grads[i]), rtol=1e-9, atol=1e-9)
        direction = rng.normal(size=np.shape(args[i]))
        plus, minus = list(args), list(args)
        plus[i] = args[i] + h * direction
        minus[i] = args[i] - h * direction
        fd = (loss(*plus) - loss(*minus)) / (2 * h)
        ad = float(np.sum(np.asarray(grads[i]) * direction))
        assert abs(ad) > 1e-3
        np.testing.assert_allclose(ad, fd, rtol=2e-5, err_msg=f"argument {i}")


# --------------------------------------------------------------------------------------
# The committed textures


def test_committed_textures_are_what_the_script_makes(tmp_path):
    spec = importlib.util.spec_from_file_location("make_textures", os.path.join(ROOT, "scripts", "make_textures.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.main([str(tmp_path)])
    names = sorted(os.listdir(tmp_path))
    assert names == sorted(mod.TEXTURES) and len(names) >= 4
    for name in names:
        with open(tmp_path / name, "rb") as a, open(os.path.join(SCENES, "textures", name), "rb") as b:
            assert a.read() == b.read(), name
    sizes = {name: load_image(tmp_path / name).shape[:2] for name in names}
    assert sizes["tiny.sunimg"] == (3, 5) and len(set(sizes.values())) == len(sizes)
