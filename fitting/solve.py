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
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import rtjax

from .errors import FitError
from .objective import (DENOISE, EXACT_SCALE, LOSSES, NARROW_BELOW, Objective, load_target, make_levels, match_size, nuisance_names,
                        nuisance_values, nuisance_y0, prepare_mask, schedule_widths)
from .select import Selection

#: Levenberg–Marquardt's first trust-region step size on every level (its damping
#: λ = 1/step): 10, where optimistix starts at 1. Residuals are in 1/255 units per
#: sample, so λ = 1 damps the first steps into slow gradient descent, and the region
#: grows only 3.5× per very good step. Measured on the sample deck, six starts each:
#: centres from ±3 units 6 of 6 within 0.01 (5 of 6 at 1: one start still on the
#: coarsest level when its 15 steps ran out, 0.10 off), ±5 4 of 6 (the same). (Carrying
#: a level's last step size on to the next was worse: 5 of 6 at ±3, one 0.019 off.)
LM_STEP0 = 10.0
#: ...and its region grows (3.5×) after a step whose actual reduction of the loss is
#: above this share of the predicted one: Moré's 0.75, where optimistix asks 0.99. Near
#: the truth the narrow Cauchy scale keeps that ratio a little below 1, so the region
#: did not grow and colours crept (~0.5 % of the loss per step). Measured on the sample
#: deck, colours and ke from ±0.25 / 0.45: largest error 0.0002 against 0.0021; the
#: centres' six ±3 starts ended exactly as before (their ratios are never in between).
LM_GROW_ABOVE = 0.75


class _TrustRegion(optx.ClassicalTrustRegion):
    """optimistix's classical trust region, starting at `LM_STEP0` on every level."""

    def init(self, y, f_info_struct):
        state = super().init(y, f_info_struct)
        return eqx.tree_at(lambda s: s.step_size, state, jnp.asarray(LM_STEP0, state.step_size.dtype))


def _levenberg_marquardt(rtol: float, atol: float) -> optx.LevenbergMarquardt:
    lm = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return eqx.tree_at(lambda s: s.search, lm, _TrustRegion(high_cutoff=LM_GROW_ABOVE))


