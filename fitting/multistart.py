"""Multi-start fitting: K perturbed starts solved in parallel, the best kept.

A least-squares fit of a scene to an image is local: a start too far from the truth
(a sphere on the wrong side of another, a light from the wrong side) settles in another
basin. `fit_multistart` perturbs the start K − 1 times in the solver's own coordinates
(start 0 is the start as given), and steps all K solves together: one jit-compiled call
advances every start, the solver's step `equinox.filter_vmap`-ped over the starts (on
an accelerator) or taken start after start by `lax.map` inside the call (on a CPU,
where that is faster, see `fit_multistart`'s `mode`). With `devices`, the starts are
laid out over a `jax.sharding.Mesh` with a `NamedSharding` that splits the starts
axis (K padded to a multiple of the device count), so that XLA's partitioner gives
each device its own starts. Each start keeps its own best point, stopping rules and
result, as `fitting.fit` does for one; a start that has stopped is frozen while the
others go on.
The result is the start with the lowest final loss, and how many starts converged.
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
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import rtjax

from .errors import FitError
from .objective import LOSSES, nuisance_values
from .solve import SOLVERS, FitResult, LevelBook, _code, _item, _message, _result_name, _Stepper, prepare_fit, run_levels

AXIS = "starts"


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


def perturbed_starts(y0: dict, starts: int, spread: float, seed: int) -> dict:
    """y0 and K − 1 copies moved by N(0, spread²) in every free coordinate, stacked
    (K, ...). In the solver's coordinates a unit is: the scene's median radius for
    centres, eye and reference point; a logit for colours, ks, kt, ke; a factor e for
    radii, exponents, n − 1; about a radian for light directions."""
    rng = np.random.default_rng(seed)
    leaves, tree = jax.tree.flatten(y0)
    out = []
    for a in leaves:
        a = np.asarray(a)
        noise = rng.normal(0.0, spread, (starts - 1,) + a.shape)
        out.append(jnp.asarray(np.concatenate([a[None], a[None] + noise]), a.dtype))
    return jax.tree.unflatten(tree, out)


class _Parallel:
    """`_Stepper`'s init/step over a leading axis of starts, in one compiled call:
    `lax.map` (mode "map": one start after another, each keeping the renderer's
    run-time skipping of finished ray segments) or `vmap` (mode "vmap": all at once);
    with a mesh, vmapped with the starts axis laid out over the devices."""

    def __init__(self, stepper: _Stepper, mesh: Mesh | None, mode: str):
        self.stepper, self.mesh, self.mode = stepper, mesh, mode
        self.init = eqx.filter_jit(self._init)
        self.step = eqx.filter_jit(self._step)
        self.keep = eqx.filter_jit(_select)

    def _over_starts(self, fn, batched, shared):
        """fn(batched..., shared...) over the starts of `batched` (non-array parts, the
        solver's static state, pass through). With a mesh, every array with a starts
        axis is laid out over the devices (`NamedSharding`, the starts axis split), so
        that XLA's partitioner gives each device its own starts. (Not `shard_map`: the
        solver's state records its arrays' structures, and a manual region adds a
        sharding to some of them and not to others.)"""
        if self.mesh is not None:
            batched = self._spread(batched)
        if self.mode == "vmap" or self.mesh is not None:
            out = eqx.filter_vmap(lambda b: fn(*b, *shared))(batched)
            return out if self.mesh is None else self._spread(out)
        dyn, static = eqx.partition(batched, eqx.is_array)
        box = []

        def one(d):
            out, out_static = eqx.partition(fn(*eqx.combine(d, static), *shared), eqx.is_array)
            box.append(out_static)
            return out

        out = jax.lax.map(one, dyn)
        return eqx.combine(out, box[0])

    def _spread(self, tree):
        split = NamedSharding(self.mesh, PartitionSpec(AXIS))
        return jax.tree.map(lambda a: jax.lax.with_sharding_constraint(a, split) if eqx.is_array(a) else a, tree)

    def _init(self, ys, samples):
        return self._over_starts(lambda y, args: self.stepper._init(y, args), (ys,), (samples,))

    def _step(self, ys, states, samples, active):
        def one(y, state, active, args):
            """One start's step, skipped (`lax.cond`) once it has stopped: in "map" mode a
            stopped start costs nothing (under vmap the cond is a select of both)."""
            dtype = jax.tree.leaves(y)[0].dtype
            dyn_y, dyn_state = eqx.filter((y, state), eqx.is_array)
            box = []

            def run(dyn):
                y, state = eqx.combine(dyn, eqx.filter((y0, s0), eqx.is_array, inverse=True))
                y2, state2, done, result, loss = self.stepper._step(y, state, args)
                code = result._value if hasattr(result, "_value") else result
                new, static = eqx.partition((y2, state2), eqx.is_array)
                box.append(static)
                return new, jnp.asarray(done, bool), jnp.asarray(code, jnp.int32), jnp.asarray(loss, dtype)

            def keep(dyn):
                return dyn, jnp.asarray(True), jnp.asarray(0, jnp.int32), jnp.asarray(jnp.inf, dtype)

            y0, s0 = y, state
            new, done, code, loss = jax.lax.cond(active, run, keep, (dyn_y, dyn_state))
            y2, state2 = eqx.combine(new, box[0])
            return y2, state2, done, code, loss

        return self._over_starts(one, (ys, states, active), (samples,))


def _host(a) -> np.ndarray:
    """A NumPy copy of an array that may span several processes' devices."""
    if jax.process_count() > 1 and isinstance(a, jax.Array) and not a.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def _select(mask, new, old):
    """Per start (mask's leading axis or a scalar), `new` where mask else `old` (arrays only)."""

    def pick(a, b):
        if not eqx.is_array(a):
            return a
        m = jnp.reshape(mask, jnp.shape(mask) + (1,) * (jnp.ndim(a) - jnp.ndim(mask)))
        return jnp.where(m, a, b)

    return jax.tree.map(pick, new, old)


