"""The fitting driver: `fit_starts` steps one or several starts through the coarse-to-fine
levels; `fit` is its one-start case.

Every level starts from the previous level's best parameters; iterations count across
levels. The solver is stepped by hand (`solvers.Stepper`), one compiled step per
iteration, so every iteration is reported (step, loss, time), each start's best
parameters so far are kept whatever happens, and a failure is a result name and
message, never an exception.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import jax
import numpy as np

import rtjax

from .errors import FitError
from .frames import build_frames
from .objective import NARROW_BELOW, nuisance_values
from .options import FitOptions
from .problem import Problem
from .select import Selection
from .solvers import CODES, Ahead, Step, Stepper, result_message, result_name
from .texels import Smoothed, TexelCoverage, coverage
from .verdict import Verdict, judge


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
    texels: TexelCoverage | None = None  # with textures free: which texels the views determine
    photo: dict[str, object] = dataclasses.field(default_factory=dict)  # a photo fit's appearance and camera (`fitting.photo`)
    verdict: Verdict | None = None  # a photo or camera-model fit's verdict (`fitting.verdict`)

    @property
    def ok(self) -> bool:
        """Converged, and (where judged) a supported verdict: what exits 0."""
        return self.converged and (self.verdict is None or self.verdict.ok)

    def table(self) -> list[tuple[str, object, object]]:
        """(parameter, start, fitted) rows in deck units."""
        return self.selection.table(self.y["scene"])

    @property
    def loss(self) -> float:
        return self.history[-1]["best_loss"] if self.history else math.nan


@dataclasses.dataclass
class MultiStartResult:
    """The kept start's fit (`best`, a `FitResult`) and what every start did."""

    best: FitResult
    index: int  # which start was kept (0: the start as given)
    starts: int
    losses: list[float]  # per start: its best loss on the last level
    results: list[str]  # per start: optimistix's result name
    start_scenes: list[rtjax.Scene]  # per start: where it began (full size)
    fitted: list[rtjax.Scene]  # per start: where it ended
    devices: int
    times: dict[str, float]

    @property
    def converged(self) -> int:
        """How many starts converged."""
        return sum(r == "successful" for r in self.results)

    @property
    def scene(self) -> rtjax.Scene:
        return self.best.scene

    @property
    def loss(self) -> float:
        return self.best.loss

    def table(self):
        return self.best.table()


