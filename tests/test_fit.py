"""Fitting: recovery of known truths on small images, targets of every kind, bad input,
and a solve that cannot converge (reported, never raised)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading

import numpy as np
import pytest
from conftest import ROOT, quick_env, scene_from_text, truth_deck

import fitting
import rtjax

#: compile-bound fits and tolerance checks: XLA's quick build (`conftest.quick_build`)
pytestmark = pytest.mark.usefixtures("quick_build")

# `truth`: conftest.py's fitting truth, 64 pixels wide


@pytest.fixture(scope="module")
def target(truth) -> np.ndarray:
    """The truth rendered at pixel centres and rounded to levels, as a file would hold it."""
    return np.floor(np.asarray(rtjax.render(truth)) + 0.5)


def moved(scene: rtjax.Scene, **deltas) -> rtjax.Scene:
    return scene.replace(**{k: np.asarray(getattr(scene.params, k)) + v for k, v in deltas.items()})


@pytest.mark.slow
def test_recovers_centres(truth, target):
    """Off by up to 1.5 units (a fifth of a radius) in every direction. Depth (along the
    view, y here) is seen only through perspective, so it is the least determined.
    (Measured 2026-11-28: across 0.0027, depth 0.0075 units, 64 pixels wide.)"""
    start = moved(truth, centers=np.array([[1.5, -1.0, 1.2], [-1.3, 1.0, -1.4]]))
    res = fitting.fit(start, target, "centers", max_steps=25)
    err = np.abs(np.asarray(res.scene.params.centers) - np.asarray(truth.params.centers))
    assert err[:, [0, 2]].max() < 0.01 and err[:, 1].max() < 0.02, res.table()
    assert res.history and res.history[-1]["best_loss"] < res.history[0]["loss"]


class _Level:
    """A pyramid level for `compile_ahead`: its name and whether it is a whole image."""

    def __init__(self, name: str, whole: bool):
        self.name, self.whole = name, whole


def _ahead(fail: str = ""):
    """`fitting.solvers.compile_ahead` over a coarse and a whole-image level whose traces
    and compiles are logged: the whole-image trace waits (up to 5 s) for the coarse
    compile to begin, logging "overlapped" if it did, and that compile for the trace to
    end; the level named `fail` raises. → (its return, the log)."""
    from fitting.solvers import compile_ahead

    log, compiling, traced = [], threading.Event(), threading.Event()

    class Lowered:
        def __init__(self, name):
            self.name = name

        def compile(self):
            if self.name == "coarse":
                compiling.set()
                traced.wait(5)
            log.append(f"compiled {self.name}")
            if fail == self.name:
                raise RuntimeError(f"out of memory compiling {self.name}")

    def lower(level):
        if level.name == "whole":
            if compiling.wait(5):
                log.append("overlapped")
            traced.set()
        log.append(f"traced {level.name}")
        return Lowered(level.name)

    return compile_ahead(lower, [_Level("coarse", False), _Level("whole", True)]), log


def test_compile_ahead_traces_each_level_beside_a_compile():
    """The coarse level is traced, then compiled while the whole-image level is traced (a
    trace holds Python's lock, a compile does not); it returns once the coarse one is
    compiled, the whole-image one compiling in the thread it returns."""
    thread, log = _ahead()
    assert log[:3] == ["traced coarse", "overlapped", "traced whole"] and "compiled coarse" in log, log
    thread.join(30)
    assert sorted(log) == ["compiled coarse", "compiled whole", "overlapped", "traced coarse", "traced whole"]


def test_compile_ahead_raises_the_first_compiles_error():
    with pytest.raises(RuntimeError, match="out of memory compiling coarse"):
        _ahead(fail="coarse")


def test_compile_ahead_keeps_the_whole_image_compiles_error_for_its_level(monkeypatch):
    """The whole-image level's compile fails in its thread: the thread does not report it
    (`threading.excepthook` printed its traceback); its level raises the error when it
    waits for it."""
    unhandled = []
    monkeypatch.setattr(threading, "excepthook", unhandled.append)
    thread, log = _ahead(fail="whole")
    thread.join(30)
    assert "compiled whole" in log and unhandled == []
    with pytest.raises(RuntimeError, match="out of memory compiling whole"):
        thread.wait()


def test_compile_ahead_needs_a_whole_image_level_after_others():
    from fitting.solvers import compile_ahead

    def lower(level):
        raise AssertionError("nothing is traced")

    assert compile_ahead(lower, [_Level("coarse", False), _Level("fine", False)]) is None
    assert compile_ahead(lower, [_Level("whole", True)]) is None


def _iteration(loss, accepted, promised):
    """One iteration's `Step` of two starts that did not say they are done (`LevelBook.update`)."""
    from fitting.solvers import Step

    return Step(None, None, np.zeros(2, bool), np.zeros(2, np.int32), loss, accepted, promised)


@pytest.mark.parametrize("coarse", [False, True])
def test_a_level_stops_after_its_patience_without_progress(coarse):
    """`LevelBook`: a start whose steps improve its best loss by less than GAIN for
    PATIENCE steps in a row stops (accepted steps that gained less, or rejected ones
    that promised less); a full-size level calls that a success (levelled off), a
    coarse one hands over without a verdict. A gain in between restarts the count."""
    from fitting.solve import GAIN, PATIENCE, LevelBook
    from fitting.solvers import CODES

    book = LevelBook(2, coarse, 0.0)
    yes, no = np.ones(2, bool), np.zeros(2, bool)
    book.update(_iteration(np.array([1.0, 1.0]), yes, np.zeros(2)))
    book.update(_iteration(np.array([0.5, 0.5]), yes, np.full(2, 0.6)))
    for _ in range(PATIENCE - 1):
        book.update(_iteration(np.array([0.499, 0.4]), yes, np.full(2, 0.3)))
        assert not book.stopped.any()
    # rejected: start 0's model promised less than GAIN, start 1's more (start 1 gained before)
    book.update(_iteration(np.array([0.499, 0.4]), no, np.array([GAIN / 2, 2 * GAIN])))
    assert book.stopped.tolist() == [True, False]
    assert book.levelled.tolist() == [not coarse, False]
    assert book.results[0] == CODES["successful"] and book.best[0] == 0.499


@pytest.mark.parametrize("coarse", [False, True])
def test_a_level_stops_after_rejected_steps_in_a_row(coarse):
    """`LevelBook`: REJECTIONS rejected steps in a row whose model promised a gain stop
    a start (the solver found no shorter step that gains); fewer do not, and an
    accepted step restarts the count."""
    from fitting.solve import GAIN, REJECTIONS, LevelBook
    from fitting.solvers import CODES

    book = LevelBook(2, coarse, 0.0)
    no, promise = np.zeros(2, bool), np.full(2, 10 * GAIN)
    book.update(_iteration(np.array([1.0, 1.0]), np.ones(2, bool), promise))
    for _ in range(REJECTIONS - 1):
        book.update(_iteration(np.array([1.0, 1.0]), no, promise))
    book.update(_iteration(np.array([1.0, 0.5]), np.array([False, True]), promise))
    assert book.stopped.tolist() == [True, False]
    assert book.levelled.tolist() == [not coarse, False]
    assert book.results[0] == CODES["successful"] and book.best.tolist() == [1.0, 0.5]
    for _ in range(REJECTIONS - 1):
        book.update(_iteration(np.array([1.0, 0.5]), no, promise))
    assert not book.stopped[1]


@pytest.mark.slow
def test_recovers_colours_and_ke(truth, target):
    start = truth.replace(diffuse=np.full((2, 3), 0.5), ke=0.5)
    res = fitting.fit(start, target, "colors,ke", max_steps=20)
    np.testing.assert_allclose(np.asarray(res.scene.params.diffuse), np.asarray(truth.params.diffuse), atol=2e-3)
    assert abs(float(res.scene.params.ke) - 0.25) < 2e-3
    assert res.converged, res.message


@pytest.mark.slow
def test_recovers_radii_and_light_direction(truth, target):
    start = truth.replace(radii=np.array([7.0, 8.0]), light_dirs=np.array([[0.6, -1.0, 0.5]]))
    res = fitting.fit(start, target, "radii,light", max_steps=30)
    np.testing.assert_allclose(np.asarray(res.scene.params.radii), [8, 7], atol=0.03)
    fitted = np.asarray(res.scene.params.light_dirs[0])
    want = np.array([0.4, -1, 0.8])
    cos = fitted @ want / np.linalg.norm(fitted) / np.linalg.norm(want)
    assert cos > 1 - 1e-5, fitted


@pytest.mark.slow
def test_bounded_parameters_stay_in_range(truth):
    """A target no valid colour can match (pure white): colours end at the bound, never past it."""
    white = np.full((truth.structure.height, truth.structure.width, 3), 255.0)
    res = fitting.fit(truth, white, "colors,ke", max_steps=8)
    d = np.asarray(res.scene.params.diffuse)
    assert d.min() >= 0 and d.max() <= 1 and 0 <= float(res.scene.params.ke) <= 1


@pytest.mark.slow
def test_only_chosen_spheres_move(truth, target):
    start = moved(truth, centers=np.array([[1.0, 0, 0.5], [0.5, 0, 0.5]]))
    res = fitting.fit(start, target, "centers", spheres=[1], max_steps=5)
    np.testing.assert_array_equal(np.asarray(res.scene.params.centers[0]), np.asarray(start.params.centers[0]))
    assert [r[0] for r in res.table()] == ["sphere 1 centre"]


@pytest.mark.slow
def test_target_of_another_size_with_the_same_aspect(truth):
    big = truth.resized(80)
    target = np.asarray(rtjax.render(big))
    res = fitting.fit(truth, target, "ke", max_steps=3)
    assert (res.scene.structure.width, res.scene.structure.height) == (80, big.structure.height)


def test_target_of_the_wrong_aspect_is_a_clear_error(truth):
    with pytest.raises(fitting.FitError, match="aspect"):
        fitting.fit(truth, np.zeros((64, 64, 3)), "centers")


def test_non_finite_target_is_a_clear_error(truth, target):
    """NaN or infinity in a target array made every residual NaN (and the fit ran on);
    it is refused with the count (image files holding them are refused when read)."""
    bad = target.copy()
    bad[3, 4] = [np.nan, np.inf, 0]
    with pytest.raises(fitting.FitError, match="target image has 2 non-finite values"):
        fitting.fit(truth, bad, "centers")


@pytest.mark.parametrize("mask, says", [(np.full((48, 64), np.nan), "weights must be numbers in"),
                                        (np.full((48, 64), 2.0), "weights must be numbers in"),
                                        (np.zeros((48, 64)), "leaves no pixel to fit")])
def test_bad_masks_are_clear_errors(mask, says):
    """A mask with NaN or weights outside [0, 1], or one that ignores every pixel, ran a
    fit of NaN or of nothing; each is refused."""
    from fitting.objective import prepare_mask

    with pytest.raises(fitting.FitError, match=says):
        prepare_mask(mask, 48, 64)
    assert prepare_mask(np.ones((48, 64), bool), 48, 64).shape == (48, 64, 1)


@pytest.mark.parametrize("bad, match", [(dict(free="wings"), "unknown parameter family"), (dict(solver="newton"), "unknown solver"),
                                        (dict(free="kt"), "kt: none of"), (dict(spheres=[5]), "out of range")])
def test_bad_requests(truth, target, bad, match):
    kwargs = dict(free="centers") | bad
    with pytest.raises(fitting.FitError, match=match):
        fitting.fit(truth, target, **kwargs)


@pytest.mark.parametrize("bad, match", [(dict(levels=0), "levels must be"), (dict(levels=[0, 32]), "levels must be"),
                                        (dict(levels=2.5), "levels must be"), (dict(loss_scale=-1.0), "loss_scale must be"),
                                        (dict(loss_scale=float("nan")), "loss_scale must be"),
                                        (dict(polish=-1.0), "polish must be")])
def test_bad_options(bad, match):
    """Values with no meaning are refused when the options are made, not taken for
    something else (a count of 0 levels was one level; a negative loss scale or
    polishing width ran a fit)."""
    with pytest.raises(fitting.FitError, match=match):
        fitting.FitOptions(**bad)
    assert fitting.FitOptions(levels=1).levels == 1 and fitting.FitOptions(levels=[32, 64]).levels == [32, 64]


@pytest.mark.slow
def test_a_solve_that_cannot_converge_reports_so(truth, target):
    """One step from far away: the result says the steps ran out; nothing raises."""
    start = moved(truth, centers=np.array([[3.0, 0, 2.0], [-3.0, 0, -2.0]]))
    res = fitting.fit(start, target, "centers", max_steps=1)
    assert not res.converged and res.result == "max_steps_reached" and res.message
    assert res.steps == 1 and np.all(np.isfinite(np.asarray(res.scene.params.centers)))


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["gn", "dogleg", "bfgs"])
def test_other_solvers_reduce_the_loss(truth, target, solver):
    start = truth.replace(ke=0.4, diffuse=np.asarray(truth.params.diffuse) * 0.8)
    # 4 box-filtered steps, then 4 at pixel centres, which hand over to the narrow robust
    # scale (objective.EXACT_SCALE) within 3 levels RMS, where colours still move slowly
    res = fitting.fit(start, target, "colors,ke", solver=solver, max_steps=8)
    assert res.history[-1]["best_loss"] < 0.2 * res.history[0]["loss"]
    assert abs(float(res.scene.params.ke) - 0.25) < 0.05


