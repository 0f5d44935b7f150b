"""Sanity tests of the NumPy reference renderer (rtjax.reference) itself.

Each test checks the reference against a value worked out by hand from DECK.md, so the
reference can in turn be trusted as a yardstick for the JAX renderer. Images are tiny.
"""

import math
import os

import numpy as np
import pytest

from rtjax.reference import (
    camera_basis,
    image_size,
    parse_deck_text,
    quantize,
    refract,
    render_reference,
)

SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")


def one_frame(text):
    frames = parse_deck_text(text)
    assert len(frames) == 1
    return frames[0]


# An 11 x 11 image: the centre pixel (5, 5) samples the screen centre exactly.
CAM_Z = """
eyep 0 -100 0
refp 0 0 0
vang 30 30
size 11
rend out.sunimg
"""


def test_sample_deck_parses_and_is_400x294():
    with open(os.path.join(SCENES, "ex2s3.dat")) as fh:
        frames = parse_deck_text(fh.read())
    assert len(frames) == 1
    f = frames[0]
    assert image_size(f) == (400, 294)
    assert [s["kind"] for s in f.spheres] == ["opaq"] * 3 + ["mirr", "trpa", "trpa", "trpa", "mirr"]
    assert f.spheres[5]["n"] == 2.42 and f.spheres[4]["kt"] == 0.8
    assert len(f.lights) == 1 and np.allclose(f.lights[0][0], [0.5, 0.5, 2.0])
    assert np.allclose(f.back, [0, 0, 128]) and f.ke == 0.2
    assert f.output == "ex2s3.sunimg"


def test_sample_deck_small_render_is_finite_and_in_range():
    with open(os.path.join(SCENES, "ex2s3.dat")) as fh:
        f = parse_deck_text(fh.read())[0]
    f.size = 40
    img = render_reference(f)
    assert img.shape == (29, 40, 3)
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 255
    # the background shows in the top right corner and some sphere is lit
    assert np.allclose(img[0, -1], [0, 0, 128])
    assert img.max() > 200


def test_state_replacement_lights_add_and_quit():
    text = """
    # comment line
    sphe 0 0 0 1   # trailing comment
    opaq 1 0 0 0 1
    plig 0 0 1 10 10 10
    back 1 2 3
    eyep 0 -10 0
    refp 0 0 0
    vang 40 30
    size 8
    rend a.sunimg
    plig 1 0 0 20 20 20
    back 4 5 6
    eyep 0 -20 0
    rend b.sunimg
    quit
    rend c.sunimg
    """
    a, b = parse_deck_text(text)
    assert a.output == "a.sunimg" and b.output == "b.sunimg"
    assert len(a.lights) == 1 and len(b.lights) == 2
    assert np.allclose(a.back, [1, 2, 3]) and np.allclose(b.back, [4, 5, 6])
    assert np.allclose(a.eye, [0, -10, 0]) and np.allclose(b.eye, [0, -20, 0])


def test_camera_basis_z_up_and_parallel_fallback():
    f = one_frame("eyep 0 -10 0\nrefp 0 0 0\nvang 40 30\nsize 4\nrend x\n")
    w, u, v = camera_basis(f)
    assert np.allclose(w, [0, 1, 0]) and np.allclose(u, [1, 0, 0]) and np.allclose(v, [0, 0, 1])
    f = one_frame("eyep 0 0 10\nrefp 0 0 0\nvang 40 30\nsize 4\nrend x\n")
    w, u, v = camera_basis(f)  # looking straight down: y stands in for z
    assert np.allclose(w, [0, 0, -1]) and np.allclose(u, [1, 0, 0]) and np.allclose(v, [0, 1, 0])


def test_image_size_rounding():
    f = one_frame("eyep 0 -10 0\nrefp 0 0 0\nvang 90 90\nsize 7\nrend x\n")
    assert image_size(f) == (7, 7)
    f.va = 2 * math.degrees(math.atan(2.6 / 7))  # 7 * tan(va/2) = 2.6: rounds up
    assert image_size(f) == (7, 3)
    f.va = 2 * math.degrees(math.atan(2.4 / 7))  # 2.4: rounds down
    assert image_size(f) == (7, 2)