def fit_multistart(
    scene: rtjax.Scene,
    target,
    free: str | Sequence[str] = "centers",
    *,
    starts: int = 4,
    seed: int = 0,
    spread: float = 0.5,
    devices=None,
    mode: str = "auto",
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
) -> MultiStartResult:
    """`fitting.fit` from `starts` starts in parallel; the one with the lowest final loss
    is kept (`result.best`, a `FitResult`), `result.converged` says how many converged.

    starts: K; start 0 is `scene` as given, the others are perturbed by N(0, spread²)
      in the solver's coordinates (`perturbed_starts`), drawn from `seed`.
    devices: None (one device), an int, "all", or a list of devices: the starts are
      laid out over them (`rtjax.device_mesh`), each device stepping its own.
    mode: one device's starts within its one compiled call per iteration: "vmap" (all
      at once), "map" (one after another, `lax.map`), or "auto" (default: "map" on a
      single CPU, where `vmap` turns the renderer's run-time skipping of finished ray
      segments into selects, measured about 3× slower; "vmap" otherwise). With
      several devices the starts are vmapped.
    Other options as `fitting.fit`. The iteration count is shared: each iteration
    steps every start that has not stopped. `callback` gets one row per iteration,
    for the start with the lowest loss so far, with `active` (starts still going).
    """
    if solver not in SOLVERS:
        raise FitError(f"unknown solver {solver!r}; choose from {', '.join(SOLVERS)}")
    if loss not in LOSSES:
        raise FitError(f"unknown loss {loss!r}; choose from {', '.join(LOSSES)}")
    if int(max_steps) < 1:
        raise FitError(f"max_steps must be ≥ 1, not {max_steps}")
    if int(starts) < 1:
        raise FitError(f"starts must be ≥ 1, not {starts}")
    if mode not in ("auto", "vmap", "map"):
        raise FitError(f"mode must be 'auto', 'vmap' or 'map', not {mode!r}")
    if not (spread >= 0 and math.isfinite(spread)):
        raise FitError(f"spread must be a finite number ≥ 0, not {spread}")
    starts = int(starts)
    try:
        mesh = rtjax.device_mesh(devices)
    except rtjax.RtjaxError as e:
        raise FitError(str(e)) from None
    if mesh is not None:
        mesh = Mesh(mesh.devices, (AXIS,))
    n_dev = 1 if mesh is None else mesh.devices.size
    t_start = time.perf_counter()

    full, selection, y, jac, widths, pyramid, objective = prepare_fit(
        scene, target, free, spheres, depth, levels, edges, polish, loss, loss_scale, mask, nuisance, jac, assignment_order,
        exact_polish)
    if mode == "auto":
        mode = "map" if mesh is None and jax.devices()[0].platform == "cpu" else "vmap"
    run = _Parallel(_Stepper(objective, SOLVERS[solver](rtol, atol), solver, jac), mesh, mode)

    # K starts, padded to a multiple of the device count with copies that never step
    padded = -(-starts // n_dev) * n_dev
    ys = perturbed_starts(y, starts, spread, seed)
    if padded > starts:
        ys = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], padded - starts, axis=0)]), ys)
    real = np.arange(padded) < starts
    y_first = jax.tree.map(lambda a: a, ys)

    histories: list[list[dict]] = [[] for _ in range(starts)]
    book = LevelBook(padded, False, 0.0, active=real)  # the last level's (none yet)

    def level(samples, width, budget, full_size, until, steps):
        nonlocal book, ys
        states = run.init(ys, samples)
        best_y = ys
        book = LevelBook(padded, not full_size, until, active=real)
        n = 0
        for n in range(1, budget + 1):
            t0 = time.perf_counter()
            ys, states, done_now, result_now, loss_now = run.step(ys, states, samples, jnp.asarray(~book.stopped))
            loss_now = _host(loss_now).astype(np.float64)
            active, better = book.update(loss_now, _host(done_now), _host(result_now))
            seconds = time.perf_counter() - t0
            if better.any():
                best_y = run.keep(jnp.asarray(better), ys, best_y)
            elapsed = time.perf_counter() - t_start
            for k in np.flatnonzero(active[:starts]):
                histories[k].append({
                    "step": steps + n, "width": width, "loss": float(loss_now[k]), "best_loss": float(book.best[k]),
                    "rmse_levels": math.sqrt(2 * book.best[k]) * 255 if math.isfinite(book.best[k]) else math.nan,
                    "seconds": seconds, "elapsed": elapsed,
                })
            if callback is not None:
                lead = int(np.argmin(np.where(real, book.best, math.inf)))
                row = dict(histories[lead][-1]) if histories[lead] and histories[lead][-1]["step"] == steps + n else {
                    "step": steps + n, "width": width, "loss": float(loss_now[lead]), "best_loss": float(book.best[lead]),
                    "rmse_levels": math.sqrt(2 * book.best[lead]) * 255, "seconds": seconds, "elapsed": elapsed}
                row.update(start=lead, active=int((~book.stopped[:starts]).sum()))
                callback(row)
            if book.stopped.all():
                break
        book.finish()
        ys = best_y
        return n

    steps, out_of_steps = run_levels(pyramid, widths, max_steps, loss_scale, lambda: book.best[real], level)
    results, best_loss, levelled = book.results, book.best, book.levelled
    if out_of_steps:
        results[real & (results == _code(optx.RESULTS.successful))] = _code(optx.RESULTS.max_steps_reached)

    names = [_result_name(_item(r)) for r in results[:starts]]
    losses = [float(x) for x in best_loss[:starts]]
    order = np.where(np.isfinite(losses), losses, math.inf)
    index = int(np.argmin(order))
    ys = jax.tree.map(lambda a: jnp.asarray(_host(a)), ys)  # every start's end, on this process
    pick = jax.tree.map(lambda a: a[index], ys)
    structure = scene.structure.replace(width=full.structure.width, height=full.structure.height)
    fitted = [rtjax.Scene(structure, selection.params(jax.tree.map(lambda a: a[k], ys)["scene"])) for k in range(starts)]
    begun = [rtjax.Scene(structure, selection.params(jax.tree.map(lambda a: a[k], y_first)["scene"])) for k in range(starts)]
    name = names[index]
    total = time.perf_counter() - t_start
    history = histories[index]
    best = FitResult(
        scene=fitted[index],
        start=begun[index],
        selection=selection,
        y=pick,
        history=history,
        result=name,
        message=(("converged: the loss levelled off" if levelled[index] else "converged") if name == "successful"
                 else _message(_item(results[index]))),
        converged=name == "successful",
        steps=steps,
        nuisance={k: float(v) for k, v in nuisance_values(pick.get("nuisance", {})).items()},
        times={"total": total, "first_step": history[0]["seconds"] if history else math.nan},
        solver=solver,
    )
    return MultiStartResult(best=best, index=index, starts=starts, losses=losses, results=names, start_scenes=begun,
                            fitted=fitted, devices=n_dev, times={"total": total})


