"""Cost of the silhouette-aware mode against the plain render, side by side in one
process (alternating runs, medians; and each one's first call, compile included): the
ratio issue 21 bounds (≤ 3×), for one box and for 2 × 2, 4 × 4 and 16 × 16 sub-boxes
where edges are (`render(..., subdivide=1, 2, 4)`); with `--grad`, also the reverse
gradient of the mean image. `--scene NAME` takes a scene of `tests/edge_scenes.py`
(issue 21's small images, float64, their depth) instead of a deck.

    python scripts/edges_cost.py [--deck scenes/ex2s3.dat | --scene overlap] [--runs 7] [--grad]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import jax

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deck", default="scenes/ex2s3.dat")
    ap.add_argument("--scene", help="a scene of tests/edge_scenes.py (float64), instead of --deck")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--grad", action="store_true", help="also time jax.grad of the mean image")
    args = ap.parse_args()
    if args.scene:
        jax.config.update("jax_enable_x64", True)
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
        from edge_scenes import DECKS

        text, depth = DECKS[args.scene]
        scene, name = rtjax.parse_deck(text).frames[0].scene.astype(jax.numpy.float64), args.scene
    else:
        scene, depth, name = rtjax.load_deck(args.deck).frames[0].scene, None, args.deck
    modes = {"plain": {}, "edges=1": dict(edges=1.0, subdivide=0)}
    modes.update({f"edges=1 subdivide={n}": dict(edges=1.0, subdivide=n) for n in (1, 2, 4)})

    def forward(kw):
        return jax.jit(lambda p: rtjax.render(rtjax.Scene(scene.structure, p), depth=depth, **kw))

    def gradient(kw):
        return jax.jit(jax.grad(lambda p: rtjax.render(rtjax.Scene(scene.structure, p), depth=depth, **kw).mean()))

    kinds = [("forward", forward)] + ([("gradient", gradient)] if args.grad else [])
    for kind, make in kinds:
        fns = {k: make(kw) for k, kw in modes.items()}
        first = {}
        for k, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(scene.params))
            first[k] = time.perf_counter() - t
        times = {k: [] for k in fns}
        for _ in range(args.runs):
            for k, fn in fns.items():
                t = time.perf_counter()
                jax.block_until_ready(fn(scene.params))
                times[k].append(time.perf_counter() - t)
        plain = statistics.median(times["plain"])
        text = ", ".join(f"{k} {statistics.median(v) * 1e3:.1f} ms ({statistics.median(v) / plain:.2f}x)"
                         for k, v in times.items())
        print(f"{name} {kind}: {text} (medians of {args.runs}, alternating)")
        print("  first calls (compile included): " + ", ".join(f"{k} {v:.1f} s" for k, v in first.items()))


if __name__ == "__main__":
    main()
