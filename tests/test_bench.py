"""`rtjax bench` on a tiny deck (the machinery, not the speed).

No timing is asserted anywhere: benchmarks print figures, tests check their shape. So
the bench run and the LM step compile with XLA's backend optimisation off
(`conftest.quick_xla`: the same program, half the compile time).
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from conftest import SCENES, quick_xla

import rtjax
from rtjax import bench
from rtjax.bench import derivatives
from rtjax.cli import main

DECK = os.path.join(SCENES, "ex2s3.dat")


@pytest.fixture(scope="module")
def tiny_result():
    cfg = bench.Config(ref_depth=6, ref_spp=4, depths=(0, 10), spps=(1, 2, 4), edges=(1.0,), subdivides=(2,), scales=(0.5, 1.0),
                       repeats=1, lm_step=False, numpy_repeats=1, width=32)
    with quick_xla(clear=True):  # its figures are checked for shape and accuracy, not speed
        return bench.run(DECK, cfg, log=lambda line: None)


@pytest.mark.slow
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
    assert knobs == {"reference", "default", "dtype", "depth", "spp", "edges", "subdivide", "scale"}
    for r in rows:
        for key in ("label", "dtype", "depth", "spp", "edges", "subdivide", "scale", "width", "height", "compile_s", "median_s",
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
    sub = next(r for r in rows if r["knob"] == "subdivide")
    assert (sub["edges"], sub["subdivide"], sub["label"]) == (1.0, 2, "edges 1 px, 4×4 sub")
    assert sub["rms_levels"] < edges["rms_levels"]  # sub-boxes: closer still (measured 2.28 vs 4.87)

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


@pytest.mark.slow
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


@pytest.mark.slow
def test_lm_step_runs():
    """The Levenberg–Marquardt step the bench times moves the centres (tiny image)."""
    scene = rtjax.load_deck(DECK).frames[0].scene.resized(12)
    st, p0 = scene.structure, scene.params

    def image(p):
        return rtjax.render(rtjax.Scene(st, p))

    with quick_xla(clear=True):
        step = derivatives.lm_step(p0, image)
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