def level_budget(pyramid, level: int, max_steps: int, steps: int, loss_scale: float) -> tuple[int, bool, float]:
    """Iterations for pyramid level `level` after `steps` of `max_steps`; whether it is a
    full-size level (else a coarse one, which stops early once it stalls); and a loss
    at which it hands over to the next (0: none).

    The coarsest level does most of the travelling: half of the steps; later levels
    share what is left equally (one that stalls early hands its remainder on). The
    full-size level takes all that is left; one followed by a narrow-scale refinement
    (`objective.EXACT_SCALE`) hands over once its RMS residual is below
    `objective.NARROW_BELOW` of the loss scale, or when it converges: the refinement
    takes what is left; it is skipped where the level before ended as close (near the
    truth the narrow scale needs its own steps from the start)."""
    main = sum(float(s.scale) == 1.0 for s in pyramid)
    if level >= main - 1:
        refined = level + 1 < len(pyramid)
        return max_steps - steps, True, 0.5 * (NARROW_BELOW * loss_scale / 255) ** 2 if refined else 0.0
    share = 2 if level == 0 else main - level
    return max(1, (max_steps - steps) // share), False, 0.0


#: A step gains when it lowers the best loss by this share (`LevelBook`).
GAIN = 0.01
#: Steps in a row without a gain that end a level (`LevelBook`).
PATIENCE = 2
#: Rejected steps in a row whose model promised a gain that end a level (`LevelBook`):
#: each shrinks the trust region (by 4 in optimistix's classical one).
REJECTIONS = 4


class LevelBook:
    """One level's bookkeeping for K starts at once (NumPy arrays): the best loss so far,
    steps without a gain and rejected steps that promised one, the result codes
    (`solvers.CODES`), and the rules that stop a start.

    A level stops a start after `PATIENCE` steps in a row without a gain (of `GAIN` of
    its best loss: accepted steps that gained less, and rejected steps whose model
    promised less), or after `REJECTIONS` rejected steps in a row whose model promised a
    gain: on a coarse level its optimum is only near the full-size one; on the full-size
    level the loss has levelled off, a success. A rejected step that promised a gain is
    the solver shortening a step its model overrated, not the loss levelling off: a
    photo's first steps on a level are often rejected two or three times before the
    shorter one gains. Any start stops once its best loss is at most `until` (a
    refinement takes over: a success), or when the solver says it is done, or when its
    loss is not finite (divergence; its best point is kept). Starts not `active`
    (padding) never step."""

    def __init__(self, starts: int, coarse: bool, until: float, active=None):
        self.coarse, self.until = coarse, until
        self.best = np.full(starts, math.inf)
        self.stalled = np.zeros(starts, int)
        self.rejected = np.zeros(starts, int)
        self.results = np.full(starts, CODES["successful"], np.int32)
        self.stopped = np.zeros(starts, bool) if active is None else ~np.asarray(active, bool)
        self.levelled = np.zeros(starts, bool)

    def update(self, step: Step) -> tuple[np.ndarray, np.ndarray]:
        """Take one iteration's `step` of K starts (its losses, solver `done` flags, result
        codes, whether each step was accepted and the share of the loss it promised to
        remove) for the starts that were active; returns which were active and which
        improved."""
        loss = np.asarray(step.loss, np.float64)
        accepted = np.asarray(step.accepted, bool)
        promising = ~accepted & (np.asarray(step.promised, np.float64) >= GAIN)
        active = ~self.stopped
        ok = active & np.isfinite(loss)
        diverged = active & ~ok
        self.results[diverged] = CODES["nonlinear_divergence"]
        gained = accepted & (loss <= self.best * (1 - GAIN))
        self.stalled = np.where(ok & ~promising, np.where(gained, 0, self.stalled + 1), self.stalled)
        self.rejected = np.where(ok, np.where(promising, self.rejected + 1, 0), self.rejected)
        better = ok & (loss < self.best)
        self.best = np.where(better, loss, self.best)
        finished = ok & np.asarray(step.done, bool)
        self.results[finished] = np.asarray(step.code, np.int32)[finished]
        close = ok & ~finished & (self.best <= self.until)
        self.results[close] = CODES["successful"]
        finished |= close
        stall = ok & ~finished & ((self.stalled >= PATIENCE) | (self.rejected >= REJECTIONS))
        if not self.coarse:
            self.levelled |= stall
            self.results[stall] = CODES["successful"]
            finished |= stall
        self.stopped |= diverged | finished | stall
        return active, better

    def finish(self) -> None:
        """After the level's budget: a full-size level's starts still going ran out of steps."""
        if not self.coarse:
            self.results[~self.stopped] = CODES["max_steps_reached"]


class Steps(Protocol):
    """How `fit_starts` steps its starts: `Single` (one start, the compiled step as it is)
    or `multistart.Parallel` (a leading axis of starts in one compiled call)."""

    size: int  # starts stepped, padding included
    devices: int
    ahead: Ahead | None  # compiling the whole-image level's step (`solvers.compile_ahead`)

    def init(self, ys, samples):
        """The solver states of starts `ys` on a level."""

    def step(self, ys, states, samples, active: np.ndarray) -> Step:
        """One step of the `active` starts: a `Step` whose fields after `state` are NumPy
        arrays of `size` (losses and promised gains float64)."""

    def keep(self, better: np.ndarray, new, old):
        """Starts `new` where `better`, else `old`."""

    def unstack(self, ys, count: int) -> list[dict]:
        """The first `count` starts of `ys`, each a y on this process."""

    def evaluate(self, points: Sequence[dict], samples) -> list[tuple[float, object]]:
        """Each of `points` (ys of one start) on the level `samples`: (loss, solver
        state) after a first step from it, which evaluates the point (a least-squares
        solver's state then holds its residuals and Jacobian there), with the compiled
        programs of the fit's own steps."""


class Single:
    """`Steps` of one start: `Stepper.step` unbatched, its outputs given a leading axis of
    1 on the host."""

    size = devices = 1

    def __init__(self, stepper: Stepper, ahead: Ahead | None = None):
        self.stepper = stepper
        self.ahead = ahead
        self.last: tuple[Step, object] | None = None  # the last step (on the host) and its level's samples

    def init(self, y, samples):
        return self.stepper.init(y, samples)

    def step(self, y, state, samples, active):
        step = self.stepper.step(y, state, samples).on_host()
        self.last = (step, samples)
        return step

    def keep(self, better, new, old):
        return new if better[0] else old

    def unstack(self, y, count):
        return [y]

    def evaluate(self, points, samples):
        out = []
        for y in points:
            step = self.stepper.step(y, self.init(y, samples), samples)
            out.append((float(step.loss), step.state))
        return out

    def end(self, y, samples) -> tuple[float, object] | None:
        """(loss, solver state) of the last step if it was on the level `samples` and
        ended at `y` (a least-squares solver's state holds its accepted point's
        residuals and Jacobian), else None."""
        if self.last is None or self.last[1] is not samples:
            return None
        last = self.last[0]
        a, b = jax.tree_util.tree_leaves(last.y), jax.tree_util.tree_leaves(y)
        same = len(a) == len(b) and all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(a, b))
        return (float(last.loss[0]), last.state) if same else None


