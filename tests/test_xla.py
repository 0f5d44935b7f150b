"""`rtjax.tune_cpu`'s memory settings (rtjax/xla.py): a program called again reuses the
pages of its temporaries instead of faulting fresh ones in, counted by the kernel's
minor page faults in a process of its own."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

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


def _faults(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", PROGRAM, mode], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


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
