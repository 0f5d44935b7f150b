"""Ray–sphere intersection (rtjax/spheres.py): culling of large scenes answers as testing
every ray against every sphere does, for hits, shadows, images and derivatives; the
choices reverse mode keeps decode to what was chosen."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import linearised

import rtjax
from rtjax import bench, spheres, trace


# -- the choices reverse mode keeps ---------------------------------------------------------


@pytest.mark.parametrize("n", [1, 8, 126, 127, 1000, 40000])
def test_kept_hit_decodes_to_the_choice(n):
    """`keep_hit`'s narrow code gives back found, index and root for every index a scene
    of n spheres has (int8 up to 126, then int16, then int32), and index 0 without a hit."""
    rng = np.random.default_rng(n)
    idx = np.concatenate([[0, n - 1], rng.integers(0, n, 500)]).astype(np.int32)
    far = rng.uniform(size=idx.size) < 0.5
    best = np.where(rng.uniform(size=idx.size) < 0.7, rng.uniform(0.1, 9, idx.size), np.inf)
    best[:2] = 1.0
    found, got, got_far = (np.asarray(a) for a in spheres.keep_hit(jnp.asarray(best), jnp.asarray(idx),
                                                                    jnp.asarray(far), n))
    assert jnp.dtype(spheres.narrowest(n)).itemsize == (1 if n <= 126 else 2 if n <= 32766 else 4)
    np.testing.assert_array_equal(found, np.isfinite(best))
    np.testing.assert_array_equal(got, np.where(found, idx, 0))
    np.testing.assert_array_equal(got_far, far & found)


@pytest.mark.parametrize("n", [1, 7, 8, 9, 17, 32, 150])
def test_kept_blockers_decode_to_the_mask(n):
    """`keep_blocked` packs a (N, P) mask into bytes and unpacks it exactly, N not a
    multiple of 8 included."""
    mask = np.random.default_rng(n).uniform(size=(n, 300)) < 0.3
    np.testing.assert_array_equal(np.asarray(spheres.keep_blocked(jnp.asarray(mask))), mask)


def test_reverse_mode_keeps_the_choices_not_the_tables(capsys):
    """The segments' checkpoint policy (`trace.KEEP`) keeps the named choices: a hit and
    its shadow ray differentiated through it save the narrow hit code and the packed
    blockers as residuals, and no (N, P) ray–sphere table."""
    o = jnp.zeros((3, 12))
    d = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0])[:, None], (3, 12))
    radii = jnp.ones(5)

    def f(centers):
        hit = spheres.nearest_hit(o, d, centers, radii, jnp.full(12, -1), 1e-4, False)
        vis = spheres.transmission(hit.point, d, centers, radii, hit.index, 1e-4, jnp.full(5, 0.25))
        return jnp.sum(hit.t * vis)

    centers = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)) + [0, 0, 5])
    jax.ad_checkpoint.print_saved_residuals(jax.checkpoint(f, policy=trace.KEEP), centers)
    saved = capsys.readouterr().out
    assert "i8[12] named 'choice'" in saved  # the hit code
    assert "u8[1,12] named 'choice'" in saved  # five blockers in one byte per ray
    assert "[5,12]" not in saved  # no ray–sphere table


# -- the silhouette mode's toggles ----------------------------------------------------------


def test_a_forced_sphere_is_seen_only_where_its_outline_lies_ahead():
    """`Toggles.force` makes a ray that misses the sphere graze it at its silhouette
    point, where the ray passes closest to it; a ray that passes it behind its origin
    (here, one leaving the sphere's side of the scene) keeps what it meets, nothing."""
    o = jnp.zeros((3, 3))
    d = jnp.asarray(np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]]).T)  # towards it, away, across (closest at o)
    centers, radii = jnp.asarray([[5.0, 2.0, 0.0]]), jnp.asarray([1.0])
    toggles = spheres.Toggles(jnp.full(3, -1), jnp.zeros(3, jnp.int32))
    hit = spheres.nearest_hit(o, d, centers, radii, jnp.full(3, -1), 1e-4, False, toggles)
    np.testing.assert_array_equal(np.asarray(hit.found), [True, False, False])
    np.testing.assert_allclose(np.asarray(hit.t)[0], 5.0)  # where it passes closest to the centre
    np.testing.assert_allclose(np.asarray(hit.point)[:, 0], [5.0, 1.0, 0.0])  # its silhouette point c + r·l̂
    free = spheres.nearest_hit(o, d, centers, radii, jnp.full(3, -1), 1e-4, False)
    assert not np.asarray(free.found).any()


