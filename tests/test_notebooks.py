"""The notebooks (notebooks/*.ipynb) run top to bottom from a fresh kernel.

Each is executed with nbclient in the reduced mode (RTJAX_NOTEBOOK_QUICK=1: small
images, few iterations, every cell still runs) by scripts/make_notebooks.py in a
subprocess of its own. The runs are background jobs (conftest.py): they start one after
another as soon as the session has collected a test that needs them, so in a run of
the whole suite they use a core the tests before them leave idle; the first test that
needs them starts every run not begun yet at once (side by side: run alone, this file
costs about as long as the slowest notebook). Checked: no cell errored, every notebook
shows images, the fitting notebook's printed errors are small; and each committed
notebook holds exactly the cells of its jupytext source (notebooks/NAME.py) with the
outputs of a full run.
"""

from __future__ import annotations

import atexit
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import jupytext
import nbformat
import pytest
from conftest import ROOT, Job, kill_group

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
NAMES = list(GEN.NAMES)
LONGEST_FIRST = ["02_fit.ipynb", "03_tradeoff.ipynb", "01_render.ipynb"]  # by their quick runs' length
assert sorted(LONGEST_FIRST) == sorted(NAMES)

BACKGROUND_FOR = "executed"  # conftest.py: the runs start once a test that needs them is collected
_JOBS: dict[str, Job] = {}
_CACHE: list[str] = []


def _cache() -> str:
    """One persistent compilation cache for the three runs (see make_notebooks.QUICK_COMPILES)."""
    if not _CACHE:
        _CACHE.append(tempfile.mkdtemp(prefix="rtjax_notebooks_jax_cache_"))
        atexit.register(shutil.rmtree, _CACHE[0], True)
    return _CACHE[0]


def _quick_run(name: str):
    """The job: notebooks/NAME as committed, outputs cleared, executed in quick mode →
    (executed notebook or None, the run's log, seconds it ran)."""

    def run(job: Job):
        out = tempfile.mkdtemp(prefix="rtjax_notebooks_")
        try:
            env = dict(os.environ, RTJAX_NOTEBOOK_QUICK="1", JAX_COMPILATION_CACHE_DIR=_cache())
            cmd = [sys.executable, SCRIPT, "--committed", "--quick", "--out", out, "--timeout", str(CELL_TIMEOUT), name]
            t0 = time.perf_counter()
            with open(os.path.join(out, "log"), "w") as log:
                proc = job.popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
                try:
                    proc.wait(timeout=RUN_TIMEOUT)
                except subprocess.TimeoutExpired:
                    kill_group(proc)
            with open(os.path.join(out, "log")) as log:
                text = log.read() + ("" if proc.returncode is not None and proc.returncode >= 0 else "\n(killed or timed out)")
            path = os.path.join(out, name)
            nb = nbformat.read(path, as_version=4) if proc.returncode == 0 and os.path.exists(path) else None
            return nb, text, time.perf_counter() - t0
        finally:
            shutil.rmtree(out, ignore_errors=True)

    return run


def background_jobs() -> list[Job]:
    if not _JOBS:
        _JOBS.update((name, Job(f"notebook {name}", _quick_run(name))) for name in LONGEST_FIRST)
    return list(_JOBS.values())


@pytest.fixture(scope="module")
def executed() -> dict[str, tuple[nbformat.NotebookNode | None, str, float]]:
    """name → (executed notebook or None, the run's log, seconds it ran)."""
    jobs = background_jobs()
    for job in jobs:  # those not begun yet start now, side by side
        job.begin()
    yield {name: job.result() for name, job in _JOBS.items()}
    for job in jobs:
        job.stop()


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
def test_committed_notebook_is_its_source_with_full_outputs(name):
    """notebooks/NAME holds exactly the cells of its jupytext source notebooks/NAME.py,
    every code cell executed in order, no errors, images shown, and not in quick mode."""
    committed = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4)
    source = jupytext.read(GEN.source(name))
    assert [(c.cell_type, c.source) for c in committed.cells] == [(c.cell_type, c.source) for c in source.cells], (
        f"notebooks/{name} differs from {os.path.relpath(GEN.source(name), ROOT)}: run "
        f"`python scripts/make_notebooks.py {name[:2]}` (or `jupytext --sync` if only markdown changed)")
    counts = [c.get("execution_count") for c in committed.cells if c.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1)), f"not one run top to bottom: {counts}"
    assert not _errors(committed), _errors(committed)
    assert _images(committed) >= 1
    assert "quick mode: False" in _text(committed)
