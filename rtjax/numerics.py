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


@jax.custom_jvp
def spread(s):
    """A per-ray scalar s (...) as a (3, ...) array, one copy per component: s·v for
    vectors v (3, ...) is `spread(s) * v`.

    The same values as broadcasting, but its tangent is a stack of three copies, so
    reverse mode sums the three rows of a cotangent elementwise where a broadcast's
    transpose is a reduction over an axis of 3, which XLA's CPU backend runs slowly."""
    return jnp.broadcast_to(s, (3,) + jnp.shape(s))


@spread.defjvp
def _spread_jvp(primals, tangents):
    (s,), (ds,) = primals, tangents
    return spread(s), jnp.stack([ds, ds, ds])


def components(v) -> list:
    """The rows v[0], v[1], ... of an array, taken by one `lax.split`: reverse mode
    stacks their cotangents back with one concatenation, where each v[k]'s transpose
    is a zero-padded copy of the whole array."""
    return [x.reshape(x.shape[1:]) for x in jax.lax.split(v, (1,) * v.shape[0], axis=0)]


def _sum_sq(v, axis: int, keepdims: bool):
    if axis == 0:  # written out: XLA's CPU reduction over a leading axis of 3 is slow
        sq = sum(x * x for x in components(v))
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
    (a0, a1, a2), (b0, b1, b2) = components(a), components(b)
    return a0 * b0 + a1 * b1 + a2 * b2


#: Tables of at most this many rows are read by `lookup` with a one-hot derivative;
#: larger ones (culled scenes) with a gather's.
LOOKUP_ONE_HOT_MAX = 32


@jax.custom_jvp
def lookup(table, idx):
    """table[idx]: per-sphere values (N,) at each ray's sphere index `idx` (P,), in 0..N−1.

    The value is the gather's; its derivative in `table` (N ≤ `LOOKUP_ONE_HOT_MAX`) is
    the one-hot product dtable · [idx = k], whose reverse mode is a matrix product too,
    where a gather's transpose is a scatter-add that XLA's CPU backend runs as a loop
    over the rays, one at a time (docs/MEASUREMENTS.md)."""
    return table[idx]


@lookup.defjvp
def _lookup_jvp(primals, tangents):
    (table, idx), (dt, _) = primals, tangents
    n = table.shape[0]
    if n == 0 or n > LOOKUP_ONE_HOT_MAX:
        return table[idx], dt[idx]
    onehot = (idx[None, :] == jnp.arange(n)[:, None]).astype(dt.dtype)  # (N, P)
    return table[idx], dt @ onehot


def take_rows(table, idx):
    """Rows `idx` (P,) of an (N, 3) table as a (3, P) array, one `lookup` per component.

    `table.T[:, idx]` gathers (P, 3) and transposes it; on XLA's CPU backend those
    transposes and their reverse-mode copies took 7–10 % of a gradient's time."""
    return jnp.stack([lookup(table[:, k], idx) for k in range(table.shape[1])])


#: The range of a colour channel (0..255): `clamp_colour`.
COLOUR_MAX = 255.0


def clamp(x, lo, hi):
    """x clamped to [lo, hi], its derivative 1 on the closed range and 0 beyond.

    A value often sits exactly at a bound, or a rounding error past it (a colour
    channel at 0 where a diffuse colour lacks it, a box's coverage at 1 where an edge
    just leaves it): `jnp.clip` halves the derivative at such a tie, and two programs
    of the same render (its jvp, its vjp) that round the value onto the bound or just
    inside it then disagree by a factor of 2. On the closed range the bound takes the
    inside's derivative, whatever rounding put it there."""
    return jnp.where((x >= lo) & (x <= hi), x, jnp.clip(x, lo, hi))


def clamp_colour(x):
    """x clamped to 0..`COLOUR_MAX` (`clamp`)."""
    return clamp(x, 0, COLOUR_MAX)
