"""Texture recovery: the matrix-free solver, the texel schedule, seen and unseen texels,
and fits to several frames at once."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, quick_env

import fitting
import rtjax
from fitting.problem import Problem
from fitting.texels import SEEN_ABOVE, coverage

#: A textured ball seen from -y and from +x; its texture is written by `ball`.
DECK = """sphe 0 0 0 10
tmap t.sunimg
plig 0.4 -1 0.7 255 255 255
elig 0.4
back 30 30 40
refp 0 0 0
vang 40 40
size 40
eyep 0 -30 5
rend a.sunimg
eyep 30 0 5
rend b.sunimg
"""


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    """(deck path, true frames' scenes, true texture (8, 16, 3)): 384 free numbers, so a
    fit of them is matrix-free."""
    folder = tmp_path_factory.mktemp("ball")
    texture = np.random.default_rng(0).uniform(30, 225, (8, 16, 3)).round()
    rtjax.save_image(folder / "t.sunimg", texture)
    (folder / "ball.dat").write_text(DECK)
    deck = rtjax.load_deck(folder / "ball.dat")
    return folder / "ball.dat", [f.scene for f in deck.frames], texture


def grey(scene: rtjax.Scene) -> rtjax.Scene:
    return scene.replace(textures=(np.full(scene.params.textures[0].shape, 128.0),))


def rendered(scene: rtjax.Scene) -> np.ndarray:
    return np.floor(np.asarray(rtjax.render(scene)) + 0.5)


def test_matrix_free_above_the_threshold(ball):
    _, truths, _ = ball
    target = rendered(truths[0])
    many = Problem.build(grey(truths[0]), target, "textures", None, fitting.FitOptions())
    few = Problem.build(truths[0], target, "ke", None, fitting.FitOptions())
    assert many.selection.size() == 384 and many.jac == "matfree"
    assert few.jac == "fwd"
    # a texture fit is the full-size image, every pixel, plain render: wide robust scale, then the fit's
    assert [s.plain for s in many.pyramid] == [True, True] and many.widths == [40, 40]
    assert many.pyramid[0].xy.shape == (40 * 40, 2) and float(many.pyramid[0].scale) > float(many.pyramid[1].scale) == 1.0


def test_more_frames_see_more_texels(ball):
    _, truths, _ = ball
    one, two = coverage(truths[:1]), coverage(truths)
    seen1, seen2 = one.seen(0), two.seen(0)
    assert seen1.sum() < seen2.sum() and np.all(seen2 >= seen1)
    np.testing.assert_allclose(two.weights[0], one.weights[0] + coverage(truths[1:]).weights[0], rtol=1e-5, atol=1e-6)
    s = two.summary()[0]
    assert s["texels"] == 128 and s["seen"] == int(seen2.sum()) and s["seen"] + s["weak"] + s["not_seen"] == 128
    assert s["seen_above"] == SEEN_ABOVE and s["not_seen"] > 0  # the poles' and the far side's rows


@pytest.mark.slow
def test_recovers_the_seen_texels_of_two_frames(ball):
    """Grey start, two exact targets: the seen texels within 2 levels RMS; texels no view
    sees reported and left exactly as they started; every frame gets the same texels."""
    _, truths, texture = ball
    starts = [grey(t) for t in truths]
    res = fitting.fit(starts, [rendered(t) for t in truths], "textures", max_steps=15)
    fitted = np.asarray(res.scene.params.textures[0])
    seen, weights = res.texels.seen(0), res.texels.weights[0]
    err = np.abs(fitted - texture)[seen]
    assert seen.sum() > 40 and np.sqrt(np.mean(err**2)) < 2, np.sqrt(np.mean(err**2))
    np.testing.assert_array_equal(fitted[weights <= 0], 128.0)
    assert res.texels.summary()[0]["not_seen"] == int((weights <= 0).sum()) > 0
    frames = fitting.fitted_scenes(starts, res.selection, res.y)
    assert all(np.array_equal(np.asarray(f.params.textures[0]), fitted) for f in frames)
    np.testing.assert_array_equal(np.asarray(frames[1].params.eye), np.asarray(truths[1].params.eye))


def test_matrix_free_agrees_with_the_dense_jacobian(ball, monkeypatch):
    """Levenberg–Marquardt steps of a small texel fit (a 4×8 texture: 96 numbers) from
    the same trust region: the dense forward-mode Jacobian's and the matrix-free ones
    give the same seen texels within a tenth of a level."""
    import equinox as eqx

    from fitting.solvers import Stepper

    import fitting.matrixfree

    # solved to convergence, the matrix-free step is the dense one's
    monkeypatch.setattr(fitting.matrixfree, "LSMR_RTOL", 1e-7)
    monkeypatch.setattr(fitting.matrixfree, "LSMR_MAX_STEPS", 500)
    _, truths, _ = ball
    texture = np.random.default_rng(1).uniform(30, 225, (4, 8, 3)).astype(np.float32)
    small = rtjax.Scene(truths[0].structure.replace(texture_shapes=((4, 8),)), truths[0].params).replace(textures=(texture,))
    problem = Problem.build(grey(small), rendered(small), "textures", None, fitting.FitOptions())
    level = problem.pyramid[0]
    texels = []
    for jac in ("fwd", "matfree"):
        stepper = Stepper(problem.objective, "lm", 1e-5, 1e-7, jac)
        y, state = problem.y0, stepper.init(problem.y0, level)
        state = eqx.tree_at(lambda s: s.search_state.step_size, state, np.float32(100.0))
        for _ in range(2):  # the first evaluates the start, the second moves
            step = stepper.step(y, state, level)
            y, state = step.y, step.state
        texels.append(np.asarray(problem.selection.params(y["scene"]).textures[0]))
    seen = coverage([small]).seen(0)
    assert seen.sum() > 8 and np.abs(texels[0] - 128)[seen].max() > 20  # the steps went somewhere
    # where seen: weakly seen texels are the ill-conditioned directions
    assert np.abs(texels[0] - texels[1])[seen].max() < 0.1, np.abs(texels[0] - texels[1])[seen].max()


def test_one_target_per_frame(ball):
    _, truths, _ = ball
    with pytest.raises(fitting.FitError, match="1 targets for 2 frames"):
        fitting.fit(truths, [rendered(truths[0])], "textures")
    with pytest.raises(fitting.FitError, match="a photo fit takes one photo"):
        fitting.fit(truths, [rendered(t) for t in truths], "centers", photo=True)


@pytest.mark.slow
def test_cli_fits_textures_from_two_frames(ball, tmp_path):
    """`rtjax fit DECK T0 T1 --free textures`: the texture file beside the fitted deck,
    its tmap line pointing at it, both frames kept, the coverage in the table and JSON."""
    deck, truths, _ = ball
    rtjax.save_image(tmp_path / "grey.sunimg", np.full((8, 16, 3), 128.0))
    start = (deck.parent / "ball.dat").read_text().replace("tmap t.sunimg", "tmap grey.sunimg")
    (tmp_path / "start.dat").write_text(start)
    for k, t in enumerate(truths):
        rtjax.save_image(tmp_path / f"t{k}.sunimg", rendered(t))
    out = tmp_path / "out" / "fitted.dat"
    proc = subprocess.run([sys.executable, "-m", "rtjax", "fit", str(tmp_path / "start.dat"), str(tmp_path / "t0.sunimg"),
                           str(tmp_path / "t1.sunimg"), "--free", "textures", "-o", str(out), "--max-steps", "8"],
                          capture_output=True, text=True, cwd=ROOT, env=quick_env(), timeout=600)
    assert proc.returncode in (0, 1), proc.stderr
    assert "texels seen" in proc.stdout and "not seen" in proc.stdout
    fitted = rtjax.load_deck(out)
    assert len(fitted.frames) == 2 and fitted.frames[0].scene.structure.texture_files == ("fitted_texture0.sunimg",)
    texture = rtjax.load_image(tmp_path / "out" / "fitted_texture0.sunimg")
    np.testing.assert_array_equal(np.asarray(fitted.frames[1].scene.params.textures[0]), texture)
    report = json.loads((tmp_path / "out" / "fitted.json").read_text())
    assert report["texels"][0]["texels"] == 128 and report["texels"][0]["seen"] > 40


def test_smoothness_prior_terms(ball):
    """One difference per pair of neighbours: along rows, columns wrapping, and down columns."""
    from fitting.texels import texel_differences

    t = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    d = np.asarray(texel_differences([t]))
    assert d.shape == (2 * 3 + 1 * 3, 3)
    np.testing.assert_array_equal(d[:6], (np.roll(t, -1, axis=1) - t).reshape(-1, 3))
    np.testing.assert_array_equal(d[6:], np.full((3, 3), 9.0))
    _, truths, _ = ball
    with pytest.raises(fitting.FitError, match="smooth is a prior on texels"):
        fitting.fit(truths[0], rendered(truths[0]), "ke", smooth=1.0)
    with pytest.raises(fitting.FitError, match="smooth must be ≥ 0"):
        fitting.FitOptions(smooth=-1.0)
