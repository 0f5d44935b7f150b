"""fitting.objective: the exact (full-size) level matches a pixel-centre target exactly at
the truth and pulls moved edges back; the pyramid; nuisance units."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import scene_from_text

import rtjax
from fitting.errors import FitError
from fitting.objective import (COARSE_SCALE, EXACT_SCALE, Objective, apply_nuisance, camera, edge_band, gaussian_blur, make_levels,
                               WHOLE_IMAGE_RENDER, nuisance_names, robust, schedule_widths, smooth)
from fitting.options import FitOptions
from fitting.problem import Problem
from fitting.select import Selection

#: compile-bound fits and tolerance checks: XLA's quick build (`conftest.quick_build`)
pytestmark = pytest.mark.usefixtures("quick_build")

DECK = """
sphe -2.3 0 0.7 6
opaq 0.9 0.3 0.2 0.4 12
plig 0.4 -1 0.8 220 210 200
elig 0.25
back 10 20 60
eyep 0 -40 0
refp 0 0 0
vang 40 30
size 24
rend x.sunimg
"""


def _levels(scene, target):
    w = scene.structure.width
    weight = np.ones(target.shape[:2] + (1,))
    return make_levels(target, weight, [w, w], [1.0, 1.0], jnp.float64, exact=[False, True])


@pytest.mark.slow
def test_exact_level_matches_a_pixel_centre_target_at_the_truth():
    """At the truth the exact level's model is the pixel-centre render (residual 0);
    the box-filtered level differs from it at the outline."""
    scene = scene_from_text(DECK).astype(jnp.float64)
    plain = np.asarray(rtjax.render(scene))
    soft, exact = _levels(scene, plain)
    assert exact.exact and not soft.exact
    selection = Selection(scene, "centers", None)
    objective = Objective(selection, None, "l2", 10.0)
    y = {"scene": selection.y0()}
    order = np.lexsort(np.asarray(exact.xy).T)  # the exact level's samples in image order (rows, then columns)
    np.testing.assert_allclose(np.asarray(objective.model(y, exact))[order], plain.reshape(-1, 3), rtol=0, atol=1e-9)
    aware = np.asarray(rtjax.render(scene, edges=1.0, subdivide=0)).reshape(-1, 3)  # the fits' one box a pixel
    np.testing.assert_allclose(np.asarray(objective.model(y, soft)), aware, rtol=0, atol=1e-9)
    assert np.abs(plain.reshape(-1, 3) - aware).max() > 10


@pytest.mark.slow
def test_exact_level_pulls_a_moved_sphere_back():
    """Moved by a fraction of a pixel, some pixel centres change side; the exact level's
    loss is then positive and its gradient points back to the truth, where the
    pixel-centre render's own gradient has no edge term at all."""
    truth = scene_from_text(DECK).astype(jnp.float64)
    target = np.asarray(rtjax.render(truth))
    _, exact = _levels(truth, target)
    shift = jnp.array([0.12, 0.0, -0.09])  # world units: ~0.4 pixel at this distance
    start = truth.replace(centers=truth.params.centers + shift)
    selection = Selection(start, "centers", None)
    objective = Objective(selection, None, "l2", 10.0)
    y = {"scene": selection.y0()}

    def loss(y):
        return 0.5 * jnp.sum(objective.residuals(y, exact) ** 2)

    assert float(loss(y)) > 1e-3
    g = np.asarray(jax.grad(loss)(y)["scene"]["centers"]).ravel()
    back = -np.asarray(shift)
    cos = g @ -back / (np.linalg.norm(g) * np.linalg.norm(back))  # descent (−g) along `back`
    assert cos > 0.9, cos
    # a step down the gradient lowers the loss
    step = {"scene": jax.tree_util.tree_map(lambda a, b: a - 0.5 * float(loss(y)) / float(np.sum(g * g)) * b, y["scene"],
                                            jax.grad(loss)(y)["scene"])}
    assert float(loss(step)) < float(loss(y))


SHADOW_DECK = """
sphe -2.3 0 4.2 7
opaq 0.3 0.7 0.9 0.4 10
sphe 0 0 -10012 10000
opaq 0.8 0.8 0.7 0 1
plig 0.5 -0.3 1 170 160 150
elig 0.15
back 30 40 90
eyep 0 -90 45
refp 0 0 -6
vang 30 30
size 32
rend x.sunimg
"""


