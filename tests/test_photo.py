"""Photo fits (`fit(..., photo=True)`, `rtjax fit --photo`): the appearance and camera
parameters stay in their ranges and are named at a bound, a fit through a camera the
model does not share comes back with per-sphere uncertainty and a verdict that names
what the photo cannot tell, and a fit that explains nothing exits 1 naming the cause."""

from __future__ import annotations

import copy
import json
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, quick_env, scene_from_text, truth_deck

import fitting
import rtjax
from fitting.photo import RANGES, Photo
from fitting.verdict import CONFIDENCE, bounds_reached, footprints, undetermined

#: compile-bound fits and tolerance checks: XLA's quick build (`conftest.quick_build`)
pytestmark = pytest.mark.usefixtures("quick_build")


def moved(scene: rtjax.Scene, **deltas) -> rtjax.Scene:
    return scene.replace(**{k: np.asarray(getattr(scene.params, k)) + v for k, v in deltas.items()})


def test_ranges_keep_every_value_inside():
    """However far the solver's coordinate goes, the value stays in its range, and a
    value inside maps back to itself."""
    for name, r in RANGES.items():
        u = jnp.asarray([-1e3, -5.0, 0.0, 5.0, 1e3])
        v = np.asarray(r.value(u))
        assert np.all(v >= r.lo - 1e-9) and np.all(v <= r.hi + 1e-9), name
        x = r.lo + 0.3 * (r.hi - r.lo)
        assert abs(float(r.value(jnp.asarray(r.free(x)))) - x) < 1e-6 * max(1.0, abs(x)), name


def test_photo_starts_as_the_deck(truth):
    """At its start the photo's scene is the deck's in linear light (its colours, lights and
    background decoded by x^2.2, the deck's ke, no dilation) and its camera only blurs:
    the largest-looking opaque sphere keeps its colour."""
    photo = Photo(truth)
    y = photo.y0(jnp.float32)
    params = photo.scene(truth.params, y)
    np.testing.assert_allclose(np.asarray(params.diffuse), np.asarray(truth.params.diffuse) ** 2.2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(params.background) / 255, (np.asarray(truth.params.background) / 255) ** 2.2,
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(params.light_colors) / 255, (np.asarray(truth.params.light_colors) / 255) ** 2.2,
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(params.radii), np.asarray(truth.params.radii), rtol=1e-6)
    assert abs(float(params.ke) - float(truth.params.ke)) < 1e-5
    assert photo.anchor == 0 and list(photo.opaque) == [1]
    values = photo.values(y)
    assert abs(float(values["gamma"]) - 1) < 1e-5 and abs(float(values["blur"]) - 0.7) < 1e-5


def test_bounds_name_runaway_parameters():
    """A photo parameter at an artificial end of its range, or a nuisance blur of
    thousands of pixels, is named; values inside (or at a natural end) are not."""
    y = {"photo": {"blur": jnp.asarray(RANGES["blur"].free(3.0)), "gamma": jnp.asarray(RANGES["gamma"].free(1.0)),
                   "ke": jnp.asarray(RANGES["ke"].free(0.0)), "gain": jnp.asarray(RANGES["gain"].free([1.0, 4.0, 1.0]))},
         "nuisance": {"blur": jnp.log(7646.0), "gamma": jnp.log(1.1)}}
    found = bounds_reached(y)
    assert set(found) == {"blur", "gain[1]"} and found["gain[1]"] > 3.9
    assert bounds_reached({"nuisance": {"blur": jnp.log(7646.0)}}) == {"blur": pytest.approx(7646.0)}


def test_bounds_name_the_channel_and_leave_colours_alone(truth):
    """A gain at the end of its range is named by channel; a colour or background channel
    at 0 or 1 (a black or white channel: natural ends) is not."""
    photo = Photo(truth)
    y = photo.y0(jnp.float64)
    y["albedo"] = jnp.asarray(RANGES["albedo"].free([[1.0, 0.5, 0.0]]))
    y["background"] = jnp.asarray(RANGES["background"].free([0.0, 0.5, 1.0]))
    y["gain"] = jnp.asarray(RANGES["gain"].free([1.0, 1.0, 0.25]))
    assert bounds_reached({"photo": y}, photo) == {"gain (blue)": pytest.approx(0.25, rel=0.01)}


