"""Forward cost of the silhouette-aware mode against the plain render, side by side in
one process (alternating runs, medians): the ratio issue 21 bounds (≤ 3×).

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
    fns = {w: (lambda s, w=w: rtjax.render(s, edges=w)) for w in (0.0, 1.0)}
    for fn in fns.values():
        jax.block_until_ready(fn(scene))
    times = {w: [] for w in fns}
    for _ in range(args.runs):
        for w, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(scene))
            times[w].append(time.perf_counter() - t)
    plain, box = statistics.median(times[0.0]), statistics.median(times[1.0])
    print(f"{args.deck}: plain {plain * 1e3:.1f} ms, edges=1 {box * 1e3:.1f} ms, ratio {box / plain:.2f}x "
          f"(medians of {args.runs}, alternating)")


if __name__ == "__main__":
    main()