@pytest.mark.slow
def test_exact_level_pulls_a_moved_shadow_edge_back():
    """The light turned by a fraction of a pixel's worth: shadow-edge pixels whose
    centres changed side are matched by the colour across the edge, scaled by how far
    the centre lies past it (a residual linear in the edge's position, not a jump),
    and the loss's gradient turns the light back."""
    truth = scene_from_text(SHADOW_DECK).astype(jnp.float64)
    target = np.asarray(rtjax.render(truth))
    _, exact = _levels(truth, target)
    turn = jnp.array([0.04, 0.03, 0.0])  # the shadow edge moves by ~0.5 pixel
    start = truth.replace(light_dirs=truth.params.light_dirs + turn)
    selection = Selection(start, "light", None)
    objective = Objective(selection, None, "l2", 10.0)
    y = {"scene": selection.y0()}
    e = rtjax.edge_samples(start, exact.xy, step=exact.step, edges=exact.width)
    centre, flipped, sx, t = (np.asarray(a) for a in (e.centre, e.flipped, e.shadow_x, exact.target))
    model = np.asarray(objective.model(y, exact))
    # (the light's turn also changes the lit floor's shading by a few levels)
    crossed = (np.asarray(e.x) == 0) & (np.abs(centre - t).max(1) > 30) & (np.abs(flipped - t).max(1) < 10)
    assert crossed.sum() >= 3
    c, f = centre[crossed], flipped[crossed]
    np.testing.assert_allclose(model[crossed], c + (1 - sx[crossed, None]) * (f - c), atol=1e-9)
    assert np.all(np.abs(model - t)[crossed] <= sx[crossed, None] * np.abs(c - f) + np.abs(f - t[crossed]) + 1e-9)
    assert np.all(sx[crossed] < 1)

    def loss(y):
        return 0.5 * jnp.sum(objective.residuals(y, exact) ** 2)

    grad = jax.grad(loss)(y)
    g = np.asarray(grad["scene"]["light"]).ravel()
    # the way back, in the plane of directions (the light vector's length is no parameter)
    unit = np.asarray(start.params.light_dirs[0]) / np.linalg.norm(np.asarray(start.params.light_dirs[0]))
    back = -np.asarray(turn) + np.dot(np.asarray(turn), unit) * unit
    assert g @ -back / (np.linalg.norm(g) * np.linalg.norm(back)) > 0.7  # measured 0.85
    step = {"scene": jax.tree_util.tree_map(lambda a, b: a - 0.5 * float(loss(y)) / float(np.sum(g * g)) * b, y["scene"], grad["scene"])}
    assert float(loss(step)) < float(loss(y))


def test_apply_nuisance_takes_the_units_fit_reports():
    """FitResult.nuisance gives gain and γ themselves; the solver moves their logs."""
    image = jnp.array([[[0.0, 51.0, 200.0]]])
    expect = 255 * np.clip(1.5 * np.array([0.0, 51.0, 200.0]) / 255, 0, 1) ** 0.8
    np.testing.assert_allclose(np.asarray(apply_nuisance(image, {"gain": 1.5, "gamma": 0.8}))[0, 0], expect, rtol=1e-6)
    logs = {"gain": np.log(1.5), "gamma": np.log(0.8), "blur": 0.0}
    np.testing.assert_allclose(np.asarray(apply_nuisance(image, logs, logs=True))[0, 0], expect, rtol=1e-6)


def test_the_full_size_level_is_exact_by_default_and_takes_every_edge_pixel():

    scene = scene_from_text(DECK, size=48)
    target = np.asarray(rtjax.render(scene))
    pyramid = Problem.build(scene, target, "centers", None, FitOptions(levels=[24, 48])).pyramid
    # the exact level, then its narrow-scale refinement on the same samples
    assert [s.exact for s in pyramid] == [False, True, True]
    assert [float(s.scale) for s in pyramid] == [1.0, 1.0, np.float32(EXACT_SCALE)]
    np.testing.assert_array_equal(np.asarray(pyramid[-1].xy), np.asarray(pyramid[-2].xy))
    band = np.flatnonzero(edge_band(target).ravel())
    w = scene.structure.width
    xy = np.asarray(pyramid[-1].xy)
    taken = set((np.floor(xy[:, 1]) * w + np.floor(xy[:, 0])).astype(int))
    assert set(band) <= taken and len(taken) == len(xy)
    # --no-exact-polish: a last box-filtered level after the full-size one; no polish: neither
    pyramid = Problem.build(scene, target, "centers", None, FitOptions(levels=[24, 48], exact_polish=False)).pyramid
    assert [s.exact for s in pyramid] == [False] * 3 and float(pyramid[-1].width) == 1.0
    pyramid = Problem.build(scene, target, "centers", None, FitOptions(levels=[24, 48], polish=None)).pyramid
    assert [s.exact for s in pyramid] == [False, False]