SOLVERS = {
    "lm": _levenberg_marquardt,
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


def _code(item) -> int:
    """optimistix's result item as its integer code (what a compiled step returns)."""
    return int(item._value) if hasattr(item, "_value") else int(item)


def _item(code: int):
    """optimistix's result item for its integer code."""
    for item in optx.RESULTS._name_to_item.values():
        if _code(item) == int(code):
            return item
    return optx.RESULTS.nonlinear_divergence


def level_budget(pyramid, level: int, max_steps: int, steps: int, loss_scale: float) -> tuple[int, bool, float]:
    """Iterations for pyramid level `level` after `steps` of `max_steps`; whether it is a
    full-size level (else a coarse one, which stops early once it stalls); and a loss
    at which it hands over to the next (0: none).

    The coarsest level does most of the travelling: half of the steps; later levels
    share what is left equally (one that stalls early hands its remainder on). The
    full-size level takes all that is left; one followed by a narrow-scale refinement
    (`objective.EXACT_SCALE`) hands over once its RMS residual is below
    `objective.NARROW_BELOW` of the loss scale, or when it converges: the refinement
    takes what is left; it is skipped where the level before ended as close (its own
    steps from the start are what the narrow scale needs near the truth: measured on
    the sample deck, one start of six ran out of steps 0.15 units off where the two
    shared them)."""
    main = sum(float(s.scale) == 1.0 for s in pyramid)
    if level >= main - 1:
        refined = level + 1 < len(pyramid)
        return max_steps - steps, True, 0.5 * (NARROW_BELOW * loss_scale / 255) ** 2 if refined else 0.0
    share = 2 if level == 0 else main - level
    return max(1, (max_steps - steps) // share), False, 0.0


def run_levels(pyramid, widths, max_steps: int, loss_scale: float, best_losses: Callable[[], np.ndarray],
               level: Callable[..., int]) -> tuple[int, bool]:
    """The coarse-to-fine schedule `fit` and `fit_multistart` share: each level in turn
    with its `level_budget`, skipped where every start's best loss so far
    (`best_losses()`) is already at its hand-over loss. `level(samples, width, budget,
    full_size, until, steps)` runs one level and returns its iterations. Returns the
    iterations in all and whether they ran out before the last level."""
    steps = 0
    for index, (width, samples) in enumerate(zip(widths, pyramid)):
        budget, full_size, until = level_budget(pyramid, index, max_steps, steps, loss_scale)
        if budget < 1:  # no steps left for this level (the refinement, or any level after max_steps=1)
            return steps, True
        if np.all(best_losses() <= until):  # the level before came as close: straight to the refinement
            continue
        steps += level(samples, width, budget, full_size, until, steps)
    return steps, False


class LevelBook:
    """One level's bookkeeping for K starts at once (NumPy arrays; `fit` has one): the
    best loss so far, iterations without a 1 % decrease, the result, and the rules that
    stop a start. A coarse level stops a start once its best loss improves by less than
    1 % over two iterations (its optimum is only near the full-size one); a full-size
    one after four such iterations (steps are rejected or negligible: the loss has
    levelled off, a success). Any start stops once its best loss is at most `until`
    (a refinement takes over: a success), or when the solver says it is done, or when
    its loss is not finite (divergence; its best point is kept)."""

    def __init__(self, starts: int, coarse: bool, until: float, active=None):
        self.coarse, self.until = coarse, until
        self.best = np.full(starts, math.inf)
        self.stalled = np.zeros(starts, int)
        self.results = np.full(starts, _code(optx.RESULTS.successful), np.int32)
        self.stopped = np.zeros(starts, bool) if active is None else ~np.asarray(active, bool)
        self.levelled = np.zeros(starts, bool)

    def update(self, loss, done, result) -> tuple[np.ndarray, np.ndarray]:
        """Take one iteration's losses, solver `done` flags and result codes of the
        starts that were active; returns which were active and which improved."""
        loss = np.asarray(loss, np.float64)
        active = ~self.stopped
        ok = active & np.isfinite(loss)
        diverged = active & ~ok
        self.results[diverged] = _code(optx.RESULTS.nonlinear_divergence)
        self.stalled = np.where(ok, np.where(loss > self.best * 0.99, self.stalled + 1, 0), self.stalled)
        better = ok & (loss < self.best)
        self.best = np.where(better, loss, self.best)
        finished = ok & np.asarray(done, bool)
        self.results[finished] = np.asarray(result, np.int32)[finished]
        close = ok & ~finished & (self.best <= self.until)
        self.results[close] = _code(optx.RESULTS.successful)
        finished |= close
        if self.coarse:
            stall = ok & ~finished & (self.stalled >= 2)
        else:
            stall = ok & ~finished & (self.stalled >= 4)
            self.levelled |= stall
            self.results[stall] = _code(optx.RESULTS.successful)
            finished |= stall
        self.stopped |= diverged | finished | stall
        return active, better

    def finish(self) -> None:
        """After the level's budget: a full-size level's starts still going ran out of steps."""
        if not self.coarse:
            self.results[~self.stopped] = _code(optx.RESULTS.max_steps_reached)


def prepare_fit(scene, target, free, spheres, depth, levels, edges, polish, loss, loss_scale, mask, nuisance, jac,
                assignment_order, exact_polish=True):
    """The set-up `fit` and `fit_multistart` share: the target at the scene's size, the
    free parameters and their start, the Jacobian mode, the pyramid and the objective."""
    target = load_target(target, assignment_order=assignment_order)
    full = match_size(scene, target)
    selection = Selection(full, free, spheres)
    y = {"scene": selection.y0()}
    dtype = jnp.result_type(full.params.centers)
    nuisance = nuisance_names(nuisance or ())
    if nuisance:
        y["nuisance"] = nuisance_y0(nuisance, jax.tree_util.tree_leaves(y["scene"])[0].dtype)
    if jac is None:
        jac = "bwd" if selection.size() > 200 else "fwd"
    blurred = "blur" in nuisance
    widths = schedule_widths(full.structure.width, levels, blurred=blurred)
    given = [1.0] if edges is None else [float(e) for e in np.ravel(edges)]
    if not given or min(given) <= 0:
        raise FitError(f"edge widths must be > 0, not {edges}")
    # one value: every level; several: one per level in order, the last repeating
    per_level = [given[min(i, len(given) - 1)] for i in range(len(widths))]
    exact, whole = [False] * len(widths), [False] * len(widths)
    if blurred:  # a photo: the full-size level is the whole image through `objective.camera`
        whole[-1] = True
    elif polish and exact_polish and len(widths) > 1:
        # matched at pixel centres, the full-size level needs no box-filtered one before it
        # (measured: the one it replaces reduced the loss by ~2 % in its 4-5 steps)
        per_level[-1], exact[-1] = float(polish), True
    elif polish:
        widths, per_level, exact = widths + [widths[-1]], per_level + [float(polish)], exact + [bool(exact_polish)]
    pyramid = make_levels(target, prepare_mask(mask, *target.shape[:2]), widths, per_level, dtype, exact=exact,
                          denoise=DENOISE if blurred else 0.0, whole=whole)
    if pyramid[-1].exact:  # the same samples again, at a narrow robust scale
        pyramid.append(pyramid[-1]._replace(scale=jnp.asarray(EXACT_SCALE, dtype)))
        widths = widths + [widths[-1]]
    objective = Objective(selection, depth, loss, loss_scale)
    return full, selection, y, jac, widths, pyramid, objective


def fit(
    scene: rtjax.Scene,
    target,
    free: str | Sequence[str] = "centers",
    *,
    spheres: Sequence[int] | None = None,
    solver: str = "lm",
    max_steps: int = 30,
    levels: int | Sequence[int] | None = None,
    edges: float | Sequence[float] | None = None,
    polish: float | None = 1.0,
    exact_polish: bool = True,
    depth: int | None = None,
    loss: str = "cauchy",
    loss_scale: float = 10.0,
    mask=None,
    nuisance: Sequence[str] = (),
    rtol: float = 1e-5,
    atol: float = 1e-7,
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
    max_steps: iterations in all, across the coarse-to-fine `levels` (default: an eighth,
      a quarter and the full width, see `schedule_widths`; an int: that many levels,
      halving the width down to 48 pixels; a list of widths; 1: full size only).
      Every level renders the same number of samples (the coarsest level's pixel
      count; finer levels take the pixels near the target's edges and a spread of the
      rest), so one compiled step serves all levels.
    edges: edge width of the silhouette-aware render in pixels of each level (default 1):
      one value, or one per level (the last repeating).
    polish: the edge width (pixels) of the full-size fit, default 1; None: no special
      full-size level. With `exact_polish` (default) the full-size level is matched at
      pixel centres, as `rtjax render` makes targets (`Objective.model`): a pixel near
      an edge counts exactly when its centre lies on the target's side of it and is
      penalised over `polish` pixels beyond, so the fit is unbiased at the truth; it
      takes all of the target's edge pixels (`make_levels`); within 3 levels RMS of the
      target it hands over to a refinement on the same samples with a tenth of the
      robust scale (`objective.EXACT_SCALE`, `level_budget`). Without, a last full-size
      level box-filters edges `polish` wide (then use a narrow one such as 0.02) — for
      targets that are themselves antialiased. Measured on the sample deck, ±3 units,
      three starts: largest centre error 0.0076, 0.062, 0.0056 units (exact) against
      0.047, 0.125, 0.055 (0.02-pixel box polish); see README "How well it works".
    loss: 'cauchy' (default, robust), 'huber', or 'l2'; `loss_scale` in levels (levels
      coarser than the image use `objective.COARSE_SCALE` times it unless a blur is
      fitted).
    nuisance: fitted jointly with the scene for photo-like targets: 'gain' and 'gamma'
      (response 255·(gain·I/255)^γ), 'blur' (a Gaussian σ in pixels), 'chroma' (a
      further blur of the chroma, as JPEG's 4:2:0 subsampling makes) and 'order' (the
      share of the blur after the response); 'camera': all five (`objective.camera`).
      With a blur the coarse levels widen the edges' box filter, and the full-size
      level is the whole image through `camera` (`polish` is not used).
    jac: 'fwd' (default: the Jacobian by forward mode, one batched pass per step) or
      'bwd' (reverse mode, for many free parameters such as texels).
    callback: called after every iteration with that iteration's history row.
    """
    if solver not in SOLVERS:
        raise FitError(f"unknown solver {solver!r}; choose from {', '.join(SOLVERS)}")
    if loss not in LOSSES:
        raise FitError(f"unknown loss {loss!r}; choose from {', '.join(LOSSES)}")
    if int(max_steps) < 1:
        raise FitError(f"max_steps must be ≥ 1, not {max_steps}")
    t_start = time.perf_counter()
    full, selection, y, jac, widths, pyramid, objective = prepare_fit(
        scene, target, free, spheres, depth, levels, edges, polish, loss, loss_scale, mask, nuisance, jac, assignment_order,
        exact_polish)
    run = _Stepper(objective, SOLVERS[solver](rtol, atol), solver, jac)

    history: list[dict] = []
    best_loss, result = math.inf, optx.RESULTS.successful

    def level(samples, width, budget, full_size, until, steps):
        nonlocal y, best_loss, result
        (y, best_loss), result, n = run.level(y, samples, budget, not full_size, history, steps, width, callback, t_start,
                                              until)
        return n

    steps, out_of_steps = run_levels(pyramid, widths, max_steps, loss_scale, lambda: np.array([best_loss]), level)
    if out_of_steps:
        result = optx.RESULTS.max_steps_reached
    fitted = selection.scene_at(y["scene"])
    name = _result_name(result)
    return FitResult(
        scene=rtjax.Scene(scene.structure.replace(width=full.structure.width, height=full.structure.height), fitted.params),
        start=full,
        selection=selection,
        y=y,
        history=history,
        result=name,
        message=("converged: the loss levelled off" if run.levelled else "converged") if name == "successful" else _message(result),
        converged=name == "successful",
        steps=steps,
        nuisance={k: float(v) for k, v in nuisance_values(y.get("nuisance", {})).items()},
        times={"total": time.perf_counter() - t_start, "first_step": history[0]["seconds"] if history else math.nan},
        solver=solver,
    )


def with_dense_jacobian(fn):
    """fn(y, args) with a jvp rule in y that builds the whole Jacobian by `jax.jacfwd`
    (one batched forward pass) and applies it: J·ẏ. optimistix's Gauss–Newton family
    linearises fn and then evaluates the linear map once per free parameter; with this
    rule that is a matrix product, and the render's forward-mode pass runs once per step
    (measured 2.3× faster to run and 2× faster to compile than `jax.linearize` on a
    render). Reverse mode still works: the rule is linear in ẏ, so JAX transposes it."""

    def dense_fn(y, args):
        # the args' non-array parts (a level's static flags) stay Python values
        arrays, static = eqx.partition(args, eqx.is_array)

        @jax.custom_jvp
        def dense(y, arrays):
            return fn(y, eqx.combine(arrays, static))

        @dense.defjvp
        def dense_jvp(primals, tangents):
            (y, arrays), (ydot, _) = primals, tangents
            flat, unravel = jax.flatten_util.ravel_pytree(y)
            jac, value = jax.jacfwd(lambda v: (fn(unravel(v), eqx.combine(arrays, static)),) * 2, has_aux=True)(flat)
            step, _ = jax.flatten_util.ravel_pytree(ydot)
            return value, jnp.tensordot(jac, step, axes=1)

        return dense(y, arrays)

    return dense_fn


class _Stepper:
    """The solver's init/step/terminate, jit-compiled once per fit (the pyramid level's
    samples are arguments), stepped by hand to report and keep the best point."""

    def __init__(self, objective: Objective, solver, name: str, jac: str):
        residuals = with_dense_jacobian(objective.residuals) if jac == "fwd" else objective.residuals
        self.options = {"jac": "bwd"} if jac == "bwd" and name != "bfgs" else {}
        self.solver = solver
        if name == "bfgs":
            def fn(y, args):
                r = residuals(y, args)
                return 0.5 * jnp.sum(r * r), None
        else:
            def fn(y, args):
                return residuals(y, args), None
        self.fn = fn
        self.levelled = False  # the last level stopped because its loss levelled off
        self.init = eqx.filter_jit(self._init)
        self.step = eqx.filter_jit(self._step)

    def _init(self, y, args):
        f_struct, aux_struct = jax.eval_shape(lambda: self.fn(y, args))
        return self.solver.init(self.fn, y, args, self.options, f_struct, aux_struct, frozenset())

    def _step(self, y, state, args):
        y, state, _ = self.solver.step(self.fn, y, args, self.options, state, frozenset())
        done, result = self.solver.terminate(self.fn, y, args, self.options, state, frozenset())
        # the returned y is the last accepted point, whose function value the state
        # holds (no second render): Gauss–Newton family residuals, or BFGS's ½Σr²
        info = state.f_info
        loss = 0.5 * jnp.mean(info.residual**2) if hasattr(info, "residual") else info.f / args.target.size
        return y, state, done, result, loss

    def level(self, y, samples, budget: int, coarse: bool, history, step0: int, width: int, callback, t_start,
              until: float = 0.0):
        """Up to `budget` iterations on one level, stopped by `LevelBook`'s rules;
        returns ((best y, best loss), result, n)."""
        state = self.init(y, samples)
        # the first step evaluates the start and returns it with its loss (optimistix
        # accepts a first step unconditionally), so no separate evaluation is needed
        book = LevelBook(1, coarse, until)
        best_y, n = y, 0
        for n in range(1, budget + 1):
            t0 = time.perf_counter()
            y_new, state_new, done, result, loss = self.step(y, state, samples)
            loss = float(loss)
            _, better = book.update([loss], [bool(done)], [_code(result)])
            if math.isfinite(loss):
                y, state = y_new, state_new
            if better[0]:
                best_y = y
            row = {
                "step": step0 + n,
                "width": width,
                "loss": loss,
                "best_loss": float(book.best[0]),
                "rmse_levels": math.sqrt(2 * book.best[0]) * 255,
                "seconds": time.perf_counter() - t0,
                "elapsed": time.perf_counter() - t_start,
            }
            history.append(row)
            if callback is not None:
                callback(row)
            if book.stopped[0]:
                break
        book.finish()
        self.levelled = bool(book.levelled[0])
        return (best_y, float(book.best[0])), _item(book.results[0]), n
