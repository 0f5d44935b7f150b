"""Shared test setup: 64-bit JAX (float64 where a test asks; float32 stays the default
for scenes loaded from decks), tests/ on the import path, and small helpers."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)
jax.config.update("jax_enable_x64", True)
# the command's compilation cache (rtjax.xla.cache_dir) stays off in tests, subprocesses
# included; tests/test_cli.py turns it on where it checks it
os.environ.setdefault("RTJAX_CACHE", "off")

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = os.path.join(ROOT, "scenes")
sys.path.insert(0, HERE)

import pytest  # noqa: E402


@contextlib.contextmanager
def quick_xla(clear: bool = False, quick: bool = True):
    """Compile what runs inside with `jax_disable_most_optimizations` (`quick=False`:
    without, inside a module that runs under it): for checks of
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
    jax.config.update("jax_disable_most_optimizations", quick)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)
        if clear:
            jax.clear_caches()


def linearised(f, p, tangent, cotangent):
    """f(p), J·t and Jᵀ·c from one linearisation (the JVP rules' tangent equations, then
    their transpose: what `jax.vjp` does), so that one program holds both modes rather
    than two programs each tracing the render."""
    out, linear = jax.linearize(f, p)
    return out, linear(tangent), jax.linear_transpose(linear, p)(cotangent)[0]


@pytest.fixture(scope="module")
def quick_build():
    """`quick_xla` over a whole test module, its caches cleared after it: for modules of
    fits and tolerance checks whose cost is compiling (opt in with
    `pytestmark = pytest.mark.usefixtures("quick_build")`)."""
    with quick_xla(clear=True):
        yield


def quick_env() -> dict[str, str]:
    """The environment for a subprocess (an `rtjax` command) whose checks are exit
    codes, outputs, plumbing or tolerances: `quick_xla`'s build in that process (JAX
    reads JAX_DISABLE_MOST_OPTIMIZATIONS at start-up)."""
    return dict(os.environ, JAX_DISABLE_MOST_OPTIMIZATIONS="1")


# -- background work: subprocesses that some tests wait for ------------------------------
#
# XLA compiles on one core and the suite runs one test after another, so on a machine
# with two cores one is mostly idle. A few tests wait for slow subprocesses (the
# notebooks' quick runs, the 4-device multi-start fit); those are `Job`s, run one after
# another in a background thread from the moment collection ends, so that they are
# usually done before the tests that need them are reached. A test module offers jobs
# with `background_jobs()` (the same Job objects on every call) and names the fixture
# that waits for them in BACKGROUND_FOR: nothing starts unless a selected test uses that
# fixture. A test that needs a job not begun yet runs it at once (`Job.result`). Jobs
# run at the tests' own priority: a niced job starves on a machine that is busy anyway.


class Job:
    """Work done in a thread, usually in the background: `run(job)` starts its
    subprocesses with `job.popen` (so that `stop` can end them) and returns a result."""

    def __init__(self, name: str, run):
        self.name, self._run = name, run
        self._lock = threading.Lock()
        self._begun = self._stopped = False
        self._done = threading.Event()
        self._procs: list[subprocess.Popen] = []
        self._result = self._error = None

    def _claim(self) -> bool:
        with self._lock:
            begun, self._begun = self._begun, True
            return not begun

    def _body(self):
        try:
            self._result = self._run(self)
        except BaseException as e:  # handed to whoever waits
            self._error = e
        finally:
            self._done.set()

    def run_here(self):
        """Run it in this thread unless it has begun (the background chain)."""
        if self._claim():
            self._body()

    def begin(self):
        """Start it in a thread of its own unless it has begun."""
        if self._claim():
            threading.Thread(target=self._body, name=self.name, daemon=True).start()

    def result(self):
        """Its result, once done (started now if it had not begun)."""
        self.begin()
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._result

    def popen(self, cmd, **kw) -> subprocess.Popen:
        """A subprocess of this job, in a process group of its own (so `stop` ends its
        children too, a notebook's kernel say)."""
        with self._lock:
            if self._stopped:
                raise RuntimeError(f"{self.name}: stopped")
            proc = subprocess.Popen(cmd, start_new_session=True, **kw)
            self._procs.append(proc)
            return proc

    def stop(self):
        """End its subprocesses still running; a job not begun never starts."""
        with self._lock:
            never = not self._begun
            self._stopped = self._begun = True
            procs = list(self._procs)
        for proc in procs:
            kill_group(proc)
        if never:
            self._error = RuntimeError(f"{self.name}: stopped before it began")
            self._done.set()


