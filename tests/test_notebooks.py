"""The notebooks (notebooks/*.ipynb) run top to bottom from a fresh kernel.

Each is executed with nbclient in the reduced mode (RTJAX_NOTEBOOK_QUICK=1: small
images, few iterations, every cell still runs) by scripts/make_notebooks.py in a
subprocess of its own; the three run side by side, so the whole costs about as long as
the slowest. Checked: no cell errored, every notebook shows images, the fitting
notebook's printed errors are small; and the committed notebooks are the generator's
cells with the outputs of a full run.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import time

import nbformat
import pytest
from conftest import ROOT

SCRIPT = os.path.join(ROOT, "scripts", "make_notebooks.py")
NOTEBOOKS = os.path.join(ROOT, "notebooks")
CELL_TIMEOUT = 300  # seconds per cell (quick mode needs a few tens at most)
TOTAL_TIMEOUT = 900


def _generator():
    spec = importlib.util.spec_from_file_location("make_notebooks", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GEN = _generator()
NAMES = list(GEN.BUILDERS)


@pytest.fixture(scope="module")
def executed(tmp_path_factory) -> dict[str, tuple[nbformat.NotebookNode | None, str, float]]:
    """Every committed notebook, outputs cleared and executed in quick mode: name →
    (executed notebook or None, the run's log, seconds). All three at once."""
    out = tmp_path_factory.mktemp("notebooks")
    # one persistent compilation cache for the three runs (see make_notebooks.QUICK_COMPILES)
    env = dict(os.environ, RTJAX_NOTEBOOK_QUICK="1", JAX_COMPILATION_CACHE_DIR=str(tmp_path_factory.mktemp("jax_cache")))
    procs = {}
    t0 = time.perf_counter()
    for name in NAMES:
        cmd = [sys.executable, SCRIPT, "--committed", "--quick", "--out", str(out), "--timeout", str(CELL_TIMEOUT), name]
        procs[name] = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    results = {}
    for name, proc in procs.items():
        try:
            log, _ = proc.communicate(timeout=max(1.0, TOTAL_TIMEOUT - (time.perf_counter() - t0)))
        except subprocess.TimeoutExpired:
            proc.kill()
            log = proc.communicate()[0] + "\n(timed out)"
        path = out / name
        nb = nbformat.read(str(path), as_version=4) if proc.returncode == 0 and path.exists() else None
        results[name] = (nb, log, time.perf_counter() - t0)
    return results


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
    print(f"{name}: done {seconds:.0f} s after the start (quick mode, three side by side)")


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
