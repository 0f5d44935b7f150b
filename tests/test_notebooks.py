"""The notebooks (notebooks/*.ipynb) run top to bottom from a fresh kernel.

Each is executed with nbclient in the reduced mode (RTJAX_NOTEBOOK_QUICK=1: small
images, few iterations, every cell still runs) by scripts/make_notebooks.py in a
subprocess of its own. The runs start in the background as soon as the session has
collected a test that needs them (conftest.py's background work), one after another at
a low priority, so in a whole-suite run they use a core the tests before them leave
idle; when the first such test is reached, every run not started yet starts at once
(side by side, as the whole used to: run alone this file costs about as long as the
slowest). Checked: no cell errored, every notebook shows images, the fitting
notebook's printed errors are small; and the committed notebooks are the generator's
cells with the outputs of a full run.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import nbformat
import pytest
from conftest import ROOT, nice_subprocess

SCRIPT = os.path.join(ROOT, "scripts", "make_notebooks.py")
NOTEBOOKS = os.path.join(ROOT, "notebooks")
CELL_TIMEOUT = 300  # seconds per cell (quick mode needs a few tens at most)
RUN_TIMEOUT = 900  # seconds per notebook


def _generator():
    spec = importlib.util.spec_from_file_location("make_notebooks", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GEN = _generator()
NAMES = list(GEN.BUILDERS)
LONGEST_FIRST = ["02_fit.ipynb", "03_tradeoff.ipynb", "01_render.ipynb"]  # quick mode: ~36, 17, 9 s alone
assert sorted(LONGEST_FIRST) == sorted(NAMES)


class QuickRuns:
    """Every committed notebook, outputs cleared and executed in quick mode, each by a
    subprocess of its own: one after another in a background thread; `hurry` starts
    the rest at once. Results: name → (executed notebook or None, the run's log,
    seconds it ran)."""

    def __init__(self):
        self.out = tempfile.mkdtemp(prefix="rtjax_notebooks_")
        # one persistent compilation cache for the three runs (see make_notebooks.QUICK_COMPILES)
        self.env = dict(os.environ, RTJAX_NOTEBOOK_QUICK="1", JAX_COMPILATION_CACHE_DIR=os.path.join(self.out, "jax_cache"))
        self.lock = threading.Lock()
        self.pending = list(LONGEST_FIRST)
        self.procs: dict[str, subprocess.Popen] = {}
        self.done = {name: threading.Event() for name in NAMES}
        self.results: dict[str, tuple[nbformat.NotebookNode | None, str, float]] = {}
        self.stopped = False
        threading.Thread(target=self._chain, daemon=True).start()

    def _take(self, every: bool = False) -> list[str]:
        with self.lock:
            names = self.pending if every else self.pending[:1]
            self.pending = self.pending[len(names):]
            return names

    def _chain(self):
        while names := self._take():
            self._run(names[0])

    def _run(self, name: str):
        log_path = os.path.join(self.out, name + ".log")
        cmd = [sys.executable, SCRIPT, "--committed", "--quick", "--out", self.out, "--timeout", str(CELL_TIMEOUT), name]
        t0 = time.perf_counter()
        with open(log_path, "w") as log:
            with self.lock:  # not after `stop`
                proc = None if self.stopped else subprocess.Popen(
                    cmd, cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT, text=True,
                    preexec_fn=nice_subprocess, start_new_session=True)  # its own group: the kernel goes with it
                if proc is not None:
                    self.procs[name] = proc
            try:
                code = -1 if proc is None else proc.wait(timeout=RUN_TIMEOUT)
            except subprocess.TimeoutExpired:
                _kill(proc)
                code = -1
        with open(log_path) as f:
            text = f.read() + ("" if code != -1 or proc is None else "\n(timed out)")
        path = os.path.join(self.out, name)
        nb = nbformat.read(path, as_version=4) if code == 0 and os.path.exists(path) else None
        self.results[name] = (nb, text, time.perf_counter() - t0)
        self.done[name].set()

    def hurry(self):
        """Start every run not started yet, side by side."""
        for name in self._take(every=True):
            threading.Thread(target=self._run, args=(name,), daemon=True).start()

    def wait(self) -> dict[str, tuple[nbformat.NotebookNode | None, str, float]]:
        self.hurry()
        for name in NAMES:
            self.done[name].wait()
        return self.results

    def stop(self):
        with self.lock:
            self.stopped, self.pending = True, []
            procs = list(self.procs.values())
        for proc in procs:
            _kill(proc)
        shutil.rmtree(self.out, ignore_errors=True)


def _kill(proc: subprocess.Popen):
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


BACKGROUND_FOR = "executed"  # conftest.py: start the runs once a test that needs them is collected
_RUNS: list[QuickRuns] = []


def start_background() -> QuickRuns:
    if not _RUNS:
        _RUNS.append(QuickRuns())
    return _RUNS[0]


def stop_background():
    while _RUNS:
        _RUNS.pop().stop()


@pytest.fixture(scope="module")
def executed() -> dict[str, tuple[nbformat.NotebookNode | None, str, float]]:
    """name → (executed notebook or None, the run's log, seconds it ran)."""
    yield start_background().wait()
    stop_background()


def _errors(nb) -> list[str]:
    return [f"cell {i}: {o.get('ename')}: {o.get('evalue')}" for i, c in enumerate(nb.cells) if c.cell_type == "code"
            for o in c.get("outputs", []) if o.get("output_type") == "error"]


def _images(nb) -> int:
    return sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))


def _text(nb) -> str:
    return "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
                   if o.get("output_type") == "stream")


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_from_a_fresh_kernel(executed, name):
    nb, log, seconds = executed[name]
    assert nb is not None, f"{name} did not run through:\n{log[-4000:]}"
    assert not _errors(nb), _errors(nb)
    unexecuted = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and c.get("execution_count") is None]
    assert not unexecuted, f"cells not executed: {unexecuted}"
    assert _images(nb) >= 1, f"{name} shows no image"
    print(f"{name}: ran in {seconds:.0f} s (quick mode, in the background)")


@pytest.mark.slow
def test_fit_notebook_recovers_the_truth(executed):
    nb, log, _ = executed["02_fit.ipynb"]
    assert nb is not None, log[-4000:]
    text = _text(nb)
    centres = float(re.search(r"FIT centres: max centre error ([0-9.]+) units", text).group(1))
    colours = float(re.search(r"FIT colours: max colour or ke error ([0-9.]+)", text).group(1))
    photo = float(re.search(r"FIT photo: smallest largest error ([0-9.]+)", text).group(1))
    print("\n".join(line for line in text.splitlines() if line.startswith("FIT")))
    # quick mode: 64 pixels wide and a few iterations; the start is off by up to 2.5 units
    assert centres < 1.0, text
    assert colours < 0.15, text
    assert photo < 0.25, text


@pytest.mark.parametrize("name", NAMES)
def test_committed_notebook_is_the_generators_with_full_outputs(name):
    """notebooks/NAME holds exactly the cells scripts/make_notebooks.py writes, every
    code cell executed in order, no errors, images shown, and not in quick mode."""
    committed = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4)
    built = GEN.build(name)
    assert [(c.cell_type, c.source) for c in committed.cells] == [(c.cell_type, c.source) for c in built.cells], (
        f"notebooks/{name} differs from scripts/make_notebooks.py: run `python scripts/make_notebooks.py {name[:2]}`")
    counts = [c.get("execution_count") for c in committed.cells if c.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1)), f"not one run top to bottom: {counts}"
    assert not _errors(committed), _errors(committed)
    assert _images(committed) >= 1
    assert "quick mode: False" in _text(committed)