# -- culling ---------------------------------------------------------------------------------


def test_small_scenes_stay_on_the_brute_force_path():
    def structure(n, culling=None):
        return rtjax.Structure(("opaq",) * n, 0, 1, 1, culling=culling)

    assert not structure(spheres.CULL_ABOVE).culls and structure(spheres.CULL_ABOVE + 1).culls
    assert structure(1, culling=True).culls and not structure(spheres.CULL_ABOVE + 1, culling=False).culls


def _random_rays(rng, centers, radii, p):
    """Incoherent rays in random order: from outside, and from sphere surfaces (both ways)."""
    n = len(radii)
    o = rng.uniform(-12, 12, (3, p))
    d = rng.normal(size=(3, p))
    origin = np.full(p, -1, np.int32)
    on = rng.uniform(size=p) < 0.5
    k = rng.integers(0, n, p)
    normal = rng.normal(size=(3, p))
    normal /= np.linalg.norm(normal, axis=0)
    o[:, on] = (centers[k].T + radii[k] * normal)[:, on]
    origin[on] = k[on]
    return o, d / np.linalg.norm(d, axis=0), origin


@pytest.mark.slow
def test_culled_nearest_and_transmission_equal_brute_force():
    """Random rays (not a camera's: the hard case for culling), rays leaving spheres,
    an excluded sphere per ray, a duplicated sphere (exact ties), inactive rays."""
    rng = np.random.default_rng(0)
    scene = bench.random_scene(150, seed=1)
    centers = np.array(scene.params.centers)
    centers[7] = centers[3]  # a duplicate: ties must resolve to the lower index
    radii = np.asarray(scene.params.radii).copy()
    radii[7] = radii[3]
    p = 5000
    o, d, origin = _random_rays(rng, centers, radii, p)
    eye = np.asarray(scene.params.eye, np.float64)[:, None]  # and rays from one point toward the spheres
    aim = centers[rng.integers(0, len(radii), p)].T + rng.normal(size=(3, p))
    from_eye = rng.uniform(size=p) < 0.3
    o[:, from_eye] = eye
    d[:, from_eye] = ((aim - eye) / np.linalg.norm(aim - eye, axis=0))[:, from_eye]
    origin[from_eye] = -1
    active = rng.uniform(size=p) < 0.8
    exclude = np.where(rng.uniform(size=p) < 0.2, rng.integers(0, len(radii), p), -1).astype(np.int32)
    args = [jnp.asarray(a, jnp.float32) for a in (o, d, centers, radii)]
    tmin = spheres.tmin_for(spheres.scene_scale(args[2], args[3], jnp.asarray(scene.params.eye)))
    origin, exclude, active = jnp.asarray(origin), jnp.asarray(exclude), jnp.asarray(active)

    t_b, i_b, f_b = (np.asarray(a) for a in spheres.nearest(*args, origin, tmin, False, exclude))
    t_c, i_c, f_c = (np.asarray(a) for a in spheres.culled_nearest(*args, origin, tmin, exclude, active))
    a = np.asarray(active)
    assert np.isfinite(t_b[a]).sum() > 1000  # most active rays hit something
    # the same sphere and root for every ray; the distance itself is recomputed from the
    # index, differentiably, by `Hit`, so only its rounding (fused differently) may differ
    np.testing.assert_array_equal(i_c[a], i_b[a])
    np.testing.assert_array_equal(np.isfinite(t_c[a]), np.isfinite(t_b[a]))
    np.testing.assert_allclose(t_c[a], t_b[a], rtol=1e-3)
    np.testing.assert_array_equal(f_c[a], f_b[a])
    assert not np.any(np.isfinite(t_c[~a]))  # inactive rays: no hit

    factor = jnp.asarray(np.where(rng.uniform(size=len(radii)) < 0.3, rng.uniform(0.2, 0.8, len(radii)) ** 2, 0), jnp.float32)
    for light in (np.array([0.5, 0.5, 2.0]), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])):
        light = jnp.asarray(light / np.linalg.norm(light), jnp.float32)
        ray = jnp.broadcast_to(light[:, None], args[0].shape)
        brute = np.asarray(spheres.transmission(args[0], ray, args[2], args[3], origin, tmin, factor, skip=(exclude,)))
        grid = spheres.light_grid(light, args[2], args[3], tmin)
        assert not bool(grid.over)
        culled = np.asarray(spheres.transmission(args[0], ray, args[2], args[3], origin, tmin, factor, skip=(exclude,),
                                                 active=active, grid=grid))
        assert 0 < np.mean(brute[a] == 0) < 1
        np.testing.assert_array_equal(culled[a], brute[a])


