"""fitting.objective: the exact (polish) level's model is the pixel-centre render in value
and the silhouette-aware render in derivative."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import scene_from_text

import rtjax
from fitting.objective import Objective, apply_nuisance, make_levels
from fitting.select import Selection

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


def test_exact_level_values_are_pixel_centres_and_derivatives_the_aware_ones():
    scene = scene_from_text(DECK).astype(jnp.float64)
    target = np.zeros((scene.structure.height, scene.structure.width, 3))
    weight = np.ones(target.shape[:2] + (1,))
    w = scene.structure.width
    soft, exact = make_levels(target, weight, [w, w], [1.0, 1.0], jnp.float64, exact=[False, True])
    selection = Selection(scene, "centers", None)
    objective = Objective(selection, None, "l2", 10.0, exact_levels=True)
    y = {"scene": selection.y0()}

    plain = np.asarray(rtjax.render(scene)).reshape(-1, 3)
    aware = np.asarray(rtjax.render(scene, edges=1.0)).reshape(-1, 3)
    np.testing.assert_allclose(np.asarray(objective.model(y, soft)), aware, atol=1e-9)
    np.testing.assert_allclose(np.asarray(objective.model(y, exact)), plain, atol=1e-9)
    assert np.abs(plain - aware).max() > 10  # the two differ at the outline

    def jac(samples):
        return np.asarray(jax.jacfwd(lambda y: objective.model(y, samples))(y)["scene"]["centers"])

    j_soft, j_exact = jac(soft), jac(exact)
    np.testing.assert_allclose(j_exact, j_soft, atol=1e-9)
    assert np.abs(j_soft).max() > 1  # edges move under the derivative


def test_apply_nuisance_takes_the_units_fit_reports():
    """FitResult.nuisance gives gain and γ themselves; the solver moves their logs."""
    image = jnp.array([[[0.0, 51.0, 200.0]]])
    expect = 255 * np.clip(1.5 * np.array([0.0, 51.0, 200.0]) / 255, 0, 1) ** 0.8
    np.testing.assert_allclose(np.asarray(apply_nuisance(image, {"gain": 1.5, "gamma": 0.8}))[0, 0], expect, rtol=1e-6)
    logs = {"gain": np.log(1.5), "gamma": np.log(0.8), "blur": 0.0}
    np.testing.assert_allclose(np.asarray(apply_nuisance(image, logs, logs=True))[0, 0], expect, rtol=1e-6)


def test_only_an_exact_polish_makes_an_exact_level():
    from fitting.solve import prepare_fit

    scene = scene_from_text(DECK)
    target = np.zeros((scene.structure.height, scene.structure.width, 3))
    args = (target, "centers", None, None, None, None, 0.02, "cauchy", 10.0, None, (), None, False)
    pyramid, objective = prepare_fit(scene, *args)[5:]
    assert [float(s.exact) for s in pyramid] == [0.0] * len(pyramid)
    assert not objective.exact_levels  # no pixel-centre render compiled into the step
    pyramid, objective = prepare_fit(scene, *args, exact_polish=True)[5:]
    assert objective.exact_levels
    assert [float(s.exact) for s in pyramid] == [0.0] * (len(pyramid) - 1) + [1.0]
    assert float(pyramid[-1].width) == pytest.approx(0.02)
    assert prepare_fit(scene, *args[:6], None, *args[7:], exact_polish=True)[5][-1].exact == 0  # no polish: none exact
