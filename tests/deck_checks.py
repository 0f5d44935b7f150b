"""Checks on parsed decks shared by the deck tests and the fuzz tests."""

from __future__ import annotations

import jax
import numpy as np

from rtjax.deck import Deck


def assert_same_frames(a: Deck, b: Deck) -> None:
    """Identical frames: outputs, Structure (texture names too), and every parameter
    identical bit for bit (dtype, shape and bytes)."""
    assert len(a.frames) == len(b.frames)
    for fa, fb in zip(a.frames, b.frames):
        assert fa.output == fb.output
        sa, sb = fa.scene.structure, fb.scene.structure
        assert sa == sb and sa.texture_files == sb.texture_files
        la, ta = jax.tree_util.tree_flatten(fa.scene.params)
        lb, tb = jax.tree_util.tree_flatten(fb.scene.params)
        assert ta == tb
        for x, y in zip(la, lb):
            x, y = np.asarray(x), np.asarray(y)
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
