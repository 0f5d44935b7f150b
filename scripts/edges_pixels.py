"""Where the silhouette mode's derivative image of one parameter is off (issue 21): the
pixels that hold most of its squared error against the finest yardstick of
`scripts/edges_yardstick.py`, each with the mode's value and both fine yardsticks'
(summed over the colour channels), the pixels where the two yardsticks agree on a
derivative that the mode lacks, and which spheres 16 × 16 rays through the worst few
pixels meet first (−1: none), to tell an outline from what a mirror or glass shows.

    python scripts/edges_pixels.py SCENE PARAMETER [--subdivide N] [--top K]

PARAMETER as `scripts/edges_accuracy.py` names them (`3x`: sphere 3's centre x; `3r`
its radius; `eye x`, ...).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import rtjax  # noqa: E402
from edge_derivatives import FINE_KEYS, derivative_images, scene, yardsticks  # noqa: E402

SAMPLES = 16  # rays per pixel side for the first-hit maps


def first_hits(s: rtjax.Scene, row: int, col: int) -> np.ndarray:
    """(SAMPLES, SAMPLES) index of the sphere each of SAMPLES² rays through pixel (row,
    col) meets first, −1 for none (the renderer's camera and `spheres.nearest`)."""
    p = s.params
    u = (np.arange(SAMPLES) + 0.5) / SAMPLES
    x, y = np.meshgrid(col + u, row + u)
    o, d = rtjax.camera.rays_through(p.eye, p.refp, p.vang, s.structure.width, s.structure.height,
                                     jnp.asarray(np.stack([x.ravel(), y.ravel()])))
    index = rtjax.spheres.nearest(o, d, p.centers, p.radii, jnp.full(SAMPLES**2, -1), 1e-6, False)[1]
    return np.asarray(index).reshape(SAMPLES, SAMPLES)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("parameter")
    ap.add_argument("--subdivide", type=int, default=None, metavar="N",
                    help="render(..., subdivide=N) (default: render's own for the image's size)")
    ap.add_argument("--top", type=int, default=10, help="pixels listed (default 10)")
    args = ap.parse_args()
    ys = yardsticks(args.scene)
    names = [str(n) for n in ys["names"]]
    if args.parameter not in names:
        sys.exit(f"{args.scene} has no parameter {args.parameter!r}; it has: {', '.join(names)}")
    i = names.index(args.parameter)
    _, jac = derivative_images(args.scene, 1.0, 1, args.subdivide)
    mode, finest, confirm = (a[i].sum(-1) for a in (jac, ys[FINE_KEYS[0]], ys[FINE_KEYS[1]]))
    error = (mode - finest) ** 2
    total = error.sum()
    print(f"{args.scene} {args.parameter}: squared error {total:.4g} of a signal {np.sum(finest**2):.4g}; "
          f"(row, col): mode / {FINE_KEYS[0]} / {FINE_KEYS[1]}, share of the error")
    worst = np.argsort(error.ravel())[::-1][:args.top]
    for k in worst:
        r, c = divmod(int(k), mode.shape[1])
        print(f"  ({r}, {c}): {mode[r, c]:9.2f} / {finest[r, c]:9.2f} / {confirm[r, c]:9.2f}  {error[r, c] / total:.2f}")
    agreed = (np.abs(finest) > 0.1 * np.abs(finest).max()) & (np.abs(confirm - finest) < 0.3 * np.abs(finest))
    missing = agreed & (np.abs(mode) < 0.2 * np.abs(finest))
    print("  derivative in both yardsticks, little in the mode:", [divmod(int(k), mode.shape[1]) for k in np.flatnonzero(missing)])
    s = scene(args.scene)
    print(f"  spheres: {', '.join(f'{j} {kind}' for j, kind in enumerate(s.structure.kinds))}")
    for k in worst[:3]:
        r, c = divmod(int(k), mode.shape[1])
        print(f"  first hits of {SAMPLES} × {SAMPLES} rays through ({r}, {c}):")
        print("\n".join("    " + " ".join(f"{v:2d}" for v in line) for line in first_hits(s, r, c)))


if __name__ == "__main__":
    main()