def test_photo_and_nuisance_are_exclusive():
    with pytest.raises(fitting.FitError, match="give photo or nuisance, not both"):
        fitting.FitOptions(photo=True, nuisance=("gain",))


def test_footprints_are_distance_times_pixel_angle(truth):
    p = truth.params
    d = np.linalg.norm(np.asarray(p.centers) - np.asarray(p.eye), axis=1)
    angle = 2 * np.tan(np.radians(float(np.asarray(p.vang)[0])) / 2) / truth.structure.width
    np.testing.assert_allclose(footprints(p, truth.structure.width), d * angle, rtol=1e-6)


def test_undetermined_says_which_spheres_are_open_along_the_view():
    """The verdict's cause names each sphere's σ (its bias in quadrature), goal and
    move, marks those whose worst direction is along the view, and when that is so for
    every one says once that depth is what is open."""
    def sphere(index, sigma, depth, limit=1.0):
        return {"index": index, "moved_px": 2.0, "sigma_total_px": 1.25 * sigma, "sigma_px": sigma,
                "sigma_depth_px": depth, "bias_px": 0.75 * sigma, "limit_px": limit}

    deep, wide = sphere(0, 1.0, 0.95), sphere(3, 2.0, 0.5)
    text = undetermined([deep, wide])
    assert text == ("undetermined: sphere 0 (σ 1.25 px along the view, 3σ over its goal of 1; moved 2.00 px), "
                    "sphere 3 (σ 2.5 px, 3σ over its goal of 1; moved 2.00 px)")
    assert undetermined([deep, sphere(5, 1.2, 1.2, limit=3.0)]) == (
        "undetermined: sphere 0 (σ 1.25 px, 3σ over its goal of 1; moved 2.00 px), "
        "sphere 5 (σ 1.5 px, 3σ over its goal of 3; moved 2.00 px); what the photo leaves open is depth along the view "
        "(across it the outlines fix a centre far better)")


@pytest.mark.slow
def test_photo_fit_through_another_camera(tmp_path):
    """A JPEG of the truth, 96 pixels wide, rendered in linear light as a photo's
    renderer lights a deck (its colours decoded by x^2.2) with 4×4 samples, its colours
    and ke changed (the model's deck keeps the old ones), blurred by σ = 1 px through a
    tone curve and a gain the model does not have: from a unit off, the centres come
    back within 0.1 pixel footprint across the view, no parameter at a bound, the
    residual far below the trivial ones. Two spheres without a floor: their silhouettes'
    sizes cannot tell a shared silhouette offset ('dilate') from their depths, and the
    verdict says so: undetermined, each σ along the view, the error along the view
    within its 3σ."""
    from PIL import Image

    truth = scene_from_text(truth_deck(96))
    shown = truth.replace(diffuse=np.array([[0.8, 0.35, 0.25], [0.25, 0.5, 0.8]]), ke=0.35)
    p = shown.params
    lit = shown.replace(diffuse=np.asarray(p.diffuse) ** 2.2, light_colors=255 * (np.asarray(p.light_colors) / 255) ** 2.2,
                        background=255 * (np.asarray(p.background) / 255) ** 2.2)
    linear = np.asarray(rtjax.render(lit, spp=4)) / 255
    photo = 255 * (np.clip(fitting.smooth(linear * np.array([1.1, 1.0, 0.9]), 1.0), 0, 1) ** (1 / 1.8))
    Image.fromarray(np.clip(photo + 0.5, 0, 255).astype(np.uint8)).save(tmp_path / "photo.jpg", quality=90)
    start = moved(truth, centers=np.array([[0.8, -1.0, 0.6], [-0.7, 1.0, -0.9]]))
    res = fitting.fit(start, str(tmp_path / "photo.jpg"), "centers", photo=True)
    foot = footprints(truth.params, truth.structure.width)
    truth_c = np.asarray(truth.params.centers, np.float64)
    off = np.asarray(res.scene.params.centers, np.float64) - truth_c
    view = truth_c - np.asarray(truth.params.eye, np.float64)
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    along = np.sum(off * view, 1) / foot
    across = np.linalg.norm(off / foot[:, None] - along[:, None] * view, axis=1)
    assert across.max() < 0.1, (across, res.table())
    v = res.verdict
    assert res.converged and not res.ok and not v.bounds
    assert len(v.causes) == 1 and v.causes[0].startswith("undetermined: sphere 0"), v.message
    assert v.causes[0].endswith("what the photo leaves open is depth along the view (across it the outlines fix a "
                                "centre far better)"), v.message
    assert [s["index"] for s in v.spheres] == [0, 1]
    for s, a in zip(v.spheres, along):
        assert CONFIDENCE * s["sigma_px"] > 1 and s["sigma_depth_px"] > 0.99 * s["sigma_px"] and len(s["sigma"]) == 3, s
        assert abs(a) < CONFIDENCE * s["sigma_depth_px"], (along, s)
    assert v.losses["end"] < v.losses["start"] and v.losses["end"] < 0.5 * v.losses["flat"]
    assert set(res.photo) >= {"gain", "gamma", "blur", "field", "ke", "albedo", "dilate", "occlusion"}


