"""One pixel of an edge scene taken apart into k × k sub-boxes: the silhouette mode's
derivative of each (a box 1/k px wide, `render_samples(step=1/k, edges=1)`, float64)
against central differences of the reference's n × n samples of the same box.

What the mode gets wrong in a pixel is usually spread along an edge (a band narrower
than the box, a nonlinearity across it); one sub-box holding most of the pixel's
derivative where the reference's is small is the signature of a fault (stop 62: a side
forced to meet a sphere behind its origin). The scenes and parameter names are those of
`tests/edge_scenes.py` ("2x": sphere 2's centre x, "3r": sphere 3's radius).

    python scripts/edges_subboxes.py SCENE ROW COL PARAM [--k 16] [--n 8] [--step 0.01] [--top 6]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, os.path.join(ROOT, "scripts"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from edge_derivatives import scene, scene_parameters, varied  # noqa: E402
from edge_scenes import DECKS  # noqa: E402
from edges_yardstick import moved  # noqa: E402

import rtjax  # noqa: E402
from rtjax import reference  # noqa: E402


def sub_boxes(name: str, row: int, col: int, param: str, k: int, n: int, step: float):
    """(mode, reference): the derivative of each of pixel (row, col)'s k × k sub-boxes
    against `param`, (k, k, 3) each, in levels per scene unit."""
    s = scene(name)
    at, count = varied(name, s)
    params = scene_parameters(name, s)
    index = [p[0] for p in params].index(param)
    _, what, sphere, axis, _ = params[index]
    depth = DECKS[name][1]
    centres = (np.arange(k) + 0.5) / k
    x, y = np.meshgrid(col + centres, row + centres)
    xy = jnp.asarray(np.stack([x.ravel(), y.ravel()], -1))
    tangent = jnp.zeros(count).at[index].set(1.0)
    _, mode = jax.jvp(lambda v: rtjax.render_samples(at(v), xy, step=1.0 / k, edges=1.0, depth=depth),
                      (jnp.zeros(count),), (tangent,))
    frame = reference.parse_deck_text(DECKS[name][0])[0]
    offsets = (np.arange(k * n) + 0.5) / (k * n)  # n × n samples in each sub-box
    sx, sy = np.meshgrid(col + offsets, row + offsets)
    samples = np.stack([sx.ravel(), sy.ravel()], -1)

    def boxes(h):
        colours = reference.render_positions(moved(frame, what, sphere, axis, h), samples, depth=depth)
        return colours.reshape(k, n, k, n, 3).mean(axis=(1, 3))

    return np.asarray(mode).reshape(k, k, 3), (boxes(step) - boxes(-step)) / (2 * step)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", choices=list(DECKS))
    ap.add_argument("row", type=int)
    ap.add_argument("col", type=int)
    ap.add_argument("param")
    ap.add_argument("--k", type=int, default=16, help="sub-boxes per side")
    ap.add_argument("--n", type=int, default=8, help="reference samples per sub-box side")
    ap.add_argument("--step", type=float, default=0.01, help="central difference step, scene units")
    ap.add_argument("--top", type=int, default=6, help="sub-boxes listed, largest disagreement first")
    args = ap.parse_args()
    mode, ref = (a.mean(-1) for a in sub_boxes(args.scene, args.row, args.col, args.param, args.k, args.n, args.step))
    cells = args.k * args.k
    print(f"{args.scene} pixel ({args.row}, {args.col}), d/d{args.param} (levels per unit, grey): "
          f"mode {mode.mean():.2f}, reference {ref.mean():.2f}")
    with np.printoptions(linewidth=200, precision=1, suppress=True):
        print("each sub-box's share of the pixel's derivative, mode:")
        print(mode / cells)
        print("reference:")
        print(ref / cells)
    worst = np.argsort(-np.abs(mode - ref), axis=None)[: args.top]
    for i, j in zip(*np.unravel_index(worst, mode.shape)):
        print(f"  sub-box ({i}, {j}): mode {mode[i, j]:.0f}, reference {ref[i, j]:.0f}, "
              f"share {mode[i, j] / cells:.2f} against {ref[i, j] / cells:.2f}")


if __name__ == "__main__":
    main()
