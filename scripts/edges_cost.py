"""Forward cost of the silhouette-aware mode against the plain render, side by side in
one process (alternating runs, medians): the ratio issue 21 bounds (≤ 3×). With
`--unsplit`, also the mode without its 2 × 2 split of the pixels whose edge lies in or
at a mirror or glass (`trace.trace_edges(split=False)`), for the split's own cost.

    python scripts/edges_cost.py [--deck scenes/ex2s3.dat] [--runs 7] [--unsplit]
"""

from __future__ import annotations

import argparse
import functools
import importlib
import statistics
import time

import jax

import rtjax

render_module = importlib.import_module("rtjax.render")  # the module (rtjax.render is the function)

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deck", default="scenes/ex2s3.dat")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--unsplit", action="store_true")
    args = ap.parse_args()
    scene = rtjax.load_deck(args.deck).frames[0].scene
    fns = {"plain": lambda s: rtjax.render(s), "edges=1": lambda s: rtjax.render(s, edges=1.0)}
    for fn in fns.values():
        jax.block_until_ready(fn(scene))
    if args.unsplit:
        # another tile size (larger than the image: the same tiling) is another compiled
        # program; it is traced while trace_edges defaults to split=False
        big = 2 * scene.structure.width * scene.structure.height
        original = render_module.trace_edges
        render_module.trace_edges = functools.partial(original, split=False)
        fns["edges=1 unsplit"] = lambda s: rtjax.render(s, edges=1.0, tile=big)
        jax.block_until_ready(fns["edges=1 unsplit"](scene))
        render_module.trace_edges = original
    times = {k: [] for k in fns}
    for _ in range(args.runs):
        for k, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(scene))
            times[k].append(time.perf_counter() - t)
    plain = statistics.median(times["plain"])
    text = ", ".join(f"{k} {statistics.median(v) * 1e3:.1f} ms ({statistics.median(v) / plain:.2f}x)"
                     for k, v in times.items())
    print(f"{args.deck}: {text} (medians of {args.runs}, alternating)")


if __name__ == "__main__":
    main()