def test_opaque_sphere_lit_from_the_eye():
    ke, d, ks, beta, L = 0.3, np.array([0.8, 0.5, 0.2]), 0.4, 7.0, np.array([200.0, 100.0, 50.0])
    f = one_frame(
        f"""
        sphe 0 0 0 10
        opaq {d[0]} {d[1]} {d[2]} {ks} {beta}
        plig 0 -1 0 {L[0]} {L[1]} {L[2]}
        back 10 20 30
        elig {ke}
        """
        + CAM_Z
    )
    img = render_reference(f, depth=0)
    # N = L = V at the sphere's front point: N.L = 1, cos(gamma) = 1
    expect = np.clip(ke * d * L + (1 - ke) * d * L + ks * L, 0, 255)
    assert np.allclose(img[5, 5], expect, rtol=0, atol=1e-9)
    for corner in (img[0, 0], img[0, -1], img[-1, 0], img[-1, -1]):
        assert np.allclose(corner, [10, 20, 30])
    # image is left-right and up-down symmetric about the centre
    assert np.allclose(img, img[::-1, ::-1])


def test_clamping_not_rounding():
    f = one_frame("sphe 0 0 0 10\nopaq 1 1 1 1 1\nplig 0 -1 0 255 255 255\nelig 0.5\n" + CAM_Z)
    img = render_reference(f)
    assert np.allclose(img[5, 5], 255.0)  # 255 + 255 clamped
    f = one_frame("sphe 0 0 0 10\nopaq 0.5 0.5 0.5 0 1\nplig 0 -1 0 1 1 1\n" + CAM_Z)
    img = render_reference(f)
    assert np.allclose(img[5, 5], 0.5)  # not rounded ...
    assert quantize(img)[5, 5, 0] == 1  # ... until quantised (half up)


def test_two_lights_add():
    base = "sphe 0 0 0 10\nopaq 0.5 0.5 0.5 0 1\nelig 0.1\n"
    f1 = one_frame(base + "plig 0 -1 0 100 100 100\n" + CAM_Z)
    f2 = one_frame(base + "plig 1 -1 1 40 60 80\n" + CAM_Z)
    f12 = one_frame(base + "plig 0 -1 0 100 100 100\nplig 1 -1 1 40 60 80\n" + CAM_Z)
    a, b, ab = render_reference(f1), render_reference(f2), render_reference(f12)
    sphere = np.any(a != 0, axis=2)
    assert np.allclose(ab[sphere], (a + b)[sphere])


def test_mirror_sphere_reflecting_background_shows_background():
    f = one_frame("sphe 0 0 0 10\nmirr\nback 7 77 177\nplig 0 -1 1 255 255 255\nelig 0.5\n" + CAM_Z)
    img = render_reference(f, depth=3)
    assert np.allclose(img, [7, 77, 177])
    # with depth 0 the reflected ray is not traced: mirror pixels are black
    img0 = render_reference(f, depth=0)
    assert np.allclose(img0[5, 5], 0) and np.allclose(img0[0, 0], [7, 77, 177])


def test_mirror_reflects_sphere_behind_the_eye():
    # The centre ray bounces straight back through the eye and hits an opaque sphere
    # behind it; the mirror shadows that point from the light: ambient only.
    ke, d, L = 0.25, np.array([0.4, 0.6, 1.0]), np.array([200.0, 150.0, 100.0])
    f = one_frame(
        f"""
        sphe 0 0 0 10
        mirr
        sphe 0 -200 0 20
        opaq {d[0]} {d[1]} {d[2]} 0.5 5
        plig 0 1 0 {L[0]} {L[1]} {L[2]}
        elig {ke}
        """
        + CAM_Z
    )
    img = render_reference(f, depth=2)
    assert np.allclose(img[5, 5], ke * d * L, atol=1e-9)


