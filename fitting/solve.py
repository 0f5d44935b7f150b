"""`fit`: recover scene parameters from a target image with optimistix solvers.

The solver is stepped by hand (`init`/`step`/`terminate`, optimistix's interactive
API), one jit-compiled step per iteration, so every iteration is reported (step, loss,
time), the best parameters so far are kept whatever happens, and a failure is a result
code and message, never an exception. Coarse-to-fine: each pyramid level starts from
the previous level's best parameters; iterations count across levels.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import rtjax

from .errors import FitError
from .objective import (
    LOSSES,
    Objective,
    downsample,
    load_target,
    match_size,
    nuisance_y0,
    prepare_mask,
    schedule_widths,
)
from .select import Selection

SOLVERS = {
    "lm": lambda rtol, atol: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
    "gn": lambda rtol, atol: optx.GaussNewton(rtol=rtol, atol=atol),
    "dogleg": lambda rtol, atol: optx.Dogleg(rtol=rtol, atol=atol),
    "bfgs": lambda rtol, atol: optx.BFGS(rtol=rtol, atol=atol),
}


@dataclasses.dataclass
class FitResult:
    """What a fit returns: the fitted scene (full size, deck units) and how it got there."""

    scene: rtjax.Scene
    start: rtjax.Scene
    selection: Selection
    y: dict
    history: list[dict]
    result: str  # optimistix's result name: "successful", "max_steps_reached", "nonlinear_divergence", …
    message: str
    converged: bool
    steps: int
    nuisance: dict[str, float]
    times: dict[str, float]
    solver: str

    def table(self) -> list[tuple[str, object, object]]:
        """(parameter, start, fitted) rows in deck units."""
        return self.selection.table(self.y["scene"])

    @property
    def loss(self) -> float:
        return self.history[-1]["best_loss"] if self.history else math.nan


def _result_name(result) -> str:
    for name in ("successful", "max_steps_reached", "nonlinear_divergence", "nonlinear_max_steps_reached",
                 "singular", "breakdown", "stagnation"):
        if hasattr(optx.RESULTS, name) and result == getattr(optx.RESULTS, name):
            return name
    return "failed"


def _message(result) -> str:
    try:
        return str(optx.RESULTS[result]) or "successful"
    except Exception:  # noqa: BLE001 — a message is a nicety; the name is what matters
        return _result_name(result)


def fit(
    scene: rtjax.Scene,
    target,
    free: str | Sequence[str] = "centers",
    *,
    spheres: Sequence[int] | None = None,
    solver: str = "lm",
    max_steps: int = 30,
    levels: int | Sequence[int] | None = None,
    edges: float = 1.0,
    depth: int | None = None,
    loss: str = "l2",
    loss_scale: float = 10.0,
    mask=None,
    nuisance: Sequence[str] = (),
    rtol: float = 1e-6,
    atol: float = 1e-6,
    jac: str | None = None,
    assignment_order: bool = False,
    callback: Callable[[dict], None] | None = None,
) -> FitResult:
    """Fit the free parameters of `scene` so that its render matches `target`.

    target: an (H, W, 3) array in 0..255 or an image path (Sun raster in either byte
      order, PNG, JPEG, EXR, TIFF, …). A different size is followed when its aspect
      ratio matches the scene's view, else `FitError`.
    free: families ('centers', 'radii', 'colors', 'ks', 'beta', 'kt', 'n', 'ke', 'light',
      'light_colors', 'background', 'eye', 'refp', 'vang', 'textures'); `spheres`
      restricts per-sphere families to some spheres.
    solver: 'lm' (Levenberg–Marquardt, default), 'gn' (Gauss–Newton), 'dogleg' (least
      squares) or 'bfgs' (minimisation of the same loss).
    max_steps: iterations in all, across the coarse-to-fine `levels` (an int: that many
      levels, halving the width; a list of widths; 1: full size only).
    edges: edge width of the silhouette-aware render, in pixels of each level.
    loss: 'l2', 'huber' or 'cauchy' (robust, with `loss_scale` in levels).
    nuisance: ('gain', 'gamma') fitted jointly: model = 255·(gain·I/255)^γ.
    jac: 'fwd' or 'bwd' Jacobians for the least-squares solvers (default: forward mode,
      reverse when the free parameters outnumber a few hundred).
    callback: called after every iteration with that iteration's history row.
    """
    if solver not in SOLVERS:
        raise FitError(f"unknown solver {solver!r}; choose from {', '.join(SOLVERS)}")
    if loss not in LOSSES:
        raise FitError(f"unknown loss {loss!r}; choose from {', '.join(LOSSES)}")
    if int(max_steps) < 1:
        raise FitError(f"max_steps must be ≥ 1, not {max_steps}")
    t_start = time.perf_counter()
    target = load_target(target, assignment_order=assignment_order)
    full = match_size(scene, target)
    weight_full = prepare_mask(mask, *target.shape[:2])
    selection = Selection(full, free, spheres)
    dtype = jnp.result_type(full.params.centers)
    y = {"scene": selection.y0()}
    if nuisance:
        y["nuisance"] = nuisance_y0(nuisance, dtype)
    if jac is None:
        jac = "bwd" if selection.size() > 400 else "fwd"
    options = {} if solver == "bfgs" else {"jac": jac}

    widths = schedule_widths(full.structure.width, levels)
    history: list[dict] = []
    best_y, best_loss = y, math.inf
    steps = 0
    result = optx.RESULTS.successful
    times = {"compile_and_run": 0.0}
    for level, width in enumerate(widths):
        final = level == len(widths) - 1
        lvl_scene = full if width == full.structure.width else full.resized(width)
        h = lvl_scene.structure.height
        obj = Objective(
            selection,
            lvl_scene,
            jnp.asarray(downsample(target, h, width) if (h, width) != target.shape[:2] else target, dtype),
            jnp.asarray(downsample(weight_full, h, width) if (h, width) != target.shape[:2] else weight_full, dtype),
            edges,
            depth,
            loss,
            loss_scale,
            tuple(nuisance),
        )
        # coarse levels stop early (their optimum is only close to the full-size one)
        tol = (rtol, atol) if final else (max(rtol, 1e-3), max(atol, 1e-3))
        budget = max_steps - steps if final else max(1, min(max_steps - steps - 1, (max_steps * 2) // 3 - steps))
        if budget <= 0:
            continue
        y_level, level_result, n, level_best = _run_level(obj, SOLVERS[solver](*tol), y, options, budget, solver, history, steps, width, callback, t_start)
        steps += n
        # the best point of this level seeds the next (and is the answer after the last)
        y = level_best[0]
        if final:
            best_y, best_loss = level_best
            result = level_result
    fitted = selection.scene_at(best_y["scene"])
    name = _result_name(result)
    converged = name == "successful"
    times["total"] = time.perf_counter() - t_start
    return FitResult(
        scene=rtjax.Scene(scene.structure.replace(width=fitted.structure.width, height=fitted.structure.height), fitted.params),
        start=full,
        selection=selection,
        y=best_y,
        history=history,
        result=name,
        message=_message(result) if not converged else "converged",
        converged=converged,
        steps=steps,
        nuisance={k: float(jnp.exp(v)) for k, v in best_y.get("nuisance", {}).items()},
        times=times,
        solver=solver,
    )


def _run_level(obj: Objective, solver, y, options, budget: int, solver_name: str, history, step0: int, width: int, callback, t_start):
    """Iterate one solver on one pyramid level; returns (y, result, iterations, (best y, best loss))."""
    tags = frozenset()
    minimise = solver_name == "bfgs"

    if minimise:
        def fn(y, args):
            r = obj.residuals(y)
            return 0.5 * jnp.sum(r * r), None
    else:
        def fn(y, args):
            return obj.residuals(y), None

    f_struct, aux_struct = jax.eval_shape(lambda: fn(y, None))

    @eqx.filter_jit
    def init(y):
        return solver.init(fn, y, None, options, f_struct, aux_struct, tags)

    @eqx.filter_jit
    def step(y, state):
        y, state, _ = solver.step(fn, y, None, options, state, tags)
        done, result = solver.terminate(fn, y, None, options, state, tags)
        return y, state, done, result, _loss(y)

    @eqx.filter_jit
    def _loss(y):
        r = obj.residuals(y)
        return 0.5 * jnp.mean(r * r)

    state = init(y)
    best = (y, float(_loss(y)))
    result = optx.RESULTS.successful
    n = 0
    for n in range(1, budget + 1):
        t0 = time.perf_counter()
        y_new, state_new, done, result, loss = step(y, state)
        loss = float(loss)
        finite = math.isfinite(loss)
        if finite:
            y, state = y_new, state_new
            if loss < best[1]:
                best = (y, loss)
        else:  # a diverging solver: stop, keep the best so far
            result = optx.RESULTS.nonlinear_divergence
        row = {
            "step": step0 + n,
            "width": width,
            "loss": loss,
            "best_loss": best[1],
            "rmse_levels": math.sqrt(2 * best[1]) * 255 if math.isfinite(best[1]) else math.nan,
            "seconds": time.perf_counter() - t0,
            "elapsed": time.perf_counter() - t_start,
        }
        history.append(row)
        if callback is not None:
            callback(row)
        if not finite:
            break
        if bool(done):
            break
    else:
        result = optx.RESULTS.max_steps_reached
    if bool(done) is False and n == budget:
        result = optx.RESULTS.max_steps_reached
    return y, result, n, best
