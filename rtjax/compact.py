"""Wavefront compaction: the live entries of a batch of rays packed to the front of a
smaller buffer, traced there, and scattered back.

Most rays of a chain end after a segment or two, and the silhouette mode traces again
only a few pixels; packing the ones still wanted into a buffer of a fixed, smaller size
lets the rest of the program run on that buffer instead of the whole batch.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Int


class Packed(NamedTuple):
    """Where the entries of a mask went in a buffer of `size` slots, in order."""

    index: Int[Array, " k"]  # the entry each slot holds (0 in padding slots)
    valid: Bool[Array, " k"]  # which slots hold an entry
    target: Int[Array, " k"]  # where each slot goes back: its entry, or n (nowhere) for padding
    count: Int[Array, ""]  # how many entries the mask had (may exceed the slots)

    def gather(self, tree):
        """The slots' values of every (..., n) leaf of `tree`: (..., k)."""
        return jax.tree_util.tree_map(lambda a: a[..., self.index], tree)

    def renumbered(self, order) -> "Packed":
        """The same packing with each entry i renamed `order[i]` (a permutation of the n
        entries): for a mask taken in another order than the arrays scattered into."""
        index = order[self.index]
        return Packed(index, self.valid, jnp.where(self.valid, index, order.shape[0]), self.count)

    def scatter(self, into, values):
        """`into` with each valid slot of `values` written back to its entry; padding
        slots write nowhere (entry 0 may itself be a packed one)."""
        return jax.tree_util.tree_map(lambda a, b: a.at[..., self.target].set(b, mode="drop"), into, values)


def pack(mask: Bool[Array, " n"], size: int) -> Packed:
    """The first `size` true entries of `mask`, in order (entries past them are dropped).

    The optimisation barrier keeps XLA from constant-folding the packing where `mask`
    is known when compiling (an all-true mask), which makes compiles slow."""
    n = mask.shape[0]
    (index,) = jnp.nonzero(jax.lax.optimization_barrier(mask), size=size, fill_value=0)
    count = jnp.sum(mask)
    valid = jnp.arange(size) < count
    return Packed(index, valid, jnp.where(valid, index, n), count)
