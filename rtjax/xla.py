"""XLA settings for rtjax: faster CPU code generation and a compilation cache.

Both are read when JAX starts its backend, so they apply to a process only if set
before its first JAX computation; the `rtjax` command sets both.
"""

from __future__ import annotations

import os

#: XLA CPU settings that `tune_cpu` adds, by flag name (checked on jaxlib 0.10.2):
#: - the newer CPU fusion emitters off: they run this renderer about half as fast and
#:   compile it slower;
#: - no YNNPACK fusions: reverse mode's sums over a (3, P) array's leading axis (the
#:   transposes of broadcasting a per-ray value to three components) ran as YNNPACK
#:   reductions at several times a loop fusion's cost, 7–9 % of a gradient's thread time
#:   (docs/MEASUREMENTS.md).
CPU_FLAGS = {"xla_cpu_use_fusion_emitters": "false", "xla_cpu_experimental_ynn_fusion_type": ""}


def tune_cpu() -> None:
    """Add `CPU_FLAGS` to the environment's XLA_FLAGS, each unless they already set that
    flag. Call it before any JAX computation (first thing in a script, a notebook, a test
    session); afterwards it has no effect on the running process."""
    flags = os.environ.get("XLA_FLAGS", "")
    extra = [f"--{name}={value}" for name, value in CPU_FLAGS.items() if name not in flags]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()


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
