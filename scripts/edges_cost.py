"""Forward cost of the silhouette-aware mode against the plain render, side by side in
one process (alternating runs, medians): the ratio issue 21 bounds (≤ 3×); and of the
mode with its 2 × 2 sub-boxes in mirrors and glass (`render(..., subdivide=True)`).

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
           "edges=1 subdivide": lambda s: rtjax.render(s, edges=1.0, subdivide=True)}
    for fn in fns.values():
        jax.block_until_ready(fn(scene))
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