def test_shadow_gives_ambient_only_and_glass_attenuates_by_kt_squared():
    ke, d, ks, beta, L = 0.2, np.array([0.9, 0.7, 0.5]), 0.3, 3.0, np.array([255.0, 200.0, 100.0])
    s2 = 1 / math.sqrt(2)
    # eye straight above sphere A, light from (1,0,1); blocker B on the shadow ray
    # from A's top point (0,0,10).
    bc = np.array([0, 0, 10]) + 40 * np.array([s2, 0, s2])
    head = f"""
        sphe 0 0 0 10
        opaq {d[0]} {d[1]} {d[2]} {ks} {beta}
        plig 1 0 1 {L[0]} {L[1]} {L[2]}
        elig {ke}
    """
    cam = "eyep 0 0 100\nrefp 0 0 0\nvang 20 20\nsize 11\nrend x\n"
    lit = render_reference(one_frame(head + cam))[5, 5]
    # N = (0,0,1), N.L = 1/sqrt2, R_L = (-1,0,1)/sqrt2, V = (0,0,1), cos(gamma) = 1/sqrt2
    diffuse_spec = (1 - ke) * s2 * d * L + ks * L * s2**beta
    assert np.allclose(lit, np.clip(ke * d * L + diffuse_spec, 0, 255), atol=1e-9)

    opaque_block = f"sphe {bc[0]} {bc[1]} {bc[2]} 5\nopaq 1 1 1 0 1\n"
    shadowed = render_reference(one_frame(head + opaque_block + cam))[5, 5]
    assert np.allclose(shadowed, ke * d * L, atol=1e-9)

    mirror_block = f"sphe {bc[0]} {bc[1]} {bc[2]} 5\nmirr\n"
    shadowed = render_reference(one_frame(head + mirror_block + cam))[5, 5]
    assert np.allclose(shadowed, ke * d * L, atol=1e-9)

    kt = 0.6
    glass_block = f"sphe {bc[0]} {bc[1]} {bc[2]} 5\ntrpa {kt} 1.5 0 1\n"
    dimmed = render_reference(one_frame(head + glass_block + cam))[5, 5]
    assert np.allclose(dimmed, np.clip(ke * d * L + kt**2 * diffuse_spec, 0, 255), atol=1e-9)


def test_clear_glass_is_invisible():
    behind = "sphe 0 40 0 15\nopaq 0.9 0.4 0.1 0.5 10\nplig -1 -2 1 255 255 255\nback 0 0 90\nelig 0.2\n"
    glass = "sphe 2 0 1 8\ntrpa 1 1 0 1\n"
    cam = "eyep 0 -60 0\nrefp 0 0 0\nvang 50 50\nsize 15\nrend x\n"
    without = render_reference(one_frame(behind + cam))
    with_glass = render_reference(one_frame(behind + glass + cam), depth=4)
    assert np.allclose(with_glass, without, atol=1e-6)


def test_glass_depth_semantics():
    f = one_frame("sphe 0 0 0 10\ntrpa 1 1 0 1\nback 50 60 70\n" + CAM_Z)
    # enter (segment 1), leave (segment 2), then the background
    assert np.allclose(render_reference(f, depth=2)[5, 5], [50, 60, 70])
    assert np.allclose(render_reference(f, depth=1)[5, 5], 0)
    assert np.allclose(render_reference(f, depth=0)[5, 5], 0)
    # the specular term survives at depth 0
    f = one_frame("sphe 0 0 0 10\ntrpa 1 1.5 0.5 1\nplig 0 -1 0 100 100 100\n" + CAM_Z)
    assert np.allclose(render_reference(f, depth=0)[5, 5], 50)


def test_glass_kt_weights_each_interface():
    kt = 0.7
    f = one_frame(f"sphe 0 0 0 10\ntrpa {kt} 1.5 0 1\nback 100 200 50\n" + CAM_Z)
    # the centre ray goes straight through: two interfaces, weight kt^2
    assert np.allclose(render_reference(f, depth=5)[5, 5], kt**2 * np.array([100, 200, 50]))


