"""Multi-start fitting: K perturbed starts solved in parallel, the best kept.

A least-squares fit of a scene to an image is local: a start too far from the truth
(a sphere on the wrong side of another, a light from the wrong side) settles in another
basin. `fit_multistart` perturbs the start K − 1 times in the solver's own coordinates
(start 0 is the start as given) and steps all K solves together through the driver
`fitting.solve.fit_starts`: one jit-compiled call advances every start (`Parallel`),
the solver's step `equinox.filter_vmap`-ped over the starts (on an accelerator) or taken
start after start by `lax.map` inside the call (on a CPU, where that is faster). With
`devices`, the starts are laid out over a `jax.sharding.Mesh` with a `NamedSharding`
that splits the starts axis (K padded to a multiple of the device count), so that XLA's
partitioner gives each device its own starts (on CPUs, a row of them that it takes
one after another by `lax.map`). Each start keeps its own best point,
stopping rules and result; a start that has stopped is frozen while the others go on.
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
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import rtjax

from .errors import FitError
from .options import FitOptions
from .problem import Problem
from .solve import MultiStartResult, fit_starts
from .solvers import CODES, Step, Stepper, compile_ahead
from .verdict import judge

#: The mesh axis the starts are laid out over.
AXIS = "starts"
#: One device's ways of stepping its starts (`fit_multistart`'s `mode`).
MODES = ("auto", "vmap", "map")


def perturbed_starts(y0: dict, starts: int, spread: float, seed: int) -> dict:
    """y0 and K − 1 copies moved by N(0, spread²) in every free coordinate, stacked
    (K, ...), drawn start after start, so that the first k starts are the same whatever
    K. In the solver's coordinates a unit is: the scene's median radius for centres,
    eye and reference point; a logit for colours, ks, kt, ke; a factor e for radii,
    exponents, n − 1; about a radian for light directions."""
    rng = np.random.default_rng(seed)
    leaves, tree = jax.tree.flatten(y0)
    arrays = [np.asarray(a) for a in leaves]
    noise = [[rng.normal(0.0, spread, a.shape) for a in arrays] for _ in range(starts - 1)]
    out = [jnp.asarray(np.stack([a] + [a + moved[i] for moved in noise]), a.dtype) for i, a in enumerate(arrays)]
    return jax.tree.unflatten(tree, out)


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


class Parallel:
    """`solve.Steps` of K starts: a `Stepper`'s init/step over a leading axis of starts, in
    one compiled call.

    **Arguments:**

    - `stepper`: the one-start `Stepper`.
    - `mesh`: None (one device), or a mesh whose one axis (`AXIS`) the starts are laid
      out over (vmapped across the devices).
    - `mode`: each device's own starts: "map" (`lax.map`: one start after another, on
      one device each keeping the renderer's run-time skipping of finished ray
      segments) or "vmap" (all at once).
    - `starts`: K; padded to a multiple of the device count with copies that never step.
    """

    def __init__(self, stepper: Stepper, mesh: Mesh | None, mode: str, starts: int):
        self.stepper, self.mesh, self.mode = stepper, mesh, mode
        self.devices = 1 if mesh is None else mesh.devices.size
        self.size = -(-starts // self.devices) * self.devices
        self._init = eqx.filter_jit(self._initial)
        self._step = eqx.filter_jit(self._advance)
        self._keep = eqx.filter_jit(_select)
        self.ahead = None  # set by `compile_ahead`

    def pad(self, ys):
        """Starts `ys` (K, ...) padded to `size` with copies of the last."""
        extra = self.size - jax.tree.leaves(ys)[0].shape[0]
        if extra <= 0:
            return ys
        return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]), ys)

    def compile_ahead(self, ys, pyramid):
        """`solvers.compile_ahead` of the step of the starts `ys` (padded) over the levels
        `pyramid` (its thread: `ahead`)."""
        active = jnp.ones(self.size, bool)

        def lower(samples):
            args = self.stepper.args(samples)
            return self._step.lower(ys, self._init(ys, args), args, active)

        self.ahead = compile_ahead(lower, pyramid)

    def init(self, ys, samples):
        return self._init(ys, self.stepper.args(samples))

    def step(self, ys, states, samples, active):
        return self._step(ys, states, self.stepper.args(samples), jnp.asarray(active)).on_host(_host)

    def keep(self, better, new, old):
        return self._keep(jnp.asarray(better), new, old)

    def unstack(self, ys, count):
        ys = jax.tree.map(lambda a: jnp.asarray(_host(a)), ys)  # every start's end, on this process
        return [jax.tree.map(lambda a: a[k], ys) for k in range(count)]

    def evaluate(self, points, samples):
        """Up to `size` points in one call of the fit's compiled step (the rest of the
        starts axis padded and left inactive)."""
        out = []
        for first in range(0, len(points), self.size):
            chunk = list(points[first:first + self.size])
            ys = self.pad(jax.tree.map(lambda *a: jnp.stack(a), *chunk))
            active = np.arange(self.size) < len(chunk)
            step = self.step(ys, self.init(ys, samples), samples, active)
            states = jax.tree.map(lambda a: np.asarray(_host(a)) if eqx.is_array(a) else a, step.state)
            out.extend((float(step.loss[k]), jax.tree.map(lambda a: a[k] if eqx.is_array(a) else a, states))
                       for k in range(len(chunk)))
        return out

    def _over_starts(self, fn, batched, shared):
        """fn(batched..., shared...) over the starts of `batched` (non-array parts, the
        solver's static state, pass through). With a mesh, every array with a starts
        axis is laid out over the devices (`NamedSharding`, the starts axis split), so
        that XLA's partitioner gives each device its own starts; in "map" mode as rows
        of (devices, starts per device), vmapped over the devices, each device mapping
        over its row. (Not `shard_map`: the solver's state records its arrays'
        structures, and a manual region adds a sharding to some of them and not to
        others.)"""
        def each(b):  # one device's starts, in the mode's way
            return self._map(fn, b, shared) if self.mode == "map" else eqx.filter_vmap(lambda b: fn(*b, *shared))(b)

        if self.mesh is None:
            return each(batched)
        if self.mode != "map":
            return self._spread(each(self._spread(batched)))

        def reshape(tree, shape):
            return jax.tree.map(lambda a: a.reshape(shape(a)) if eqx.is_array(a) else a, tree)

        rows = self._spread(reshape(batched, lambda a: (self.devices, -1) + a.shape[1:]))
        return self._spread(reshape(eqx.filter_vmap(each)(rows), lambda a: (-1,) + a.shape[2:]))

    @staticmethod
    def _map(fn, batched, shared):
        """fn over the leading axis of `batched` by `lax.map`, one start after another."""
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

    def _initial(self, ys, args):
        return self._over_starts(self.stepper.initial, (ys,), (args,))

    def _advance(self, ys, states, args, active):
        def one(y, state, active, args):
            """One start's step, skipped (`lax.cond`) once it has stopped: in "map" mode a
            stopped start costs nothing (under vmap the cond is a select of both)."""
            dtype = jax.tree.leaves(y)[0].dtype
            dyn, static = eqx.partition((y, state), eqx.is_array)
            box = []

            def run(dyn):
                step = self.stepper.advance(*eqx.combine(dyn, static), args)
                (y2, state2), out_static = eqx.partition((step.y, step.state), eqx.is_array)
                box.append(out_static)
                return step._replace(y=y2, state=state2)

            def keep(dyn):
                return Step(*dyn, jnp.asarray(True), jnp.asarray(CODES["successful"], jnp.int32),
                            jnp.asarray(jnp.inf, dtype), jnp.asarray(False), jnp.asarray(0, dtype))

            step = jax.lax.cond(active, run, keep, dyn)
            y2, state2 = eqx.combine((step.y, step.state), box[0])
            return step._replace(y=y2, state=state2)

        return self._over_starts(one, (ys, states, active), (args,))


def fit_multistart(scene: rtjax.Scene, target, free: str | Sequence[str] = "centers", *, starts: int = 4, seed: int = 0,
                   spread: float = 0.5, devices=None, mode: str = "auto", spheres: Sequence[int] | None = None,
                   options: FitOptions | None = None, callback: Callable[[dict], None] | None = None,
                   **settings) -> MultiStartResult:
    """`fitting.fit` from `starts` starts in parallel; the one with the lowest final loss
    is kept (`result.best`, a `FitResult`), `result.converged` says how many converged.

    **Arguments:**

    - `scene`, `target`, `free`, `spheres`, `options`, `settings`: as `fitting.fit`.
    - `starts`: K; start 0 is `scene` as given, the others are perturbed by
      N(0, spread²) in the solver's coordinates (`perturbed_starts`), drawn from `seed`.
    - `devices`: None (one device), an int, "all", or a list of devices: the starts are
      laid out over them (`rtjax.device_mesh`), each device stepping its own (not
      several CPU devices for a fit with a whole-image level, a photo or a fitted blur:
      refused, for that level ran minutes per step there).
    - `mode`: one device's starts within its one compiled call per iteration: "vmap"
      (all at once), "map" (one after another, `lax.map`), or "auto" (default: "map" on
      CPUs, where `vmap` turns the renderer's run-time skipping of finished ray
      segments into selects, and where a camera model's step with two or more starts
      vmapped on each of several devices hung; "vmap" otherwise). Across several
      devices the starts are vmapped, each device taking its own.
    - `callback`: called after every iteration (each steps every start that has not
      stopped) with the history row of the start with the lowest loss so far, plus
      `start` (which one) and `active` (how many starts are still going).

    **Returns:** a `MultiStartResult`.
    """
    options = dataclasses.replace(options or FitOptions(), **settings)
    if int(starts) < 1:
        raise FitError(f"starts must be ≥ 1, not {starts}")
    if mode not in MODES:
        raise FitError(f"mode must be 'auto', 'vmap' or 'map', not {mode!r}")
    if not (spread >= 0 and math.isfinite(spread)):
        raise FitError(f"spread must be a finite number ≥ 0, not {spread}")
    starts = int(starts)
    try:
        mesh = rtjax.device_mesh(devices)
    except rtjax.RtjaxError as e:
        raise FitError(str(e)) from None
    cpu = jax.devices()[0].platform == "cpu"
    if mode == "auto":
        mode = "map" if cpu else "vmap"
    if mesh is not None and 1 < mesh.devices.size < starts and mode == "vmap" and cpu \
            and (options.photo or options.nuisance):
        raise FitError(f"a camera model (--photo, --nuisance) with {starts} starts vmapped over {mesh.devices.size} CPU "
                       "devices hangs in XLA's sharded step when a device holds two starts or more (a known issue): "
                       "use mode 'map' (the default on CPUs), at most one start per device, or one device")
    started = time.perf_counter()
    problem = Problem.build(scene, target, free, spheres, options)
    if mesh is not None and mesh.devices.size > 1 and cpu and any(level.whole for level in problem.pyramid):
        raise FitError("a fit whose full-size level renders the whole image (--photo, or a fitted blur) with its "
                       f"starts over {mesh.devices.size} CPU devices ran minutes per step there (XLA's sharded "
                       "whole-image step): use one device")
    if mesh is not None:
        mesh = Mesh(mesh.devices, (AXIS,))
    stepper = Parallel(Stepper(problem.objective, options.solver, options.rtol, options.atol, problem.jac), mesh, mode,
                       starts)
    ys = stepper.pad(perturbed_starts(problem.y0, starts, spread, seed))
    stepper.compile_ahead(ys, problem.pyramid)
    structure = problem.scene.structure
    begun = [rtjax.Scene(structure, problem.selection.params(jax.tree.map(lambda a: a[k], ys)["scene"]))
             for k in range(starts)]
    result = fit_starts(problem, stepper, ys, begun, options, callback, started=started, several=True)
    if options.photo or options.nuisance:  # judged with the starts' own compiled step
        result.best.verdict = judge(problem, stepper, result.best.y)
    return result
