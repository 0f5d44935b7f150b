"""Forward cost of the silhouette-aware mode against the plain render, side by side in
one process (alternating runs, medians; and each one's first call, compile included):
the ratio issue 21 bounds (≤ 3×); and of the
mode with its 2 × 2 and 4 × 4 sub-boxes (`render(..., subdivide=1)`
and `subdivide=2`).

    python scripts/edges_cost.py [--deck scenes/ex2s3.dat] [--runs 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deck", default="scenes/ex2s3.dat")
    ap.add_argument("--runs", type=int, default=7)
    args = ap.parse_args()
    scene = rtjax.load_deck(args.deck).frames[0].scene
    fns = {"plain": lambda s: rtjax.render(s), "edges=1": lambda s: rtjax.render(s, edges=1.0),
           "edges=1 subdivide=1": lambda s: rtjax.render(s, edges=1.0, subdivide=1),
           "edges=1 subdivide=2": lambda s: rtjax.render(s, edges=1.0, subdivide=2)}
    first = {}
    for k, fn in fns.items():
        t = time.perf_counter()
        jax.block_until_ready(fn(scene))
        first[k] = time.perf_counter() - t
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
    print("first calls (compile included): " + ", ".join(f"{k} {v:.1f} s" for k, v in first.items()))


if __name__ == "__main__":
    main()