def fit_starts(problem: Problem, stepper: Steps, ys, begun: Sequence[rtjax.Scene], options: FitOptions,
               callback: Callable[[dict], None] | None = None, *, started: float, several: bool = False
               ) -> MultiStartResult:
    """Fit `problem` from the starts `ys` (as `stepper` holds them; `begun`: their scenes,
    one per real start), level by level (`level_budget`, `LevelBook`); the start with the
    lowest final loss is kept.

    **Arguments:**

    - `options`: its `max_steps`, `loss_scale` and `solver` are used here.
    - `callback`: called after every iteration with the history row of the start with the
      lowest loss so far; with `several`, the row also says which start that is (`start`)
      and how many are still going (`active`).
    - `started`: `time.perf_counter()` when the fit began (its set-up included).

    The background compile of the whole-image level's step (`stepper.ahead`) is joined
    before that level begins, and in any case before this returns.

    **Returns:** a `MultiStartResult` (for one start, its `best` is the fit).
    """
    count = len(begun)
    real = np.arange(stepper.size) < count
    histories: list[list[dict]] = [[] for _ in range(count)]
    book = LevelBook(stepper.size, False, 0.0, active=real)  # the last level's (none yet)
    steps, out_of_steps = 0, False
    for level, (width, samples) in enumerate(zip(problem.widths, problem.pyramid)):
        budget, full_size, until = level_budget(problem.pyramid, level, options.max_steps, steps, options.loss_scale)
        if budget < 1:  # no steps left for this level (the refinement, or any level after max_steps=1)
            out_of_steps = True
            break
        if np.all(book.best[real] <= until):  # the level before came as close: straight to the refinement
            continue
        # the first step evaluates the start and returns it with its loss (optimistix
        # accepts a first step unconditionally), so no separate evaluation is needed
        if samples.whole and stepper.ahead is not None:
            stepper.ahead.wait()  # its step compiled once, not again beside it; its error raised here
        states = stepper.init(ys, samples)
        best_ys = ys
        book = LevelBook(stepper.size, not full_size, until, active=real)
        n = 0
        for n in range(1, budget + 1):
            t0 = time.perf_counter()
            step = stepper.step(ys, states, samples, ~book.stopped)
            ys, states, losses = step.y, step.state, step.loss
            active, better = book.update(step)
            seconds = time.perf_counter() - t0
            if better.any():
                best_ys = stepper.keep(better, ys, best_ys)
            elapsed = time.perf_counter() - started

            def row(k):
                best = float(book.best[k])
                return {"step": steps + n, "width": width, "loss": float(losses[k]), "best_loss": best,
                        "rmse_levels": math.sqrt(2 * best) * 255, "seconds": seconds, "elapsed": elapsed}

            for k in np.flatnonzero(active[:count]):
                histories[k].append(row(k))
            if callback is not None:
                lead = int(np.argmin(np.where(real, book.best, math.inf)))
                # a lead that has stopped took no step: its best loss, not the stopped step's inf
                shown = histories[lead][-1] if active[lead] else dict(row(lead), loss=float(book.best[lead]))
                if several:
                    shown = dict(shown, start=lead, active=int((~book.stopped[:count]).sum()))
                callback(shown)
            if book.stopped.all():
                break
        book.finish()
        ys = best_ys
        steps += n
    if stepper.ahead is not None:
        stepper.ahead.join()  # where the whole-image level was skipped: not left compiling

    results = book.results
    if out_of_steps:
        results[real & (results == CODES["successful"])] = CODES["max_steps_reached"]
    names = [result_name(int(r)) for r in results[:count]]
    losses = [float(x) for x in book.best[:count]]
    index = int(np.argmin(np.where(np.isfinite(losses), losses, math.inf)))
    ends = stepper.unstack(ys, count)
    selection, structure = problem.selection, problem.scene.structure
    fitted = [rtjax.Scene(structure, selection.params(y["scene"])) for y in ends]
    name, y = names[index], ends[index]
    total = time.perf_counter() - started
    history = histories[index]
    best = FitResult(
        scene=fitted[index],
        start=begun[index],
        selection=selection,
        y=y,
        history=history,
        result=name,
        message=(("converged: the loss levelled off" if book.levelled[index] else "converged") if name == "successful"
                 else result_message(int(results[index]))),
        converged=name == "successful",
        steps=steps,
        nuisance={k: float(v) for k, v in nuisance_values(y.get("nuisance", {})).items()},
        times={"total": total, "first_step": history[0]["seconds"] if history else math.nan},
        solver=options.solver,
        photo=problem.photo_values(y),
    )
    return MultiStartResult(best=best, index=index, starts=count, losses=losses, results=names, start_scenes=list(begun),
                            fitted=fitted, devices=stepper.devices, times={"total": total})