@pytest.mark.slow
def test_photo_like_target_with_gain_and_gamma(truth):
    """A target seen through a camera response 255·(1.2·I/255)^0.9 plus noise: the
    nuisance parameters absorb the response and the colours come back."""
    rng = np.random.default_rng(0)
    image = np.asarray(rtjax.render(truth))
    photo = 255 * np.clip(1.2 * image / 255, 0, 1) ** 0.9 + rng.normal(0, 2, image.shape)
    start = truth.replace(diffuse=np.full((2, 3), 0.5))
    res = fitting.fit(start, np.clip(photo, 0, 255), "colors", nuisance=("gain", "gamma"), max_steps=25)
    np.testing.assert_allclose(np.asarray(res.scene.params.diffuse), np.asarray(truth.params.diffuse), atol=0.03)
    assert abs(res.nuisance["gain"] - 1.2) < 0.08 and abs(res.nuisance["gamma"] - 0.9) < 0.05


@pytest.mark.slow
def test_photo_like_target_through_the_camera_model(tmp_path):
    """A JPEG photo (quality 85, Pillow's 4:2:0 chroma) of the truth, 96 pixels wide,
    rendered with 4×4 samples, blurred by σ = 0.8 px and seen through
    255·(1.1·I/255)^0.9, with noise of σ = 2 levels: `nuisance=("camera",)` brings the
    centres back from a unit off, and the response and blur close to how they were
    made. (Measured: 0.013 units in 13 iterations; without chroma and order, 0.12.)"""
    from PIL import Image

    truth = scene_from_text(truth_deck(96))
    rng = np.random.default_rng(1)
    made = {"gain": 1.1, "gamma": 0.9, "blur": 0.8}
    photo = np.asarray(fitting.camera(rtjax.render(truth, spp=4), made)) + rng.normal(0, 2, (truth.structure.height, truth.structure.width, 3))
    Image.fromarray(np.clip(photo + 0.5, 0, 255).astype(np.uint8)).save(tmp_path / "photo.jpg", quality=85)
    start = moved(truth, centers=np.array([[0.8, -1.0, 0.6], [-0.7, 1.0, -0.9]]))
    res = fitting.fit(start, str(tmp_path / "photo.jpg"), "centers", nuisance=("camera",))
    err = np.abs(np.asarray(res.scene.params.centers) - np.asarray(truth.params.centers))
    assert err.max() < 0.05, res.table()
    assert abs(res.nuisance["gamma"] - 0.9) < 0.03 and abs(res.nuisance["gain"] - 1.1) < 0.05, res.nuisance
    assert abs(res.nuisance["blur"] - 0.8) < 0.15 and 0.3 < res.nuisance["chroma"] < 2, res.nuisance