def _blur(image, sigma, radius=8):
    """A reference Gaussian blur, written apart from fitting's: np.convolve per row and
    column of the edge-extended image, kernel truncated at `radius`."""
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    out = np.asarray(image, np.float64)
    for axis in (0, 1):
        pad = [(0, 0)] * out.ndim
        pad[axis] = (radius, radius)
        padded = np.pad(out, pad, mode="edge")
        out = np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), axis, padded)
    return out


def test_camera_blurs_in_the_responses_order_and_blurs_chroma_further():
    """`camera` against NumPy: a share `order` of the blur after the response, the rest
    before; then Cb and Cr of JPEG's YCbCr (ITU-R BT.601, written out here) blurred by
    `chroma` more, Y untouched."""
    rng = np.random.default_rng(3)
    image = np.clip(rng.uniform(0, 255, (18, 21, 3)) * (rng.uniform(size=(18, 21, 1)) > 0.5), 0, 255)
    nuisance = {"gain": 1.1, "gamma": 0.8, "blur": 0.9, "chroma": 1.2, "order": 0.3}

    def response(x):
        return 255 * np.clip(1.1 * x / 255, 0, 1) ** 0.8

    early, late = response(_blur(image, 0.9)), _blur(response(image), 0.9)
    rgb = 0.7 * early + 0.3 * late
    ycc = rgb @ np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]]).T
    ycc[..., 1:] = _blur(ycc[..., 1:], 1.2)
    expect = ycc @ np.linalg.inv(np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])).T
    got = np.asarray(camera(jnp.asarray(image), nuisance))
    np.testing.assert_allclose(got, expect, rtol=0, atol=1e-6)
    # the solver's coordinates: logs, and the logit of order
    logs = {k: np.log(v / (1 - v)) if k == "order" else np.log(v) for k, v in nuisance.items()}
    np.testing.assert_allclose(np.asarray(camera(jnp.asarray(image), logs, logs=True)), expect, rtol=0, atol=1e-6)
    grey = np.repeat(image[..., :1], 3, axis=2)  # no chroma: the chroma blur changes nothing
    no_chroma = {k: v for k, v in nuisance.items() if k != "chroma"}
    np.testing.assert_allclose(np.asarray(camera(jnp.asarray(grey), nuisance)), np.asarray(camera(jnp.asarray(grey), no_chroma)),
                               rtol=0, atol=1e-9)
    # gaussian_blur truncated as smooth is: the same blur
    np.testing.assert_allclose(np.asarray(gaussian_blur(jnp.asarray(image), 1.3, radius=4)), smooth(image, 1.3), rtol=0, atol=1e-9)


