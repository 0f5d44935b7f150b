"""Shared test setup: 64-bit JAX (float64 where a test asks; float32 stays the default
for scenes loaded from decks), the reference on the import path, and small helpers."""

from __future__ import annotations

import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = os.path.join(ROOT, "scenes")
sys.path.insert(0, HERE)

import pytest  # noqa: E402

import rtjax  # noqa: E402


def scene_from_text(text: str, size: int | None = None, index: int = 0) -> rtjax.Scene:
    """The `index`-th frame of deck text, optionally at another width (small tests)."""
    scene = rtjax.parse_deck(text).frames[index].scene
    return scene if size is None else scene.resized(size)


@pytest.fixture(scope="session")
def sample_deck_text() -> str:
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        return f.read()
