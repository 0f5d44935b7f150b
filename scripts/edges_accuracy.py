"""The silhouette mode's derivatives against the yardstick of `scripts/edges_yardstick.py`
(issue 21's table): for each scene of `tests/edge_scenes.py`, the derivatives of
J = Σ w·image (fixed random weights) by jax.jacfwd of `render(..., edges=w, dtype=float64)`
against the supersampled finite differences: their cosine over the parameters, the
median relative error, the worst parameters, and the per-pixel cosine per parameter;
the worst over the fine yardsticks (64 × 64 samples, 0.04 px; 48 × 48, 0.05 px) and over
the coarse ones (16 × 16 and 24 × 24, 0.3 and 0.6 px) apart.

    python scripts/edges_accuracy.py [--edges W] [--spp K] [--subdivide [N]] [SCENE ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from edge_scenes import DECKS  # noqa: E402
from edge_derivatives import COARSE_KEYS, FINE_KEYS, compare, derivative_images, yardsticks  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="*")
    ap.add_argument("--edges", type=float, default=1.0)
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--subdivide", type=int, nargs="?", const=1, default=0, metavar="N",
                    help="render(..., subdivide=N): 2^N x 2^N sub-boxes in the pixels an edge may cross (N = 1 without a value)")
    args = ap.parse_args()
    for name in args.scenes or list(DECKS):
        ys = yardsticks(name)
        t = time.time()
        image, jac = derivative_images(name, args.edges, args.spp, args.subdivide)
        elapsed = time.time() - t
        print(f"== {name}  edges={args.edges} spp={args.spp} subdivide={args.subdivide}  ({elapsed:.0f} s)  mean |image − ss| = "
              f"{np.abs(image - ys['image']).mean():.3f}")
        for key in FINE_KEYS + COARSE_KEYS:
            print(f"  vs {key}: " + compare(jac, ys[key], ys["names"]).summary())
        for which, keys in (("fine", FINE_KEYS), ("coarse", COARSE_KEYS)):
            cs = [compare(jac, ys[k], ys["names"]) for k in keys]
            print(f"  over the {which} yardsticks: cos ≥ {min(c.cosine for c in cs):.4f}, median ≤ "
                  f"{max(c.median for c in cs) * 100:.1f} %, pixel cos ≥ {min(c.pixel_cosines.min() for c in cs):.3f}")
        for key in FINE_KEYS[1:] + COARSE_KEYS:
            print(f"  yardstick {key} vs the finest: " + compare(ys[key], ys[FINE_KEYS[0]], ys["names"]).summary(short=True))


if __name__ == "__main__":
    main()