def test_refract_snell_and_tir():
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    th = np.radians([0.0, 30.0, 60.0])
    d = np.stack([np.sin(th), np.zeros(3), -np.cos(th)], axis=1)
    eta = np.full(3, 1 / 1.5)
    t, tir = refract(d, n, eta)
    assert not tir.any()
    assert np.allclose(np.linalg.norm(t, axis=1), 1)
    assert np.allclose(t[:, 0], eta * d[:, 0])  # sin(theta_t) = eta sin(theta_i)
    assert (t[:, 2] < 0).all()
    # leaving glass (eta = 1.5) at 60 degrees: sin = 1.3 > 1, total internal reflection
    t, tir = refract(d, n, np.full(3, 1.5))
    assert list(tir) == [False, False, True]
    assert np.allclose(t[2], [d[2, 0], 0, -d[2, 2]])


def test_eye_inside_glass_sphere_is_finite():
    f = one_frame("sphe 0 -100 0 30\ntrpa 0.9 2.42 0.3 10\nsphe 0 40 0 10\nopaq 1 0 0 0 1\n"
                  "plig 0 -1 1 255 255 255\nback 0 0 50\n" + CAM_Z)
    img = render_reference(f, depth=6)
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 255


def test_supersampling_averages_clamped_samples():
    # elig 1: the sphere is a flat 255 disc (ambient only), the background black
    f = one_frame("sphe 0 0 0 10\nopaq 1 1 1 0 1\nplig 0 -1 0 255 255 255\nelig 1\n" + CAM_Z)
    img1 = render_reference(f, spp=1)
    img3 = render_reference(f, spp=3)
    assert img3.shape == img1.shape
    # fully inside or fully outside pixels agree; edge pixels lie in between
    assert np.allclose(img3[5, 5], img1[5, 5]) and np.allclose(img3[0, 0], 0)
    edge = (img3[..., 0] > 0) & (img3[..., 0] < 255)
    assert edge.any() and np.allclose(img3[edge] * 9 / 255, np.round(img3[edge] * 9 / 255))


# ----- the scene decks ------------------------------------------------------------


DECKS = ["ex2s3.dat", "level1_opaque.dat", "level2_mirrors.dat", "level3_glass.dat", "multi_frame.dat"]


def load(name):
    with open(os.path.join(SCENES, name)) as fh:
        return parse_deck_text(fh.read())


@pytest.mark.parametrize("name", DECKS)
def test_decks_parse_and_render_small(name):
    for f in load(name):
        f.size = 24
        img = render_reference(f)
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 255
        assert img.std() > 5  # something is in view


def test_multi_frame_moves_only_the_camera():
    frames = load("multi_frame.dat")
    assert len(frames) == 3
    assert len({f.output for f in frames}) == 3
    assert len({tuple(f.eye) for f in frames}) == 3
    for f in frames[1:]:
        assert image_size(f) == image_size(frames[0]) == (200, 147)
        assert len(f.spheres) == len(frames[0].spheres) == 8


def test_level1_needs_no_depth():
    (f,) = load("level1_opaque.dat")
    f.size = 40
    assert np.array_equal(render_reference(f, depth=0), render_reference(f, depth=5))


def test_level2_has_multiple_bounces():
    (f,) = load("level2_mirrors.dat")
    f.size = 120
    d1, d10 = render_reference(f, depth=1), render_reference(f, depth=10)
    assert (np.abs(d1 - d10).max(axis=2) > 1).sum() >= 5


def test_level3_has_total_internal_reflection(monkeypatch):
    from rtjax import reference

    (f,) = load("level3_glass.dat")
    f.size = 100
    img = render_reference(f)
    seen = []
    orig = reference.refract

    def straight_through_on_tir(d, n, eta):  # replace TIR by "no bend": pixels change
        t, tir = orig(d, n, eta)
        seen.append(tir.sum())
        return np.where(tir[:, None], d, t), tir

    monkeypatch.setattr(reference, "refract", straight_through_on_tir)
    img2 = render_reference(f)
    assert sum(seen) > 0
    assert (np.abs(img - img2).max(axis=2) > 2).sum() >= 20