def test_targets_from_files_in_both_byte_orders(truth, target, tmp_path):
    for name, kw in (("t.sunimg", {}), ("t_assignment.sunimg", {"assignment_order": True}), ("t.png", {})):
        rtjax.save_image(tmp_path / name, target, **kw)
        loaded = fitting.load_target(str(tmp_path / name), **kw)
        np.testing.assert_array_equal(loaded, target)


@pytest.mark.slow
def test_cli_fit_writes_its_outputs(tmp_path, truth, target):
    """`rtjax fit` end to end: progress lines (first what the first step waits for, then a
    line per step with the time since the start, as the report's history has it), a
    table, the fitted deck (a valid deck that renders the fitted image), the image, the
    JSON report and the plot; exit 0 or 1."""
    rtjax.save_image(tmp_path / "target.sunimg", target)
    start = truth.replace(ke=0.4)
    rtjax.save_deck(tmp_path / "start.dat", start, "start.sunimg")
    out = tmp_path / "out" / "fitted.dat"
    proc = subprocess.run(
        [sys.executable, "-m", "rtjax", "fit", str(tmp_path / "start.dat"), str(tmp_path / "target.sunimg"),
         "--free", "ke", "-o", str(out), "--max-steps", "12"],
        capture_output=True, text=True, cwd=ROOT, env=quick_env(), timeout=600,
    )
    assert proc.returncode in (0, 1), proc.stderr
    assert "step   1" in proc.stdout and "ke" in proc.stdout and "Traceback" not in proc.stderr
    report = json.loads((tmp_path / "out" / "fitted.json").read_text())
    assert report["free"] == ["ke"] and report["iterations"] == len(report["history"]) >= 1
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("the first step waits") and "not kept: RTJAX_CACHE=off" in lines[0], lines[0]
    at = [int(m) for m in re.findall(r"^step +\d+ .* at (\d+) s$", proc.stdout, re.M)]
    assert at == [round(row["elapsed"]) for row in report["history"]], (at, report["history"])
    assert abs(report["parameters"][0]["fitted"] - 0.25) < 0.01
    assert (proc.returncode == 0) == report["converged"]
    fitted = rtjax.load_deck(out)
    assert abs(float(fitted.frames[0].scene.params.ke) - report["parameters"][0]["fitted"]) < 1e-6
    assert rtjax.load_image(tmp_path / "out" / "fitted.sunimg").shape == target.shape
    assert (tmp_path / "out" / "fitted_convergence.png").stat().st_size > 1000