@pytest.fixture(scope="module")
def scene200():
    return bench.random_scene(200, seed=1, size=24)


def brute_force(scene: rtjax.Scene) -> rtjax.Scene:
    """The scene rendered with every ray against every sphere."""
    return rtjax.Scene(scene.structure.replace(culling=False), scene.params)


@pytest.mark.slow
def test_culled_render_equals_brute_force(scene200):
    """A random 200-sphere scene: the image (pixel centres and 2×2 samples) is the same
    float for float with culling as with every ray against every sphere."""
    assert scene200.structure.culls
    culled = [np.asarray(rtjax.render(scene200, spp=k)) for k in (1, 2)]
    brute = [np.asarray(rtjax.render(brute_force(scene200), spp=k)) for k in (1, 2)]
    for c, b in zip(culled, brute):
        assert np.ptp(c) > 50  # a real picture
        np.testing.assert_array_equal(c, b)


@pytest.mark.slow
def test_culled_derivatives_equal_brute_force(scene200):
    """Reverse gradient (of the mean image) in every parameter and a forward derivative
    in the centres, both from one linearisation per structure (one compiled program)."""
    st, p0 = scene200.structure, scene200.params

    @functools.partial(jax.jit, static_argnums=1)
    def derivatives(p, st):
        tangent = dataclasses.replace(jax.tree_util.tree_map(jnp.zeros_like, p), centers=jnp.ones_like(p.centers))
        mean = jnp.full((st.height, st.width, 3), 1 / (3 * st.height * st.width), p.centers.dtype)
        _, jvp, grad = linearised(lambda q: rtjax.render(rtjax.Scene(st, q)), p, tangent, mean)
        return grad, jvp

    # the optimised build (not conftest.quick_xla): its LLVM -O0 build measured culled
    # and brute-force centre gradients 1.5e-4 apart, more than the tolerance below
    g_c, j_c = derivatives(p0, st)
    g_b, j_b = derivatives(p0, st.replace(culling=False))
    for name in ("centers", "radii", "diffuse", "kt", "ior", "light_dirs", "eye"):
        a, b = np.asarray(getattr(g_c, name)), np.asarray(getattr(g_b, name))
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7 * max(1.0, np.abs(b).max()), err_msg=name)
    assert np.abs(np.asarray(g_c.centers)).max() > 0
    np.testing.assert_allclose(np.asarray(j_c), np.asarray(j_b), rtol=1e-5, atol=1e-4)


@pytest.mark.slow
def test_culled_silhouette_mode_equals_brute_force(scene200):
    """The silhouette-aware mode goes through the same culled hits (excluded spheres)."""
    culled = np.asarray(rtjax.render(scene200, edges=1.0))
    brute = np.asarray(rtjax.render(brute_force(scene200), edges=1.0))
    np.testing.assert_array_equal(culled, brute)