def summary_line(result: MultiStartResult) -> str:
    """One line: starts, devices, how many converged, which was kept."""
    devices = f"{result.devices} device{'s' if result.devices != 1 else ''}"
    return (f"multi-start: {result.starts} starts on {devices}, {result.converged} of {result.starts} converged; "
            f"kept start {result.index} (loss {result.losses[result.index]:.4e}, {result.results[result.index]})")


def report_entry(result: MultiStartResult) -> dict:
    """The multi-start part of the JSON report."""
    return {
        "starts": result.starts,
        "devices": result.devices,
        "converged": result.converged,
        "kept": result.index,
        "losses": result.losses,
        "results": result.results,
        "start_values": [result.best.selection.values(s.params) for s in result.start_scenes],
        "seconds": result.times["total"],
    }


def add_to_report(path: str, result: MultiStartResult) -> None:
    """Add `report_entry` to a fit's JSON report (written by `report.save_outputs`)."""
    import json

    from .report import write_json

    with open(path) as f:
        data = json.load(f)
    entry = report_entry(result)
    entry["start_values"] = [{k: np.asarray(v).tolist() if not isinstance(v, tuple) else "texels"
                              for k, v in values.items()} for values in entry["start_values"]]
    data["multistart"] = entry
    write_json(path, data)