@pytest.mark.slow
def test_cli_photo_of_nothing_exits_1_naming_the_cause(tmp_path):
    """A flat grey photo, fitted from two starts (`--starts 2`: `fit_multistart`, which
    judges the start it keeps): no geometry explains it better than a flat image does;
    the report says so and gives each sphere's uncertainty and its move from the deck's
    centre to the kept start's fitted one, and the command exits 1."""
    truth = scene_from_text(truth_deck(32))
    rtjax.save_deck(tmp_path / "start.dat", truth, "x.sunimg")
    rtjax.save_image(tmp_path / "grey.png", np.full((truth.structure.height, truth.structure.width, 3), 128.0))
    out = tmp_path / "out" / "fitted.dat"
    proc = subprocess.run([sys.executable, "-m", "rtjax", "fit", str(tmp_path / "start.dat"), str(tmp_path / "grey.png"),
                           "--photo", "--starts", "2", "--seed", "1", "--max-steps", "4", "-o", str(out)],
                          capture_output=True, text=True, cwd=ROOT, env=quick_env(), timeout=600)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "verdict: FAILED" in proc.stdout and "Traceback" not in proc.stderr
    report = json.loads((tmp_path / "out" / "fitted.json").read_text())
    verdict = report["verdict"]
    assert not verdict["ok"] and verdict["causes"]
    assert any(c.startswith("no better than a flat image") for c in verdict["causes"]), verdict["causes"]
    assert [s["index"] for s in verdict["spheres"]] == [0, 1]
    fitted = rtjax.load_deck(out).frames[0].scene
    moved_by = np.linalg.norm(np.asarray(fitted.params.centers, np.float64)
                              - np.asarray(truth.params.centers, np.float64), axis=1)
    np.testing.assert_allclose([s["moved_units"] for s in verdict["spheres"]], moved_by, rtol=1e-4, atol=1e-5)


@pytest.fixture(scope="module")
def small_fit():
    """A photo fit's problem and stepper at 16 px (the truth as its own target)."""
    from fitting.problem import Problem
    from fitting.solvers import Stepper

    small = scene_from_text(truth_deck(16))
    options = fitting.FitOptions(photo=True)
    problem = Problem.build(small, np.asarray(rtjax.render(small), np.float64), "centers", None, options)
    return problem, Stepper(problem.objective, options.solver, options.rtol, options.atol, problem.jac)


