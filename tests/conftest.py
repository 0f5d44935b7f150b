"""Shared test setup: 64-bit JAX (float64 where a test asks; float32 stays the default
for scenes loaded from decks), the reference on the import path, and small helpers."""

from __future__ import annotations

import contextlib
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


@contextlib.contextmanager
def quick_xla(clear: bool = False):
    """Compile what runs inside with `jax_disable_most_optimizations`: for checks of
    finiteness, tolerances or plumbing whose cost is XLA compile time (a jvp and a vjp
    of the silhouette-aware render take XLA tens of seconds per dtype), not for checks
    of bit-for-bit equality nor for timings.

    What the flag changes: XLA's *backend* optimisation (LLVM -O0, no expensive LLVM
    passes), which halves those compile times. The JAX program, its jvp and vjp, and
    even XLA's optimised HLO are the same (checked: identical `compiled.as_text()` for a
    glass-and-opaque scene's jvp and grad, JAX 0.10.2 on x86), every guard (`where`,
    safe square roots, clamps) included; what differs is the machine code's rounding
    (instruction selection, fused multiply-adds). Measured on every check of
    tests/test_extremes.py, the outputs differ from the optimised build's by ~1e-6
    relative in float32 and ~1e-14 in float64 (more only at singular points, such as
    1/√disc at an exactly tangent ray, where both builds are finite). The optimised
    build's rounding already differs between CPUs (vector width, FMA), and a scene
    meets a singular point only to rounding (a radius or light direction computed in
    float), so no test here pinned which side of a singularity a ray lands on: the
    checks are that the program's guards hold on either side, which this build checks
    as well.

    The flag is not part of JAX's compile cache keys, so an executable compiled inside
    would be reused outside for the same function and arguments: use it around
    functions called nowhere else, or with `clear=True` (JAX's caches cleared on exit).
    """
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)
        if clear:
            jax.clear_caches()


# -- background work: subprocesses that some tests wait for ------------------------------
#
# A test module may define `start_background()` (start its slow subprocesses; called at
# most once), `stop_background()` (end what is left, at the end of the session) and
# BACKGROUND_FOR, the name of the fixture that waits for them. When a selected test uses
# that fixture, the work starts as soon as collection ends, at a low priority (nice), so
# that it runs on an otherwise idle core while the tests before it run (XLA compiles on
# one core; the suite runs test after test). Nothing starts for tests not selected.

_STARTED: list = []


def pytest_collection_finish(session):
    for item in session.items:
        module = getattr(item, "module", None)
        start = getattr(module, "start_background", None)
        if start is None or module in _STARTED or getattr(module, "BACKGROUND_FOR", None) not in item.fixturenames:
            continue
        _STARTED.append(module)
        start()


def pytest_sessionfinish(session):
    while _STARTED:
        _STARTED.pop().stop_background()


def nice_subprocess() -> None:
    """`preexec_fn` for background subprocesses: below the tests' own priority."""
    os.nice(10)


def scene_from_text(text: str, size: int | None = None, index: int = 0) -> rtjax.Scene:
    """The `index`-th frame of deck text, optionally at another width (small tests)."""
    scene = rtjax.parse_deck(text).frames[index].scene
    return scene if size is None else scene.resized(size)


@pytest.fixture(scope="session")
def sample_deck_text() -> str:
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        return f.read()
