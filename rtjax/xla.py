"""XLA settings for rtjax: a faster CPU code generator and a compilation cache.

Both are read when JAX starts its backend, so they apply to a process only if set
before its first JAX computation; the `rtjax` command sets both.
"""

from __future__ import annotations

import os

#: XLA's newer CPU fusion emitters, which run this renderer about half as fast and
#: compile it slower (docs/MEASUREMENTS.md); `tune_cpu` turns them off.
CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"


def tune_cpu() -> None:
    """Add `CPU_FLAG` to the environment's XLA_FLAGS unless they already say how to use
    the fusion emitters. Call it before any JAX computation (first thing in a script,
    a notebook, a test session); afterwards it has no effect on the running process."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " " + CPU_FLAG).strip()


def cache_dir() -> str | None:
    """Where the command keeps XLA's compiled programs between runs: `$RTJAX_CACHE`, or
    `$XDG_CACHE_HOME/rtjax/xla` (default `~/.cache/rtjax/xla`); `RTJAX_CACHE=off`: none.
    A fit compiles its solver steps; the next fit of a scene of the same structure and
    size loads them instead."""
    value = os.environ.get("RTJAX_CACHE")
    if value is not None:
        return None if value.strip().lower() in ("", "off", "0", "none") else value
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "rtjax", "xla")


#: Programs that take less than this to compile are not worth a cache entry (seconds).
CACHE_MIN_COMPILE_S = 0.5


def use_compilation_cache() -> None:
    """Keep compiled programs in `cache_dir()` (if any) for later processes."""
    path = cache_dir()
    if path is None:
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)
