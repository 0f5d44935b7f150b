"""`rtjax bench` on a tiny deck (the machinery, not the speed), and sphere culling: the
same images and derivatives as testing every ray against every sphere.

No timing is asserted anywhere: benchmarks print figures, tests check their shape. So
the bench run and the LM step compile with XLA's backend optimisation off
(`conftest.quick_xla`: the same program, half the compile time); the comparisons of
culled and brute-force renders and derivatives run the optimised build.
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SCENES, quick_xla

import rtjax
from rtjax import bench, spheres
from rtjax.cli import main

DECK = os.path.join(SCENES, "ex2s3.dat")


@pytest.fixture(scope="module")
def tiny_result():
    cfg = bench.Config(ref_depth=6, ref_spp=4, depths=(0, 10), spps=(1, 2, 4), edges=(1.0,), scales=(0.5, 1.0),
                       repeats=1, lm_step=False, numpy_repeats=1, width=32)
    with quick_xla(clear=True):  # its figures are checked for shape and accuracy, not speed
        return bench.run(DECK, cfg, log=lambda line: None)


def test_bench_json_fields_and_plausible_values(tiny_result, tmp_path):
    res = tiny_result
    paths = bench.write_outputs(res, str(tmp_path), "tiny")
    with open(paths["json"]) as f:
        data = json.load(f)  # strict JSON (no NaN/Infinity)
    assert data == json.loads(json.dumps(res))
    for key in ("deck", "width", "height", "n_spheres", "settings", "reference", "derivatives", "numpy", "machine", "config"):
        assert key in data, key
    assert (data["width"], data["height"]) == (32, rtjax.image_height(32, 40, 30))
    with open(paths["plot"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"

    rows = data["settings"]
    knobs = {r["knob"] for r in rows}
    assert knobs == {"reference", "default", "dtype", "depth", "spp", "edges", "scale"}
    for r in rows:
        for key in ("label", "dtype", "depth", "spp", "edges", "scale", "width", "height", "compile_s", "median_s",
                    "runs_s", "psnr_db", "rms_levels", "max_levels", "frac_off"):
            assert key in r, (r["label"], key)
        assert r["median_s"] > 0 and r["compile_s"] >= 0 and len(r["runs_s"]) >= 1
        assert 0 <= r["frac_off"] <= 1 and 0 <= r["max_levels"] <= 255

    ref = next(r for r in rows if r["knob"] == "reference")
    assert (ref["psnr_db"], ref["rms_levels"], ref["max_levels"], ref["frac_off"]) == (None, 0, 0, 0)
    assert (ref["dtype"], ref["depth"], ref["spp"]) == ("float64", 6, 4)

    spp = {r["spp"]: r["rms_levels"] for r in rows if r["knob"] == "spp"}
    assert spp[1] > spp[2] > spp[4], spp  # more samples per pixel, closer to the 4×4 reference
    default = next(r for r in rows if r["knob"] == "default")
    depth0 = next(r for r in rows if r["knob"] == "depth" and r["depth"] == 0)
    assert depth0["rms_levels"] > default["rms_levels"]  # no mirrors or glass: far from the reference
    half = next(r for r in rows if r["knob"] == "scale" and r["scale"] == 0.5)
    assert half["width"] == 16
    f64 = next(r for r in rows if r["knob"] == "dtype" and r["dtype"] == "float64")
    assert abs(f64["rms_levels"] - default["rms_levels"]) < 0.5  # precision is not what limits a 1×1 render
    edges = next(r for r in rows if r["knob"] == "edges")
    assert edges["rms_levels"] < default["rms_levels"]  # box-filtered edges are closer to a supersampled image

    d = data["derivatives"]
    assert (d["width"], d["height"]) == (32, data["height"]) and d["n_params_centers"] == 24
    for name in ("grad", "jacfwd_centers"):
        assert d[name]["median_s"] > 0 and d[name]["ratio"] > 0
    assert "lm_step" not in d

    n = data["numpy"]
    assert n["median_s"] > 0 and n["speedup"] > 0 and n["depth"] == 10
    assert n["rtjax_default_vs_numpy"]["frac_off"] < 0.02  # the same settings, an independent renderer

    text = bench.table_text(data)
    assert "reference" in text and "NumPy" in text and "×" in text


def test_plots_leave_the_callers_backend_alone(tiny_result, tmp_path, monkeypatch):
    """The bench's and the fit report's plots draw on Figures of their own: no
    `matplotlib.use`, which would switch a notebook's backend."""
    import types

    import matplotlib

    from fitting.report import plot_convergence

    calls = []
    monkeypatch.setattr(matplotlib, "use", lambda *a, **k: calls.append(a))
    bench.pareto_plot(tiny_result, str(tmp_path / "pareto.png"))
    history = [{"step": i, "loss": 1.0 / i, "best_loss": 1.0 / i, "width": 16 if i < 3 else 32} for i in range(1, 6)]
    plot_convergence(types.SimpleNamespace(history=history, solver="lm", result="successful"), str(tmp_path / "fit.png"))
    assert not calls
    for name in ("pareto.png", "fit.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_image_errors():
    ref = np.zeros((4, 6, 3))
    assert bench.image_errors(ref, ref) == {"psnr_db": None, "rms_levels": 0.0, "max_levels": 0, "frac_off": 0.0}
    img = ref.copy()
    img[0, 0, 1] = 0.6  # rounds to 1 level
    e = bench.image_errors(img, ref)
    assert e["max_levels"] == 1 and e["frac_off"] == pytest.approx(1 / 24)
    assert e["psnr_db"] == pytest.approx(10 * np.log10(255**2 / (1 / 72)))
    small = np.full((2, 3, 3), 10.0)  # a half-size image is compared pixel for pixel after upsampling
    assert bench.image_errors(small, np.full((4, 6, 3), 10.0))["max_levels"] == 0


def test_lm_step_runs():
    """The Levenberg–Marquardt step the bench times moves the centres (tiny image)."""
    scene = rtjax.load_deck(DECK).frames[0].scene.resized(12)
    st, p0 = scene.structure, scene.params

    def image(p):
        return rtjax.render(rtjax.Scene(st, p))

    with quick_xla(clear=True):
        step = bench._lm_step(st, p0, image)
        y = np.asarray(step())
    assert y.shape == (8, 3) and np.all(np.isfinite(y))


def test_cli_bench_parses_and_rejects_bad_decks(tmp_path, capsys):
    args = rtjax.cli.build_parser().parse_args(["bench", DECK, "--quick", "--scale", "-o", str(tmp_path)])
    assert (args.quick, args.scale, args.outdir) == (True, True, str(tmp_path))
    bad = tmp_path / "bad.dat"
    bad.write_text("sphe 0 0 0\n")
    assert main(["bench", str(bad), "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bad.dat:1:") and "\n" not in err
    assert not list(tmp_path.glob("bench_*"))


def test_random_scene_is_non_overlapping():
    scene = bench.random_scene(200, seed=3, size=40)
    c, r = np.asarray(scene.params.centers, np.float64), np.asarray(scene.params.radii, np.float64)
    gap = np.linalg.norm(c[:, None] - c[None], axis=-1) - (r[:, None] + r[None])
    np.fill_diagonal(gap, np.inf)
    assert gap.min() > 0 and scene.structure.n_spheres == 200
    assert {"opaq", "mirr", "trpa"} <= set(scene.structure.kinds)


# -- culling ---------------------------------------------------------------------------------


def test_small_scenes_stay_on_the_brute_force_path():
    assert not spheres.culls(spheres.CULL_ABOVE) and spheres.culls(spheres.CULL_ABOVE + 1)


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

    with spheres.brute_force():
        t_b, i_b, f_b = (np.asarray(a) for a in spheres.nearest(*args, origin, tmin, exclude))
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
        brute = np.asarray(spheres.transmission(args[0], ray, args[2], args[3], origin, tmin, factor, skip=exclude))
        grid = spheres.light_grid(light, args[2], args[3], tmin)
        assert not bool(grid.over)
        culled = np.asarray(spheres.transmission(args[0], ray, args[2], args[3], origin, tmin, factor, skip=exclude,
                                                 active=active, grid=grid))
        assert 0 < np.mean(brute[a] == 0) < 1
        np.testing.assert_array_equal(culled[a], brute[a])


@pytest.fixture(scope="module")
def scene200():
    return bench.random_scene(200, seed=1, size=24)


def test_culled_render_equals_brute_force(scene200):
    """A random 200-sphere scene: the image (pixel centres and 2×2 samples) is the same
    float for float with culling as with every ray against every sphere."""
    assert spheres.culls(scene200.structure.n_spheres)
    culled = [np.asarray(rtjax.render(scene200, spp=k)) for k in (1, 2)]
    with spheres.brute_force():
        brute = [np.asarray(rtjax.render(scene200, spp=k)) for k in (1, 2)]
    for c, b in zip(culled, brute):
        assert np.ptp(c) > 50  # a real picture
        np.testing.assert_array_equal(c, b)


def test_culled_derivatives_equal_brute_force(scene200):
    """Reverse gradient in every parameter and a forward derivative in the centres."""
    st, p0 = scene200.structure, scene200.params

    def loss(p):
        return rtjax.render(rtjax.Scene(st, p)).mean()

    def jvp(p):
        tangent = jax.tree_util.tree_map(jnp.zeros_like, p)
        tangent = bench._replace_params(tangent, centers=jnp.ones_like(p.centers))
        return jax.jvp(lambda q: rtjax.render(rtjax.Scene(st, q)), (p,), (tangent,))[1]

    # the optimised build (not conftest.quick_xla): its LLVM -O0 build measured culled
    # and brute-force centre gradients 1.5e-4 apart, more than the tolerance below
    g_c, j_c = jax.grad(loss)(p0), jvp(p0)
    with spheres.brute_force():
        g_b, j_b = jax.grad(loss)(p0), jvp(p0)
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
    with spheres.brute_force():
        brute = np.asarray(rtjax.render(scene200, edges=1.0))
    np.testing.assert_array_equal(culled, brute)
