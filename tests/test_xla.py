"""rtjax/xla.py: `rtjax.tune_cpu`'s memory settings (a program called again reuses the
pages of its temporaries instead of faulting fresh ones in, counted by the kernel's
minor page faults in a process of its own), and `rtjax.use_compilation_cache` (a later
process loads the compiled program instead of compiling it)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest
from conftest import ROOT

# A program with 128 MiB of temporaries (a loop's carry, which XLA cannot fuse away),
# called ten times; prints the minor page faults of each call.
PROGRAM = """
import json, resource, sys
import jax, jax.numpy as jnp
if sys.argv[1] == "tuned":
    import rtjax
    rtjax.tune_cpu()
def f(x):
    step = lambda i, y: jnp.roll(y, 1) * 0.5 + jnp.cos(y)
    return jnp.sum(jax.lax.fori_loop(0, 3, step, jnp.sin(x)))
x = jnp.linspace(0, 1, 1 << 24)
compiled = jax.jit(f).lower(x).compile()
faults = []
for _ in range(10):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    compiled(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({"faults": faults, "temp": compiled.memory_analysis().temp_size_in_bytes}))
"""


def _run(program: str, arg: str, timeout: int) -> dict:
    """`program` in a Python process of its own, from the repository's root: the JSON of
    its last line of output."""
    out = subprocess.run([sys.executable, "-c", program, arg], capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _faults(mode: str) -> dict:
    return _run(PROGRAM, mode, timeout=300)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the settings are glibc's")
def test_tune_cpu_reuses_temporaries():
    plain, tuned = _faults("plain"), _faults("tuned")
    pages = plain["temp"] / 4096
    # untuned, every call faults its temporaries in afresh (what the settings are for)
    assert all(f > 0.5 * pages for f in plain["faults"]), plain
    # tuned, the first calls grow the heap until it settles (one to three calls, more
    # on a loaded machine); most calls fault almost nothing in
    assert sum(f < 0.01 * pages for f in tuned["faults"]) >= 6, tuned


@pytest.mark.parametrize("error", [OSError, AttributeError, TypeError])
def test_without_glibc_nothing_is_changed(monkeypatch, error):
    """No C library handle (Windows: TypeError), or no glibc (macOS, musl: no such
    symbol): `reuse_freed_memory` changes nothing and says so."""
    import ctypes

    from rtjax import xla

    def refuse(*args, **kwargs):
        raise error("no C library here")

    monkeypatch.setattr(ctypes, "CDLL", refuse)
    assert xla.reuse_freed_memory() is False


# The gradient of the sample deck at 40 pixels wide (seconds to compile), in a process of
# its own that keeps compiled programs in the folder it is given.
CACHED = """
import json, sys
import rtjax
rtjax.tune_cpu()
folder = rtjax.use_compilation_cache(sys.argv[1])
import jax, jax.numpy as jnp
text = open("scenes/ex2s3.dat").read().replace("size 400", "size 40")
scene = rtjax.parse_deck(text).frames[0].scene
grad = jax.grad(lambda p: jnp.mean(rtjax.render(rtjax.Scene(scene.structure, p))))(scene.params)
print(json.dumps({"folder": folder, "grad": [float(v) for v in grad.centers.ravel()]}))
"""


def _cached_run(folder) -> dict:
    return _run(CACHED, str(folder), timeout=600)  # the folder given overrides the environment's RTJAX_CACHE=off (conftest)


@pytest.mark.slow
def test_a_later_process_loads_the_compiled_gradient(tmp_path):
    folder = tmp_path / "xla"
    first = _cached_run(folder)
    assert first["folder"] == str(folder)
    kept = sorted(os.listdir(folder))
    assert kept  # the gradient's program was written
    second = _cached_run(folder)
    assert sorted(os.listdir(folder)) == kept  # loaded, nothing compiled anew
    assert second["grad"] == first["grad"] and any(v != 0 for v in first["grad"])


def test_use_compilation_cache_keeps_nothing_when_switched_off(monkeypatch):
    from rtjax import xla

    monkeypatch.setenv("RTJAX_CACHE", "off")
    assert xla.use_compilation_cache() is None
