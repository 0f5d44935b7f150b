"""`rtjax bench --scale`: render time against the number of spheres (random scenes,
culled as the renderer does, and brute force where affordable, the two images compared)
and against the pixel count (the deck at several widths), and the peak memory of the
reverse gradient against depth (XLA's compiled memory analysis).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .config import Config
from .measure import memory_bytes, timed
from ..random_scenes import random_scene


def measure_scale(scene, cfg: Config, log: Callable[[str], None]) -> dict:
    """Render time against spheres and pixels; gradient memory against depth.

    **Arguments:**

    - `scene`: the deck's scene (for the widths and the memory analysis).
    - `cfg`: `sphere_counts`, `brute_counts`, `scale_width`, `widths`, `memory_depths`
      and `scale_repeats`.
    - `log`: called with each progress line.

    **Returns:** a dict of three lists: `spheres` (n, width, height, culled, `timed`'s
    figures; where also rendered brute force: `brute`, `identical_to_brute`,
    `max_abs_diff_to_brute`), `pixels` (width, height, pixels, `timed`'s figures) and
    `memory` (depth, compile_s, `memory_bytes` of the gradient and of the forward render).
    """
    import jax

    import rtjax

    out: dict = {"spheres": [], "pixels": [], "memory": []}
    log(f"scale: random scenes at width {cfg.scale_width}, default settings (float32, depth 10, 1×1) …")
    scenes = {n: random_scene(n, size=cfg.scale_width) for n in cfg.sphere_counts}
    images = {}
    for n, sc in scenes.items():
        m = timed(lambda sc=sc: rtjax.render(sc), cfg.scale_repeats)
        images[n] = np.asarray(m.pop("out"))
        out["spheres"].append({"n": n, "width": sc.structure.width, "height": sc.structure.height,
                               "culled": sc.structure.culls, **m})
        log(f"  {n:5d} spheres  {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s"
            f"{'  (culled)' if sc.structure.culls else ''}")
    brute = [n for n in cfg.brute_counts if n in scenes and scenes[n].structure.culls]
    if brute:
        log("  brute force (every ray against every sphere), one timed run each …")
        for n in brute:
            sc = rtjax.Scene(scenes[n].structure.replace(culling=False), scenes[n].params)
            m = timed(lambda sc=sc: rtjax.render(sc), 1)
            img = np.asarray(m.pop("out"))
            row = next(r for r in out["spheres"] if r["n"] == n)
            row["brute"] = m
            row["identical_to_brute"] = bool(np.array_equal(img, images[n]))
            row["max_abs_diff_to_brute"] = float(np.max(np.abs(img - images[n])))
            log(f"  {n:5d} spheres  brute {1e3 * m['median_s']:9.1f} ms  identical: {row['identical_to_brute']}")
    log(f"scale: the deck at widths {', '.join(map(str, cfg.widths))} …")
    for w in cfg.widths:
        sc = scene.resized(w)
        m = timed(lambda sc=sc: rtjax.render(sc), cfg.scale_repeats)
        m.pop("out")
        out["pixels"].append({"width": w, "height": sc.structure.height, "pixels": w * sc.structure.height, **m})
        log(f"  {w:5d}×{sc.structure.height:<5d} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    st = scene.structure
    log(f"scale: memory of the reverse gradient (mean image) against depth, {st.width}×{st.height} …")
    for depth in cfg.memory_depths if st.needs_secondary_rays else (0,):
        def loss(p, depth=depth):
            return rtjax.render(rtjax.Scene(st, p), depth=depth).mean()

        t0 = time.perf_counter()
        compiled = jax.jit(jax.grad(loss)).lower(scene.params).compile()
        seconds = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        fwd = jax.jit(loss).lower(scene.params).compile().memory_analysis()
        row = {"depth": depth, "compile_s": seconds, **memory_bytes(mem, "grad"), **memory_bytes(fwd, "forward")}
        out["memory"].append(row)
        log(f"  depth {depth:2d}  gradient peak {row['grad_peak_bytes'] / 2**20:8.1f} MiB   forward {row['forward_peak_bytes'] / 2**20:7.1f} MiB")
    return out
