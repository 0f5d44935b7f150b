"""NaN-free building blocks: every value and every derivative (jvp and vjp) is finite.

The traps they avoid: `sqrt` and `norm` at 0 have infinite slope, `x**β` at x = 0 has
log(0) in its β-derivative, and `where` does not stop a NaN in the branch it discards
from reaching the gradient (hence the "double where": make the discarded input safe).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def tiny(dtype) -> float:
    """A floor for squared quantities: far below anything meaningful, far above underflow."""
    return 1e-30 if jnp.dtype(dtype) == jnp.float32 else 1e-200


@jax.custom_jvp
def safe_sqrt(x, floor):
    """sqrt(max(x, 0)) whose derivative stays finite at and below 0.

    The slope 1/(2√x) is evaluated at max(x, floor), so a tangent ray (x = 0 exactly)
    gets a large but finite slope. Callers pass a floor relative to the scale of x
    (e.g. (1e-4·r)² for a sphere's discriminant); `floor` itself is not differentiated.
    """
    return jnp.sqrt(jnp.maximum(x, 0))


@safe_sqrt.defjvp
def _safe_sqrt_jvp(primals, tangents):
    (x, floor), (dx, _) = primals, tangents
    return safe_sqrt(x, floor), dx * 0.5 / jnp.sqrt(jnp.maximum(x, floor))


def _sum_sq(v, axis: int, keepdims: bool):
    if axis == 0:  # written out: XLA's CPU reduction over a leading axis of 3 is slow
        sq = sum(v[k] * v[k] for k in range(v.shape[0]))
        return sq[None] if keepdims else sq
    return jnp.sum(v * v, axis=axis, keepdims=keepdims)


def norm(v, axis: int = 0, keepdims: bool = False):
    """Euclidean norm with a finite derivative at v = 0 (double-where)."""
    sq = _sum_sq(v, axis, keepdims)
    ok = sq > tiny(v.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1)), 0)


def normalize(v, axis: int = 0):
    """v/|v|; the zero vector maps to zero with a zero (not NaN) derivative."""
    sq = _sum_sq(v, axis, True)
    ok = sq > tiny(v.dtype)
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, sq, 1)), 0)


def safe_pow(x, beta):
    """max(x, 0)^β for β ≥ 1, with finite derivatives in x and β at x = 0."""
    pos = x > 0
    xs = jnp.where(pos, x, 1)
    return jnp.where(pos, jnp.exp(beta * jnp.log(xs)), 0)


def safe_div(a, b):
    """a/b where |b| > tiny, else 0 (and a zero derivative)."""
    ok = jnp.abs(b) > tiny(jnp.result_type(b))
    return jnp.where(ok, a / jnp.where(ok, b, 1), 0)


def dot(a, b):
    """Component-wise dot product of (3, ...) arrays."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