def kill_group(proc: subprocess.Popen):
    """SIGKILL a subprocess started by `Job.popen` and its children; reap it."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()


_JOBS: list[Job] = []


def background_modules(items) -> list:
    """The test modules, in order, of which a selected test (among `items`) uses the
    fixture that waits for their background jobs (`BACKGROUND_FOR`)."""
    modules = []
    for item in items:
        module = getattr(item, "module", None)
        if module not in modules and getattr(module, "BACKGROUND_FOR", None) in getattr(item, "fixturenames", ()):
            modules.append(module)
    return modules


def pytest_collection_finish(session):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # several workers: each job starts when a test of the worker that runs it needs it
    for module in background_modules(session.items):
        _JOBS.extend(module.background_jobs())
    if _JOBS:
        jobs = list(_JOBS)
        threading.Thread(target=lambda: [job.run_here() for job in jobs], name="background jobs", daemon=True).start()


def pytest_sessionfinish(session):
    while _JOBS:
        _JOBS.pop().stop()


def scene_from_text(text: str, size: int | None = None, index: int = 0) -> rtjax.Scene:
    """The `index`-th frame of deck text, optionally at another width (small tests)."""
    scene = rtjax.parse_deck(text).frames[index].scene
    return scene if size is None else scene.resized(size)


#: The fitting tests' known truth (tests/test_fit.py, tests/test_multistart.py): two
#: opaque spheres under one light; `truth_deck` adds the image width and the rend line.
TRUTH_SCENE = """
sphe -9 0 0 8
opaq 0.9 0.3 0.2 0.4 12
sphe 9 4 2 7
opaq 0.2 0.6 0.9 0.3 8
plig 0.4 -1 0.8 220 210 200
elig 0.25
back 10 20 60
eyep 0 -50 10
refp 0 0 0
vang 60 45
"""


def truth_deck(width: int = 64) -> str:
    return TRUTH_SCENE + f"size {width}\nrend truth.sunimg\n"


@pytest.fixture(scope="module")
def truth(request) -> rtjax.Scene:
    """The fitting truth (`TRUTH_SCENE`) at the image width the test module sets as
    TRUTH_WIDTH (default 64)."""
    return scene_from_text(truth_deck(getattr(request.module, "TRUTH_WIDTH", 64)))


@pytest.fixture(scope="session")
def sample_deck_text() -> str:
    with open(os.path.join(SCENES, "ex2s3.dat")) as f:
        return f.read()


def first_hits(s: rtjax.Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's ray through its centre (the renderer's camera, NumPy from there):
    the sphere it meets first (H, W; −1 for none), the hit point (H, W, 3) and that
    sphere's outward normal there, in float64."""
    p = s.params
    _, d = rtjax.camera.primary_rays(p.eye, p.refp, p.vang, s.structure.width, s.structure.height, jnp.array([0.5, 0.5]))
    eye, dirs = np.asarray(p.eye, np.float64), np.asarray(d, np.float64).T  # (P, 3)
    centers, radii = np.asarray(p.centers, np.float64), np.asarray(p.radii, np.float64)
    oc = eye - centers  # (N, 3)
    b = dirs @ oc.T  # (P, N)
    disc = b * b - np.sum(oc * oc, 1) + radii**2
    t = -b - np.sqrt(np.maximum(disc, 0))
    t = np.where((disc > 0) & (t > 0), t, np.inf)
    index = np.where(np.isfinite(t.min(1)), t.argmin(1), -1)
    point = eye + t.min(1)[:, None] * dirs
    normal = (point - centers[np.maximum(index, 0)]) / radii[np.maximum(index, 0)][:, None]
    shape = (s.structure.height, s.structure.width)
    return index.reshape(shape), point.reshape(*shape, 3), normal.reshape(*shape, 3)

