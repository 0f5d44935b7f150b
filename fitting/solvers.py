"""The solvers and their compiled step: optimistix's `init`/`step`/`terminate` for one start.

A fit steps its solver by hand (optimistix's interactive API), one jit-compiled step per
iteration, so that every iteration can be reported and the best point kept; a step's
optimistix result comes back as an integer code of this module's own table (`RESULTS`).
"""

from __future__ import annotations

import threading
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .matrixfree import LM_STEP0_MATRIX_FREE, matrix_free
from .objective import Objective, Stages

#: Levenberg–Marquardt's first trust-region step size on every level (its damping
#: λ = 1/step; optimistix starts at 1): residuals are in 1/255 units per sample, so λ = 1
#: damps the first steps into slow gradient descent.
LM_STEP0 = 10.0
#: Levenberg–Marquardt's trust region grows (3.5×) after a step whose actual reduction of
#: the loss is above this share of the predicted one (Moré's 0.75; optimistix asks 0.99).
LM_GROW_ABOVE = 0.75


class _TrustRegion(optx.ClassicalTrustRegion):
    """optimistix's classical trust region, starting at `step0` (default `LM_STEP0`) on every level."""

    step0: float = LM_STEP0

    def init(self, y, f_info_struct):
        state = super().init(y, f_info_struct)
        return eqx.tree_at(lambda s: s.step_size, state, jnp.asarray(self.step0, state.step_size.dtype))


def _levenberg_marquardt(rtol: float, atol: float) -> optx.LevenbergMarquardt:
    lm = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    return eqx.tree_at(lambda s: s.search, lm, _TrustRegion(high_cutoff=LM_GROW_ABOVE))


def promised_gain(y, state):
    """The share of the loss at the last accepted point `y` that a least-squares
    solver's model (Gauss–Newton's ½‖r + J·Δ‖²) expects its trial point `state.y_eval`
    to remove; 0 for BFGS, whose line search has no such model (its rejected steps
    count as steps without a gain)."""
    info = state.f_info
    if not isinstance(info, optx.FunctionInfo.ResidualJac):
        return jnp.zeros((), jax.tree.leaves(y)[0].dtype)
    diff = jax.tree.map(lambda a, b: a - b, state.y_eval, y)
    predicted = optx.ClassicalTrustRegion().predict_reduction(diff, info)
    loss = info.as_min()  # ½‖r‖², the loss the trust region itself compares
    return -predicted / jnp.maximum(loss, jnp.finfo(loss.dtype).tiny)


#: The solvers by name, each made from (rtol, atol).
SOLVERS = {
    "lm": _levenberg_marquardt,
    "gn": lambda rtol, atol: optx.GaussNewton(rtol=rtol, atol=atol),
    "dogleg": lambda rtol, atol: optx.Dogleg(rtol=rtol, atol=atol),
    "bfgs": lambda rtol, atol: optx.BFGS(rtol=rtol, atol=atol),
}

#: optimistix's results a compiled step can return, in the order of their integer codes
#: (`result_code`); a result outside the table has code `len(RESULTS)`.
RESULTS = tuple(name for name in ("successful", "max_steps_reached", "nonlinear_divergence", "nonlinear_max_steps_reached",
                                  "singular", "breakdown", "stagnation", "conlim", "nonfinite_input", "nonfinite")
                if hasattr(optx.RESULTS, name))
#: The results a fit reports by name (`result_name`); any other is "failed".
NAMED = ("successful", "max_steps_reached", "nonlinear_divergence", "nonlinear_max_steps_reached", "singular", "breakdown",
         "stagnation")
#: Integer code of each result in `RESULTS`.
CODES = {name: code for code, name in enumerate(RESULTS)}
_MESSAGES = tuple(optx.RESULTS[getattr(optx.RESULTS, name)] for name in RESULTS)


def result_code(result) -> Int[Array, ""]:
    """An optimistix result as its code in `RESULTS` (traceable: public comparisons only)."""
    code = jnp.asarray(len(RESULTS), jnp.int32)
    for index in reversed(range(len(RESULTS))):
        code = jnp.where(result == getattr(optx.RESULTS, RESULTS[index]), jnp.int32(index), code)
    return code


def result_name(code: int) -> str:
    """The name a fit reports for a result code: the result's own if `NAMED`, else "failed"."""
    name = RESULTS[code] if 0 <= code < len(RESULTS) else "failed"
    return name if name in NAMED else "failed"


def result_message(code: int) -> str:
    """optimistix's message for a result code (its name where the message is empty)."""
    if not 0 <= code < len(RESULTS):
        return "failed"
    return _MESSAGES[code] or RESULTS[code]