@pytest.mark.slow
def test_verdict_from_the_last_step_equals_a_fresh_evaluation(small_fit):
    """`judge` given the fit's last step on the full-size level (its loss and solver
    state) says exactly what it says when it evaluates that point afresh."""
    from fitting.solve import Single
    from fitting.verdict import judge

    problem, stepper = small_fit
    level = problem.pyramid[-1]
    single = Single(stepper)
    y, state = problem.y0, stepper.init(problem.y0, level)
    for _ in range(3):
        step = single.step(y, state, level, None)
        y, state = step.y, step.state
    assert single.end(y, copy.copy(level)) is None  # another level's
    assert single.end(problem.y0, level) is None  # not where it ended
    end = single.end(y, level)
    assert end is not None
    fresh, reused = judge(problem, single, y), judge(problem, single, y, end)
    assert reused.as_dict() == fresh.as_dict()
    assert [s["index"] for s in fresh.spheres] == [0, 1] and all(np.isfinite(s["sigma_px"]) for s in fresh.spheres)


@pytest.mark.slow
def test_verdict_names_a_non_finite_jacobian(small_fit):
    """A fit whose linearisation at the end is not finite (a render singular there) gets
    a verdict naming that cause, with no uncertainty, instead of a linear-algebra error:
    the fit's own stepper with one Jacobian entry replaced by NaN."""
    from types import SimpleNamespace

    from fitting.solve import Single
    from fitting.verdict import judge

    problem, stepper = small_fit

    class Poisoned(Single):
        def evaluate(self, points, level):
            out = []
            for loss, state in super().evaluate(points, level):
                jac = np.array(state.f_info.jac.as_matrix(), np.float64)
                jac[0, 0] = np.nan
                info = SimpleNamespace(jac=SimpleNamespace(as_matrix=lambda jac=jac: jac), residual=state.f_info.residual)
                out.append((loss, SimpleNamespace(f_info=info)))
            return out

    v = judge(problem, Poisoned(stepper), problem.y0)
    assert not v.ok and v.spheres == []
    assert [c for c in v.causes if c.startswith("undetermined:")] == [
        "undetermined: the Jacobian and residuals at the end hold 1 non-finite values (the render is singular there): "
        "no uncertainty can be given"]


@pytest.mark.slow
def test_several_starts_judge_as_one(small_fit):
    """A multi-start fit's verdict comes from its own batched step
    (`multistart.Parallel.evaluate`: the end and the start's geometry in one call, the
    rest of the starts axis inactive): the same as one start's, to rounding."""
    from fitting.multistart import Parallel
    from fitting.solve import Single
    from fitting.verdict import judge

    problem, stepper = small_fit
    y = jax.tree_util.tree_map(lambda v: v + 0.05, problem.y0)  # geometry and appearance off the start
    one, several = judge(problem, Single(stepper), y), judge(problem, Parallel(stepper, None, "map", 3), y)
    assert several.bounds == one.bounds
    # the causes read alike; their figures (σ, bias: rounded to whole pixels) agree to rounding
    number = r"\d+(?:\.\d+)?"
    assert [re.sub(number, "#", c) for c in several.causes] == [re.sub(number, "#", c) for c in one.causes]
    for a, b in zip(several.causes, one.causes):
        np.testing.assert_allclose([float(x) for x in re.findall(number, a)], [float(x) for x in re.findall(number, b)],
                                   rtol=1e-3, atol=1)
    for k in ("end", "start", "flat"):  # float32 renders of two programs: they round alike to a few 1e-8
        assert several.losses[k] == pytest.approx(one.losses[k], rel=1e-6)
    assert one.losses["start"] != one.losses["end"]
    assert [s["index"] for s in several.spheres] == [s["index"] for s in one.spheres] == [0, 1]
    for a, b in zip(several.spheres, one.spheres):  # σ and bias: float32 Jacobians of two programs, solved
        assert a["moved_px"] == b["moved_px"]  # where depth is all but undetermined (σ of hundreds of px)
        np.testing.assert_allclose([a["sigma_px"], a["bias_px"]], [b["sigma_px"], b["bias_px"]], rtol=1e-3)