@pytest.mark.slow
def test_a_fitted_blur_is_the_whole_image_at_full_size_and_wider_edges_below():
    """Full size: the whole image, each pixel box-filtered at edges, through `camera`,
    looked at in the level's pixels, with derivatives in the blur that match finite differences;
    coarse levels: the edges' box widened to the blur's variance."""
    scene = scene_from_text(DECK).astype(jnp.float64)
    target = np.asarray(rtjax.render(scene))
    w = scene.structure.width
    weight = np.ones(target.shape[:2] + (1,))
    coarse, full = make_levels(target, weight, [w // 2, w], [1.0, 1.0], jnp.float64, whole=[False, True])
    assert full.whole and not full.exact and not coarse.whole
    i, j = (np.floor(np.asarray(full.xy)[:, a]).astype(int) for a in (0, 1))
    np.testing.assert_array_equal(np.asarray(full.target), target[j, i])
    selection = Selection(scene, "centers", None)
    objective = Objective(selection, None, "l2", 10.0)
    sigma = 0.7
    nuisance = {"blur": jnp.log(sigma), "chroma": jnp.log(0.8), "order": jnp.asarray(0.4)}
    y = {"scene": selection.y0(), "nuisance": nuisance}
    expect = np.asarray(camera(rtjax.render(scene, **WHOLE_IMAGE_RENDER), nuisance, logs=True))[j, i]
    np.testing.assert_allclose(np.asarray(objective.model(y, full)), expect, rtol=0, atol=1e-9)
    step = float(coarse.step)
    wide = np.sqrt(1 + 12 * (sigma / step) ** 2)
    expect = np.asarray(rtjax.render_samples(scene, np.asarray(coarse.xy), step=step, edges=wide))
    np.testing.assert_allclose(np.asarray(objective.model(y, coarse)), expect, rtol=0, atol=1e-9)

    def total(b):
        return jnp.sum(objective.model({"scene": y["scene"], "nuisance": {**nuisance, "blur": b}}, full))

    b, h = jnp.log(sigma), 1e-5
    fd = (float(total(b + h)) - float(total(b - h))) / (2 * h)
    g = float(jax.jacfwd(total)(b))
    assert abs(g) > 1 and abs(g - fd) < 1e-5 * abs(fd)


@pytest.mark.parametrize("kind", ["photo", "camera"])
def test_staged_jacobian_is_the_plain_one(kind):
    """`Objective.stages` splits a level's residuals into the render and the camera after
    it; `solvers.staged_jacobian` differentiates the render in the render's parameters
    alone. On both levels of a photo fit and of a fit with the camera's nuisance
    parameters the camera's part holds the blur on the whole-image level only (a
    coarse level's blur widens the render's edges: the render's); the Jacobian is
    `jax.jacfwd`'s of the residuals, in float64, on the photo's whole-image level (blur
    in the camera) and the nuisance fit's coarse level (blur in the render): one
    compile of each kind of split, the other two forms differ from these only in the
    group the keys are in."""
    from fitting.solvers import staged_jacobian

    scene = scene_from_text(DECK, 16).astype(jnp.float64)
    target = np.asarray(rtjax.render(scene)) * 0.9 + 8
    options = FitOptions(levels=(8, 16), **({"photo": True} if kind == "photo" else {"nuisance": ("camera",)}))
    problem = Problem.build(scene, target, "centers", None, options)
    y = jax.tree_util.tree_map(lambda v: v + 0.01, problem.y0)  # off the start: no entry at a special value
    assert jax.tree_util.tree_leaves(y)[0].dtype == jnp.float64
    flat, unravel = jax.flatten_util.ravel_pytree(y)
    assert [s.whole for s in problem.pyramid] == [False, True]
    group = "photo" if kind == "photo" else "nuisance"
    for samples in problem.pyramid:
        stages = problem.objective.stages(y, samples)
        first, second = stages.split(y)
        assert set(first[group]) | set(second[group]) == set(y[group]) and not set(first[group]) & set(second[group])
        assert ("blur" in second[group]) == samples.whole and {"gain", "gamma"} <= set(second[group])
    samples = problem.pyramid[1 if kind == "photo" else 0]
    stages = problem.objective.stages(y, samples)
    jac, value = jax.jit(lambda y: staged_jacobian(stages, y))(y)
    expect, residuals = jax.jit(jax.jacfwd(lambda v: (problem.objective.residuals(unravel(v), samples),) * 2,
                                           has_aux=True))(flat)
    np.testing.assert_allclose(np.asarray(value), np.asarray(residuals), rtol=0, atol=1e-12)
    scale = float(np.abs(expect).max())
    assert scale > 0
    np.testing.assert_allclose(np.asarray(jac), np.asarray(expect), rtol=0, atol=1e-9 * scale)


def test_nuisance_names():
    assert nuisance_names(["camera"]) == ("gain", "gamma", "blur", "chroma", "order")
    assert nuisance_names(["blur", "gain"]) == ("gain", "blur")
    for bad, says in ((["exposure"], "unknown nuisance parameter 'exposure'"), (["chroma"], "fit blur with them")):
        with pytest.raises(FitError, match=says):
            nuisance_names(bad)


def test_default_schedule_an_eighth_a_quarter_and_full_size():
    assert schedule_widths(400, None) == [50, 100, 400]
    assert schedule_widths(240, None) == [60, 120, 240]  # an eighth would be below 48 pixels
    assert schedule_widths(96, None) == [48, 96]
    assert schedule_widths(64, None) == [64]
    # a fitted blur: three levels halving the width; an int: that many halving levels
    assert schedule_widths(400, None, blurred=True) == [100, 200, 400]
    assert schedule_widths(400, 4) == [50, 100, 200, 400]
    assert schedule_widths(400, [50, 100, 900]) == [50, 100, 400]


@pytest.mark.slow
def test_levels_scale_the_robust_loss():
    """Levels coarser than the image use a Cauchy scale COARSE_SCALE times wider, the
    refinement of a level matched at pixel centres one EXACT_SCALE times narrower; a
    full-size level, and every level of a fit with a blur, the given one."""
    scene = scene_from_text(DECK).astype(jnp.float64)
    target = np.asarray(rtjax.render(scene.replace(centers=scene.params.centers + 0.3)))
    weight = np.ones(target.shape[:2] + (1,))
    coarse, full, exact = make_levels(target, weight, [12, 24, 24], [1.0, 1.0, 1.0], jnp.float64, exact=[False, False, True])
    selection = Selection(scene, "centers", None)
    objective = Objective(selection, None, "cauchy", 10.0)
    y = {"scene": selection.y0()}
    refined = exact._replace(scale=jnp.asarray(EXACT_SCALE))
    for level, scale in ((coarse, 10.0 * COARSE_SCALE), (full, 10.0), (exact, 10.0), (refined, 10.0 * EXACT_SCALE)):
        r = (objective.model(y, level) - level.target) * level.weight / 255
        assert np.abs(np.asarray(r)).max() * 255 > 20  # residuals where the scale matters
        np.testing.assert_allclose(np.asarray(objective.residuals(y, level)), np.asarray(robust(r, "cauchy", scale / 255)), rtol=1e-12)
    blurred = {**y, "nuisance": {"blur": jnp.asarray(np.log(0.3))}}
    for level in (coarse, exact):
        r = (objective.model(blurred, level) - level.target) * level.weight / 255
        np.testing.assert_allclose(np.asarray(objective.residuals(blurred, level)), np.asarray(robust(r, "cauchy", 10.0 / 255)), rtol=1e-12)


def test_levels_of_a_few_pixels_take_their_samples_from_the_edges():
    """Widths of a few pixels (`--levels 5,3`): a level whose pixels are nearly all near
    an edge takes the rest of its K samples from the edge band, each pixel once."""
    img = np.zeros((40, 60, 3))
    img[10:30, 15:45] = 200.0
    levels = make_levels(img, np.ones((40, 60, 1)), [3, 5, 60], [1.0] * 3, jnp.float64)
    sizes = [len(level.xy) for level in levels]
    assert sizes == [3 * 2] * 3  # K: the coarsest level's pixels (3 × 2)
    for level in levels:
        xy = np.asarray(level.xy)
        assert len(np.unique(xy, axis=0)) == len(xy)


def test_smooth_is_a_normalised_gaussian():
    impulse = np.zeros((21, 21))
    impulse[10, 10] = 1
    x = np.arange(-5, 6)  # truncated at ⌈3σ⌉
    k = np.exp(-(x**2) / (2 * 1.5**2))
    k /= k.sum()
    expected = np.zeros((21, 21))
    expected[5:16, 5:16] = np.outer(k, k)
    np.testing.assert_allclose(smooth(impulse, 1.5), expected, atol=1e-15)
    flat = np.full((8, 9, 3), 7.0)
    np.testing.assert_allclose(smooth(flat, 1.0), flat)  # edges extended: no darkening at the border


def test_denoised_edge_band_finds_the_edges_not_the_noise():
    """Noise of σ = 4 levels makes most pixels of a two-colour target look like edge
    pixels; found on the target blurred by 1 pixel (`make_levels(denoise=1)`, what a fit
    with a fitted blur uses), the band is the edge's neighbourhood alone."""
    img = np.zeros((40, 60, 3))
    img[:, 30:] = 200.0
    noisy = img + np.random.default_rng(0).normal(0, 4, img.shape)
    assert edge_band(noisy).mean() > 0.5
    band = edge_band(smooth(noisy, 1.0))
    assert band[:, 29:31].all()
    assert not band[:, :24].any() and not band[:, 36:].any()
    levels = make_levels(noisy, np.ones((40, 60, 1)), [15, 60], [1.0, 1.0], jnp.float64, exact=[False, True], denoise=1.0)
    xs = np.asarray(levels[-1].xy)[:, 0]
    # the full-size level: every edge pixel, others up to a quarter of the image
    assert len(xs) == int(0.25 * 40 * 60) and np.sum(np.abs(xs - 30) < 2) == 4 * 40
