"""The bench's measuring tools: wall-clock timing, image errors as 8-bit files hold
them, XLA's memory analysis and a description of the machine.

Timings are wall-clock medians on whatever else the machine is running: on a shared
machine they move from run to run; ratios within one run are steadier.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable

import numpy as np


def timed(fn: Callable[[], object], repeats: int) -> dict:
    """Time a zero-argument JAX computation.

    **Arguments:**

    - `fn`: called once to compile, then `repeats` (at least 1) times to time.
    - `repeats`: the number of timed calls.

    **Returns:** a dict with `compile_s` (first call minus the median, ≥ 0), `median_s`,
    `runs_s` (each timed call), `first_s` and `out` (the last call's output).
    """
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    med = float(np.median(runs))
    return {"compile_s": max(first - med, 0.0), "median_s": med, "runs_s": runs, "first_s": first, "out": out}


def quantize(image) -> np.ndarray:
    """What a file holds: clamped, rounded half up, 8-bit levels (as `rtjax.to_uint8`),
    as int16 so that differences of two images do not wrap."""
    return np.floor(np.clip(np.asarray(image, np.float64), 0, 255) + 0.5).astype(np.int16)


def upsample(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-pixel resampling onto a height × width grid (pixel centres to pixel centres)."""
    h, w = image.shape[:2]
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return image[rows][:, cols]


def image_errors(image, reference) -> dict:
    """Errors of an image against a reference, both as 8-bit files would hold them.

    **Arguments:**

    - `image`: (h, w, 3) levels 0..255; a smaller image is upsampled (`upsample`) to the
      reference's size.
    - `reference`: (H, W, 3) levels 0..255.

    **Returns:** a dict with `psnr_db` (None when identical: infinite), `rms_levels` and
    `max_levels` (level differences), and `frac_off` (the fraction of pixels off by ≥ 1
    level in some channel).
    """
    a, b = quantize(image), quantize(reference)
    if a.shape != b.shape:
        a = upsample(a, *b.shape[:2])
    diff = np.abs(a.astype(np.int32) - b.astype(np.int32))
    mse = float(np.mean(diff.astype(np.float64) ** 2))
    return {
        "psnr_db": None if mse == 0 else 10 * math.log10(255.0**2 / mse),
        "rms_levels": math.sqrt(mse),
        "max_levels": int(diff.max()),
        "frac_off": float(np.mean(diff.max(axis=-1) >= 1)),
    }


def memory_bytes(stats, prefix: str) -> dict:
    """XLA's compiled memory analysis as `{prefix}_temp_bytes` and `{prefix}_peak_bytes`
    (temporaries + arguments + outputs − aliased); only `{prefix}_peak_bytes`, None,
    where the backend gives no analysis (`stats` None)."""
    if stats is None:
        return {f"{prefix}_peak_bytes": None}
    temp, arg, outb, alias = (int(getattr(stats, k, 0) or 0) for k in
                              ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes", "alias_size_in_bytes"))
    return {f"{prefix}_temp_bytes": temp, f"{prefix}_peak_bytes": temp + arg + outb - alias}


def machine() -> dict:
    """The platform, processor, core count, JAX version and backend, XLA_FLAGS and load average."""
    import jax

    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