def with_dense_jacobian(fn, stages=None):
    """fn(y, args) with a jvp rule in y that builds the whole Jacobian by `jax.jacfwd`
    (one batched forward pass) and applies it: J·ẏ.

    optimistix's Gauss–Newton family linearises fn and then evaluates the linear map once
    per free parameter; with this rule that is a matrix product, and the render's
    forward-mode pass runs once per step. Reverse mode still works: the rule is linear in
    ẏ, so JAX transposes it.

    `stages(y, args)`, where given, is fn in two stages (`objective.Stages`): the render
    then carries tangents of the parameters it reads alone, and the camera's parameters
    (a photo's gain, tone curve, blur, ...) are differentiated after it, on its output.
    The same Jacobian, at a fraction of the render's cost (it is most of a step's)."""

    def dense_fn(y, args):
        # the args' non-array parts (a level's static flags) stay Python values
        arrays, static = eqx.partition(args, eqx.is_array)

        @jax.custom_jvp
        def dense(y, arrays):
            return fn(y, eqx.combine(arrays, static))

        @dense.defjvp
        def dense_jvp(primals, tangents):
            (y, arrays), (ydot, _) = primals, tangents
            a = eqx.combine(arrays, static)
            if stages is not None:
                jac, value = staged_jacobian(stages(y, a), y)
            else:
                flat, unravel = jax.flatten_util.ravel_pytree(y)
                jac, value = jax.jacfwd(lambda v: (fn(unravel(v), a),) * 2, has_aux=True)(flat)
            step, _ = jax.flatten_util.ravel_pytree(ydot)
            return value, jnp.tensordot(jac, step, axes=1)

        return dense(y, arrays)

    return dense_fn


def staged_jacobian(s: Stages, y: dict):
    """(J, value) of r(y) = s.finish(s.render(a), b), (a, b) = s.split(y): J (…, n) over
    y's flattened entries, as `jax.jacfwd` gives it; the render's Jacobian over a's
    entries alone, pushed through the finish's linearisation, and the finish's own over
    b's entries."""
    leaves, tree = jax.tree_util.tree_flatten(y)
    ends = np.cumsum([0] + [np.size(leaf) for leaf in leaves])
    first, second = s.split(y)
    # where a's and b's entries sit in y's flattening (static: NumPy, not traced)
    where = tree.unflatten([np.arange(a, b).reshape(np.shape(leaf)) for a, b, leaf in zip(ends[:-1], ends[1:], leaves)])
    index = [np.concatenate([np.ravel(i) for i in jax.tree_util.tree_leaves(part)] + [np.zeros(0, np.int64)])
             for part in s.split(where)]
    v1, unravel1 = jax.flatten_util.ravel_pytree(first)
    v2, unravel2 = jax.flatten_util.ravel_pytree(second)
    if v2.size == 0:  # nothing after the render: the plain Jacobian
        return jax.jacfwd(lambda v: (s.finish(s.render(unravel1(v)), second),) * 2, has_aux=True)(v1)
    jac1, rendered = jax.jacfwd(lambda v: (s.render(unravel1(v)),) * 2, has_aux=True)(v1)
    value, linear = jax.linearize(lambda r: s.finish(r, second), rendered)
    columns = [jax.vmap(linear, in_axes=-1, out_axes=-1)(jac1),
               jax.jacfwd(lambda v: s.finish(rendered, unravel2(v)))(v2)]
    jac = jnp.zeros(value.shape + (int(ends[-1]),), value.dtype)
    for i, c in zip(index, columns):
        jac = jac.at[..., i].set(c)
    return jac, value


class Ahead(threading.Thread):
    """A daemon thread, started at once, that compiles a program ahead of its use
    (`compile_ahead`). Its error is kept for `wait`, not printed by the thread: it
    belongs to the fit, raised where the fit needs the program."""

    def __init__(self, compile: Callable[[], object], name: str = "compile ahead"):
        super().__init__(name=name, daemon=True)
        self._compile, self.error = compile, None
        self.start()

    def run(self) -> None:
        try:
            self._compile()
        except BaseException as e:  # handed to `wait`
            self.error = e

    def wait(self) -> None:
        """Once compiled: raises the compile's error, if any."""
        self.join()
        if self.error is not None:
            raise self.error


def compile_ahead(lower, pyramid) -> Ahead | None:
    """Where a fit's levels `pyramid` end in a whole-image level after coarser ones (a
    photo's, with a program of its own): traces the first level's step here and compiles
    it in a background thread, meanwhile traces the last level's step here and compiles
    it in another, started and returned (else None); returns once the first level's is
    compiled. `lower` gives a level's step traced and lowered. Tracing holds Python's
    lock and XLA's compile does not, so each trace overlaps a compile: the first step
    waits for one trace and the longer of its compile and the other trace, and the
    whole-image program, the larger, compiles while the levels before it run (its first
    step finds the executable: JAX keeps it). Both compile in `Ahead` threads: the first
    is awaited here, its error raised; the whole-image one is returned unawaited, so
    that a fit stopped early need not wait for it, and should it fail, its error is
    raised when its level begins (`Ahead.wait`)."""
    if len(pyramid) < 2 or not pyramid[-1].whole:
        return None
    first = Ahead(lower(pyramid[0]).compile, "compile first")
    ahead = Ahead(lower(pyramid[-1]).compile)
    first.wait()
    return ahead


