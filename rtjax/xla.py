"""CPU settings for rtjax (XLA's code generation, the C library's reuse of freed memory)
and XLA's compilation cache.

XLA reads its settings when JAX starts its backend, so they apply to a process only if
set before its first JAX computation; the `rtjax` command sets them all.
"""

from __future__ import annotations

import ctypes
import os

#: XLA CPU settings that `tune_cpu` adds, by flag name (checked on jaxlib 0.10.2):
#: - the newer CPU fusion emitters off: they run this renderer about half as fast and
#:   compile it slower;
#: - no YNNPACK fusions: reverse mode's sums over a (3, P) array's leading axis (the
#:   transposes of broadcasting a per-ray value to three components) ran as YNNPACK
#:   reductions at several times a loop fusion's cost, 7–9 % of a gradient's thread time
#:   (docs/MEASUREMENTS.md).
CPU_FLAGS = {"xla_cpu_use_fusion_emitters": "false", "xla_cpu_experimental_ynn_fusion_type": ""}


#: glibc `mallopt` settings that `tune_cpu` makes, by name: (parameter number in
#: <malloc.h>, value). XLA:CPU allocates a program's temporaries afresh at each call,
#: and glibc serves a block over 32 MiB (a gradient's, at a few hundred pixels square)
#: with a fresh `mmap`, unmapped when freed, so each call faulted its temporaries in
#: page by page, a quarter of the gradient's time (docs/MEASUREMENTS.md). With no
#: `mmap` (`M_MMAP_MAX` 0) and up to `M_TRIM_THRESHOLD` bytes of freed memory kept, the
#: next call reuses the same pages. That holds in the main thread's heap only (other
#: threads' heaps cap a block at 64 MiB), hence `tune_cpu`'s synchronous dispatch; one
#: heap for all threads (`M_ARENA_MAX` 1) would do too, but slows XLA's compiles.
MALLOC_OPTIONS = {"M_TRIM_THRESHOLD": (-1, 1 << 30), "M_MMAP_MAX": (-4, 0)}


def tune_cpu() -> None:
    """Settings for rendering on CPUs: add `CPU_FLAGS` to the environment's XLA_FLAGS
    (each unless they already set that flag), run computations synchronously (in the
    calling thread, so that their temporaries come from its heap), and make
    `MALLOC_OPTIONS` where the C library is glibc. Call it before any JAX computation
    (first thing in a script, a notebook, a test session); afterwards the first two
    have no effect on the running process."""
    flags = os.environ.get("XLA_FLAGS", "")
    extra = [f"--{name}={value}" for name, value in CPU_FLAGS.items() if name not in flags]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", False)
    reuse_freed_memory()


def reuse_freed_memory() -> bool:
    """Make `MALLOC_OPTIONS` (glibc only: elsewhere nothing is changed). Returns whether
    all of them were accepted."""
    try:
        libc = ctypes.CDLL(None)  # the process's own C library
        mallopt, _ = libc.mallopt, libc.gnu_get_libc_version  # glibc's (musl's mallopt does nothing)
    except (OSError, AttributeError, TypeError):  # TypeError: Windows has no CDLL(None)
        return False
    return all(mallopt(code, value) == 1 for code, value in MALLOC_OPTIONS.values())


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


def use_compilation_cache(path: str | os.PathLike | None = None) -> str | None:
    """Keep XLA's compiled programs in the folder `path` (default `cache_dir()`) for later
    processes: a later process that compiles the same program (same structure, size,
    options and XLA settings) loads it instead, which spares the silhouette-aware
    gradient most of its minute-long compile (JAX's own trace of the program remains).
    Programs that compile in under `CACHE_MIN_COMPILE_S` are not kept. Call it before
    compiling; the `rtjax` command does. Returns the folder, or None (`RTJAX_CACHE=off`
    and no `path`: nothing is kept)."""
    path = cache_dir() if path is None else os.fspath(path)
    if path is None:
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)
    return path