def test_cli_fit_bad_input_is_one_line(tmp_path, truth):
    rtjax.save_deck(tmp_path / "start.dat", truth, "x.sunimg")
    rtjax.save_image(tmp_path / "square.png", np.zeros((64, 64, 3)))
    proc = subprocess.run([sys.executable, "-m", "rtjax", "fit", str(tmp_path / "start.dat"), str(tmp_path / "square.png")],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 2 and "aspect" in proc.stderr and "Traceback" not in proc.stderr and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1
    rtjax.save_image(tmp_path / "t.png", np.zeros((truth.structure.height, truth.structure.width, 3)))
    proc = subprocess.run([sys.executable, "-m", "rtjax", "fit", str(tmp_path / "start.dat"), str(tmp_path / "t.png"),
                           "--nuisance", "gain,chroma"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().endswith("the nuisance parameters chroma and order model a photo's blur: fit blur with them")


@pytest.mark.slow
def test_recovers_the_texels_it_can_see(tmp_path):
    """A texture as a free parameter family: the texels on the side facing the camera
    come back to within 2 levels (the far side is not seen and keeps its start value);
    the fitted deck points at the fitted texture, written beside it."""
    from fitting.report import save_outputs

    rng = np.random.default_rng(0)
    rtjax.save_image(tmp_path / "t.sunimg", rng.uniform(20, 235, (4, 8, 3)))
    (tmp_path / "s.dat").write_text(
        "sphe 0 0 0 10\ntmap t.sunimg 0.2 10\nplig 0.3 -1 0.6 230 230 230\nelig 0.3\nback 0 0 40\n"
        "eyep 0 -40 8\nrefp 0 0 0\nvang 40 40\nsize 48\nrend x.sunimg\n"
    )
    truth = rtjax.load_deck(tmp_path / "s.dat").frames[0].scene
    start = truth.replace(textures=(np.full((4, 8, 3), 128.0),))
    res = fitting.fit(start, np.asarray(rtjax.render(truth)), "textures", max_steps=15)
    fitted, true = np.asarray(res.scene.params.textures[0]), np.asarray(truth.params.textures[0])
    assert np.abs(fitted - true)[:3, 1:3].max() < 2  # texels facing the camera (u in (0, ½), away from the poles)
    np.testing.assert_allclose(fitted[:, 5:7], 128.0, atol=1e-3)  # the far side: unseen, unchanged
    paths = save_outputs(res, str(tmp_path / "out"), "fitted")
    again = rtjax.load_deck(paths["deck"]).frames[0].scene
    np.testing.assert_allclose(np.asarray(again.params.textures[0]), np.clip(np.floor(fitted + 0.5), 0, 255))
