"""The yardstick of the silhouette mode's derivatives (issue 21): central finite
differences of the independent float64 reference renderer
(`rtjax.reference`), box-filtered from k × k samples per pixel, for the scenes and
parameters of `tests/edge_scenes.py`, written to `tests/data/edges_yardstick.npz`
(read by `tests/test_edges_chain.py`).

For each scene: the supersampled image (`image`, 16 × 16), and the finite-difference
derivative images (P, H, W, 3) at 16 × 16 samples with steps of 0.3 and 0.6 px of image
motion (`fd16_0.3`, `fd16_0.6`), at 24 × 24 with 0.3 px (`fd24_0.3`, confirming them),
and the fine ones (`edge_scenes.FINE`): 64 × 64 with 0.04 px (`fd64_0.04`) and 48 × 48
with 0.05 px (`fd48_0.05`, confirming it), stored as float32. About 45 minutes on one
core; `--only KEY,...` recomputes some of them, the others kept.

    python scripts/edges_yardstick.py [--only KEY,...] [--out PATH] [SCENE ...]
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))

from edge_scenes import COARSE, DECKS, FINE, SPP, parameters, yardstick_key  # noqa: E402

from rtjax import reference  # noqa: E402

OUT = os.path.join(ROOT, "tests", "data", "edges_yardstick.npz")


def moved(frame: reference.Frame, what: str, index: int, axis: int, h: float) -> reference.Frame:
    """`frame` with one parameter moved by h."""
    f = copy.deepcopy(frame)
    if what == "center":
        f.spheres[index]["center"][axis] += h
    elif what == "radius":
        f.spheres[index]["r"] += h
    elif what == "light":
        f.lights[index][0][axis] += h
    elif what == "eye":
        f.eye = np.array(f.eye, float)
        f.eye[axis] += h
    else:
        raise ValueError(what)
    return f


def yardstick(name: str, which=COARSE + FINE) -> dict[str, np.ndarray]:
    """Scene `name`'s image and its finite differences for each (k, step) of `which`."""
    text, depth = DECKS[name]
    frame = reference.parse_deck_text(text)[0]
    centers = [s["center"] for s in frame.spheres]
    params = parameters(name, frame.eye, frame.refp, frame.ha, frame.size, centers)
    out = {"image": reference.render_reference(frame, depth=depth, spp=SPP).astype(np.float32)}
    for spp, step in which:
        fd = []
        for label, what, index, axis, size in params:
            h = step * size
            up, down = (reference.render_reference(moved(frame, what, index, axis, s * h), depth=depth, spp=spp)
                        for s in (1, -1))
            fd.append((up - down) / (2 * h))
        out[yardstick_key(spp, step)] = np.asarray(fd, np.float32)
        print(f"{name} {spp}x{spp} step {step}: {time.strftime('%H:%M:%S')}", flush=True)
    out["names"] = np.array([p[0] for p in params])
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="*")
    ap.add_argument("--only", help="comma-separated keys (e.g. fd64_0.04) to recompute; the others are kept")
    ap.add_argument("--out", default=OUT)
    args = ap.parse_args()
    which = COARSE + FINE
    if args.only is not None:
        which = tuple(c for c in which if yardstick_key(*c) in args.only.split(","))
    stored = dict(np.load(args.out)) if os.path.exists(args.out) else {}
    for name in args.scenes or list(DECKS):
        for k, value in yardstick(name, which).items():
            stored[f"{name}/{k}"] = value
        np.savez_compressed(args.out, **stored)


if __name__ == "__main__":
    main()
