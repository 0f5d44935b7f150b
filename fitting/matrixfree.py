"""Least squares without a dense Jacobian, for fits of many free parameters (texels).

The Gauss–Newton family's step solves the (damped) linear least-squares problem
min ‖J·δ + r‖² (+ λ‖δ‖²). With few free parameters `solvers.with_dense_jacobian` builds J
by one batched forward-mode pass; with thousands (a texture's texels) J would not fit in
memory. Here J is never formed: optimistix linearises the residual function
(`jax.linearize`, its `jac="fwd"`), so J·v is one forward-mode pass through the stored
linearisation and Jᵀ·w its transpose (reverse mode, derived by JAX), and the step comes
from LSMR (`lineax.LSMR`: conjugate gradients on the normal equations in their stable
form, with scale-free stopping rules), a few tens of J·v and Jᵀ·w products per step.
"""

from __future__ import annotations

import equinox as eqx
import lineax as lx

#: Fits of more free parameters than this solve their steps matrix-free (`jac="matfree"`);
#: fewer take the dense forward-mode Jacobian (`jac="fwd"`).
MATRIX_FREE_ABOVE = 200
#: LSMR per step: its relative tolerance (‖Jᵀr‖ ≤ rtol·‖J‖·‖r‖ of the damped problem),
#: and at most this many iterations (one J·v and one Jᵀ·w each). An inexact step is
#: enough: the trust region judges it by the loss it achieves.
LSMR_RTOL = 1e-4
LSMR_MAX_STEPS = 60
#: Levenberg–Marquardt's first trust-region step size (damping λ = 1/step) on a
#: matrix-free fit. Its free parameters are many and each weighs little in the residual
#: (a texel moves a few pixels by a share of its change, in 1/255 units), so the entries
#: of JᵀJ are small and `solvers.LM_STEP0` would damp the first steps into slow gradient
#: descent.
LM_STEP0_MATRIX_FREE = 1000.0


class Truncated(lx.AbstractLinearSolver):
    """A linear solver whose iterations running out is a success: its solution is taken
    as it stands (a truncated, inexact Newton step), since optimistix rejects a step
    whose linear solve failed."""

    inner: lx.AbstractLinearSolver

    def init(self, operator, options):
        return self.inner.init(operator, options)

    def compute(self, state, vector, options):
        solution, result, stats = self.inner.compute(state, vector, options)
        ran_out = result == lx.RESULTS.max_steps_reached
        return solution, lx.RESULTS.where(ran_out, lx.RESULTS.successful, result), stats

    def transpose(self, state, options):
        return self.inner.transpose(state, options)

    def conj(self, state, options):
        return self.inner.conj(state, options)

    def assume_full_rank(self):
        return self.inner.assume_full_rank()


def lsmr() -> lx.AbstractLinearSolver:
    """The matrix-free linear solver: LSMR, at most `LSMR_MAX_STEPS` iterations
    (`Truncated`). Not `lineax.Normal(lineax.CG)`: its breakdown test is relative to
    the operator's scale and stops it at once in float32 on JᵀJ of 1/255-unit residuals."""
    return Truncated(lx.LSMR(rtol=LSMR_RTOL, atol=0.0, max_steps=LSMR_MAX_STEPS, conlim=float("inf")))


def matrix_free(solver):
    """An optimistix least-squares solver (Levenberg–Marquardt, Gauss–Newton, Dogleg)
    whose descent solves its linear problem by `lsmr` instead of a factorisation of
    the materialised Jacobian. Use it with the option `jac="fwd"` (`jax.linearize`)."""
    return eqx.tree_at(lambda s: s.descent.linear_solver, solver, lsmr())
