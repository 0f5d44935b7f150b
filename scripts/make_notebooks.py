"""Run the worked-example notebooks in notebooks/:

* 01_render: a forward tour (decks, every level, re-rendering without a recompile,
  the Sun raster round trip, a texture),
* 02_fit: fitting (centres, then colours and ke, from a known truth; a photo-like
  target with a robust loss and nuisance parameters),
* 03_tradeoff: the speed/accuracy study of the sample deck (rtjax.bench) and a tour
  of the numerical extremes with gradient maps.

Each notebook's source is a jupytext percent file, notebooks/NAME.py, paired with
notebooks/NAME.ipynb (notebooks/jupytext.toml), which holds the outputs of a full run.
This script builds each .ipynb from its .py, executes it from a fresh kernel with
nbclient (kernel `python3`, in notebooks/) and saves it with its outputs:

    python scripts/make_notebooks.py                  # run all in full mode, save with outputs
    python scripts/make_notebooks.py --quick 01       # run one in reduced mode (outputs not saved)
    python scripts/make_notebooks.py --committed --quick --out OUT   # the committed .ipynb files

Edits to markdown cells alone need no run: `jupytext --sync notebooks/NAME.py` rewrites
the .ipynb's cells and keeps the outputs of the code cells it leaves unchanged.

Reduced mode (the test suite, tests/test_notebooks.py): the environment variable
RTJAX_NOTEBOOK_QUICK=1 makes every notebook use small images and few iterations; every
cell still runs. `execute(..., quick=True)` also gives the kernel cheaper compiles
(QUICK_COMPILES).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import jupytext
import nbformat

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOKS = os.path.join(ROOT, "notebooks")
NAMES = ("01_render.ipynb", "02_fit.ipynb", "03_tradeoff.ipynb")
QUICK_ENV = "RTJAX_NOTEBOOK_QUICK"

#: Quick mode's compile-time savers, for the kernel's environment (the notebooks' results
#: do not depend on them): XLA's cheaper backend optimisation (faster compiles, slower
#: runs: right for small images), and JAX's persistent compilation cache (fits with the
#: same free parameters, loss and constants compile once; a folder shared by the notebooks
#: of one run when JAX_COMPILATION_CACHE_DIR is set, else a new one).
QUICK_COMPILES = {"XLA_FLAGS": "--xla_backend_optimization_level=0"}


def source(name: str) -> str:
    """The jupytext source of notebooks/NAME (NAME.ipynb → notebooks/NAME.py)."""
    return os.path.join(NOTEBOOKS, os.path.splitext(name)[0] + ".py")


def build(name: str) -> nbformat.NotebookNode:
    """The notebook `name` built from its jupytext source, without outputs
    (deterministic cell ids, so diffs stay small)."""
    nb = jupytext.read(source(name))
    nb.metadata = nbformat.from_dict({
        "kernelspec": {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"},
        "language_info": {"name": "python"},
    })
    stem = name.split("_")[0]
    for i, cell in enumerate(nb.cells):
        cell["id"] = f"nb{stem}-{i:02d}"
    nbformat.validate(nb)
    return nb


def kernel_env(quick: bool, cache: str) -> dict[str, str]:
    """The kernel's environment: this process's, with RTJAX_NOTEBOOK_QUICK=1 and
    QUICK_COMPILES in quick mode (and JAX's compilation cache in the folder `cache`
    unless the environment names one), without RTJAX_NOTEBOOK_QUICK otherwise."""
    env = {k: v for k, v in os.environ.items() if k != QUICK_ENV}
    if quick:
        env[QUICK_ENV] = "1"
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + QUICK_COMPILES["XLA_FLAGS"]).strip()
        if not env.get("JAX_COMPILATION_CACHE_DIR"):
            env["JAX_COMPILATION_CACHE_DIR"] = cache
    return env


def execute(nb: nbformat.NotebookNode, *, quick: bool, timeout: int = 900, record_timing: bool = False) -> float:
    """Run `nb` in place from a fresh `python3` kernel (cwd: the notebooks folder);
    returns seconds."""
    from nbclient import NotebookClient

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="rtjax_nb_jax_cache_") as cache:
        NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": NOTEBOOKS}},
                       record_timing=record_timing).execute(env=kernel_env(quick, cache))
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="notebooks to make (prefixes such as 01; default: all)")
    ap.add_argument("--quick", action="store_true", help="execute in reduced mode and save nothing")
    ap.add_argument("--out", help="save the executed notebooks in this folder instead (quick mode too)")
    ap.add_argument("--committed", action="store_true",
                    help="execute notebooks/NAME.ipynb as committed (outputs cleared) instead of building it from NAME.py")
    ap.add_argument("--timeout", type=int, default=900, help="seconds per cell (default 900)")
    args = ap.parse_args(argv)
    names = [n for n in NAMES if not args.names or any(n.startswith(p) for p in args.names)]
    for name in names:
        if args.committed:
            nb = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4)
            for cell in nb.cells:
                if cell.cell_type == "code":
                    cell.outputs, cell.execution_count = [], None
        else:
            nb = build(name)
        seconds = execute(nb, quick=args.quick, timeout=args.timeout, record_timing=bool(args.out))
        print(f"{name}: ran in {seconds:.1f} s ({'quick' if args.quick else 'full'} mode)", flush=True)
        if args.out:
            os.makedirs(args.out, exist_ok=True)
            nbformat.write(nb, os.path.join(args.out, name))
            print(f"wrote {os.path.join(args.out, name)}", flush=True)
        elif not args.quick:
            nbformat.write(nb, os.path.join(NOTEBOOKS, name))
            print(f"wrote notebooks/{name}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
