"""One parameter of one scene of `tests/edge_scenes.py` against a finer yardstick than
the stored one: central differences of the reference (`rtjax.reference`) at k × k
samples a pixel with a small step (default 32 × 32, 0.075 px of image motion), beside
the stored yardsticks and the silhouette mode's derivative image at 1 × 1 and 2 × 2
sub-boxes a pixel (`--modes`; jax.jvp of `render(..., edges=1, spp=s, dtype=float64)`;
`--subdivide [N]`: also with `subdivide=N`, 2^N × 2^N sub-boxes in the pixels an edge
may cross, N = 1 without a value): per-pixel cosines and the weighted sums' ratio to the
fine yardstick's.

    python scripts/edges_fine_check.py SCENE PARAM [--step 0.075] [--spp 32] [--modes 1,2] [--subdivide [N]]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, os.path.join(ROOT, "scripts"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import rtjax  # noqa: E402
from edge_derivatives import cosine, scene, varied, weights, yardsticks  # noqa: E402
from edge_scenes import DECKS, parameters  # noqa: E402
from edges_yardstick import moved  # noqa: E402

from rtjax import reference  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("param")
    ap.add_argument("--step", type=float, default=0.075)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--subdivide", type=int, nargs="?", const=1, default=0, metavar="N")
    ap.add_argument("--modes", default="1,2", help="the mode's sub-boxes a pixel (k for k × k), comma-separated")
    args = ap.parse_args()
    text, depth = DECKS[args.scene]
    frame = reference.parse_deck_text(text)[0]
    params = parameters(args.scene, frame.eye, frame.refp, frame.ha, frame.size, [s["center"] for s in frame.spheres])
    k = [p[0] for p in params].index(args.param)
    _, what, index, axis, size = params[k]
    h = args.step * size
    up, down = (reference.render_reference(moved(frame, what, index, axis, s * h), depth=depth, spp=args.spp)
                for s in (1, -1))
    fine = (up - down) / (2 * h)
    w = weights(fine.shape)
    total = float(np.sum(fine * w))
    ys = yardsticks(args.scene)
    print(f"{args.scene} {args.param}: fine yardstick {args.spp}x{args.spp}, step {args.step} px")
    for key in [key for key in ys if key.startswith("fd")]:
        fd = ys[key][k]
        print(f"  stored {key}: pixel cos {cosine(fd, fine):.4f}, sum ratio {np.sum(fd * w) / total:.3f}")
    s = scene(args.scene)
    at, n = varied(args.scene, s)
    e = jnp.zeros(n, jnp.float64).at[k].set(1.0)
    for spp in (int(k) for k in args.modes.split(",")):
        for subdivide in (0, args.subdivide) if args.subdivide else (0,):
            t = time.time()
            jac = np.asarray(jax.jvp(lambda v: rtjax.render(at(v), depth=depth, edges=1.0, spp=spp, subdivide=subdivide),
                                     (jnp.zeros(n),), (e,))[1])
            print(f"  mode spp={spp} subdivide={subdivide}: pixel cos {cosine(jac, fine):.4f}, sum ratio "
                  f"{np.sum(jac * w) / total:.3f} ({time.time() - t:.0f} s)")


if __name__ == "__main__":
    main()