class Step(NamedTuple):
    """One solver step of one start (`Stepper.advance`), or of K starts (a leading axis;
    `fitting.solve.Steps.step`, NumPy arrays on the host)."""

    y: Any  # the last accepted point
    state: Any  # the solver's state
    done: Bool[Array, "*starts"]  # the solver says it is done
    code: Int[Array, "*starts"]  # its result (`result_code`)
    loss: Float[Array, "*starts"]  # ½·mean(r²) at y
    accepted: Bool[Array, "*starts"]  # this step's trial point was accepted (y is it)
    promised: Float[Array, "*starts"]  # the share of the loss its model expected it to remove (`promised_gain`)

    def on_host(self, host=np.asarray) -> Step:
        """This step as `fitting.solve.Steps.step` returns it: its flags, codes, losses and
        promised gains as NumPy arrays with a leading axis of starts (one for a single
        start; losses and gains float64), each copied by `host` (y and state as they are)."""

        def field(a, dtype):
            return np.atleast_1d(host(a)).astype(dtype)

        return self._replace(done=field(self.done, bool), code=field(self.code, np.int32),
                             loss=field(self.loss, np.float64), accepted=field(self.accepted, bool),
                             promised=field(self.promised, np.float64))


class Stepper:
    """A solver's init and step on one start, for every level of a fit.

    **Arguments:**

    - `objective`: the residual function r(y, samples).
    - `solver`: a key of `SOLVERS`; `rtol`, `atol` its tolerances.
    - `jac`: 'fwd' (the Jacobian by `with_dense_jacobian`), 'bwd' (reverse mode) or
      'matfree' (no Jacobian: `matrixfree.matrix_free`).

    `initial` and `advance` are traceable; their `args` are a level's samples and the
    objective's start (`Stepper.args`). `init` and `step` are their `eqx.filter_jit`
    forms on a level's samples, compiled once per fit; the samples and the start being
    arguments, a fit of the same structure from another start or target lowers to the
    same programs and finds them in the compilation cache.
    """

    def __init__(self, objective: Objective, solver: str, rtol: float, atol: float, jac: str):
        self.start = objective.start()

        def residual(y, args):
            samples, start = args
            return objective.at(start).residuals(y, samples)

        def stages(y, args):
            samples, start = args
            return objective.at(start).stages(y, samples)

        staged = stages if hasattr(objective, "stages") else None
        residuals = with_dense_jacobian(residual, staged) if jac == "fwd" else residual
        self.options = {"jac": "bwd"} if jac == "bwd" and solver != "bfgs" else {}
        self.solver = SOLVERS[solver](rtol, atol)
        if jac == "matfree" and solver != "bfgs":
            self.solver = matrix_free(self.solver)
            if solver == "lm":
                self.solver = eqx.tree_at(lambda s: s.search.step0, self.solver, LM_STEP0_MATRIX_FREE)
        if solver == "bfgs":
            def fn(y, args):
                r = residuals(y, args)
                return 0.5 * jnp.sum(r * r), None
        else:
            def fn(y, args):
                return residuals(y, args), None
        self.fn = fn
        self._init = eqx.filter_jit(self.initial)
        self._step = eqx.filter_jit(self.advance)

    def args(self, samples):
        """The solver's `args` on the level `samples`: (samples, the objective's start)."""
        return samples, self.start

    def init(self, y, samples):
        """The solver's state at y on the level `samples` (compiled)."""
        return self._init(y, self.args(samples))

    def step(self, y, state, samples):
        """`advance` on the level `samples` (compiled)."""
        return self._step(y, state, self.args(samples))

    def initial(self, y, args):
        """The solver's state at y for `args` (`Stepper.args`)."""
        f_struct, aux_struct = jax.eval_shape(lambda: self.fn(y, args))
        return self.solver.init(self.fn, y, args, self.options, f_struct, aux_struct, frozenset())

    def compile_ahead(self, y, pyramid) -> Ahead | None:
        """`compile_ahead` of `step` at y over the levels `pyramid`."""

        def lower(samples):
            args = self.args(samples)
            return self._step.lower(y, self._init(y, args), args)

        return compile_ahead(lower, pyramid)

    def advance(self, y, state, args) -> Step:
        """One solver step (a `Step`: the last accepted point, the state, and what the
        level's bookkeeping needs of it)."""
        dtype = jax.tree.leaves(y)[0].dtype
        before = state.num_accepted_steps
        promised = promised_gain(y, state)
        y, state, _ = self.solver.step(self.fn, y, args, self.options, state, frozenset())
        done, result = self.solver.terminate(self.fn, y, args, self.options, state, frozenset())
        # the state holds the accepted point's function value (no second render):
        # Gauss–Newton family residuals, or BFGS's ½Σr²
        info = state.f_info
        loss = 0.5 * jnp.mean(info.residual**2) if hasattr(info, "residual") else info.f / args[0].target.size
        return Step(y, state, jnp.asarray(done, bool), result_code(result), jnp.asarray(loss, dtype),
                    state.num_accepted_steps > before, jnp.asarray(promised, dtype))