def fit(scene: rtjax.Scene | Sequence[rtjax.Scene], target, free: str | Sequence[str] = "centers", *, spheres: Sequence[int] | None = None,
        options: FitOptions | None = None, callback: Callable[[dict], None] | None = None, **settings) -> FitResult:
    """Fit the free parameters of `scene` so that its render matches `target`.

    **Arguments:**

    - `scene`: the start.
    - `target`: an (H, W, 3) array in 0..255 or an image path (Sun raster in either byte
      order, PNG, JPEG, EXR, TIFF, …). A different size is followed when its aspect
      ratio matches the scene's view, else `FitError`.
      Several views: `scene` a list of scenes (a deck's frames) and `target` a list of
      one target each; the free parameters are shared, the residuals of all frames
      fitted together (`fitting.frames`); the result's scene is the first frame's
      (`frames.fitted_scenes` gives every frame's).
    - `free`: parameter families ('centers', 'radii', 'colors', 'ks', 'beta', 'kt', 'n',
      'ke', 'light', 'light_colors', 'background', 'eye', 'refp', 'vang', 'textures'),
      as a list or comma-separated.
    - `spheres`: restricts per-sphere families to these spheres (indices of `scene`'s).
    - `options`: a `FitOptions`; `settings`, any of its fields by keyword, override it
      (`fit(scene, target, max_steps=10)`).
    - `callback`: called after every iteration with that iteration's history row.

    **Returns:** a `FitResult`.
    """
    options = dataclasses.replace(options or FitOptions(), **settings)
    started = time.perf_counter()
    if isinstance(scene, rtjax.Scene):
        problem = Problem.build(scene, target, free, spheres, options)
        views = [problem.scene]
    else:  # one scene and one target per frame, the free parameters shared (`fitting.frames`)
        problem = build_frames(scene, target, free, spheres, options)
        views = problem.objective.scenes
    if options.smooth:
        if "textures" not in problem.selection.families:
            raise FitError("smooth is a prior on texels: fit textures with it")
        problem = dataclasses.replace(problem, objective=Smoothed(problem.objective, problem.selection, options.smooth))
    stepper = Stepper(problem.objective, options.solver, options.rtol, options.atol, problem.jac)
    single = Single(stepper, stepper.compile_ahead(problem.y0, problem.pyramid))
    result = fit_starts(problem, single, problem.y0, [problem.scene], options, callback, started=started).best
    if "textures" in problem.selection.families:
        result.texels = coverage(views, options.mask, options.depth, smoothed=bool(options.smooth))
    if options.photo or options.nuisance:
        result.verdict = judge(problem, single, result.y, single.end(result.y, problem.pyramid[-1]))
    result.times["total"] = time.perf_counter() - started  # the coverage and verdict included
    return result
