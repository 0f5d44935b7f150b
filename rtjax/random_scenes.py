"""Random scenes of many non-overlapping spheres, as deck text or as a `rtjax.Scene`:
for timing the renderer against the number of spheres and for testing culling.
"""

from __future__ import annotations

import math

import numpy as np


def random_deck_text(n: int, seed: int = 0, size: int = 400, mirrors: float = 0.1, glass: float = 0.1) -> str:
    """A deck of random non-overlapping spheres.

    **Arguments:**

    - `n`: the number of spheres (radii 0.5–1.5), filling a cube at about 8 % of its volume.
    - `seed`: the NumPy random generator's seed: the same arguments give the same deck.
    - `size`: the image width in pixels (the height is 294 at 400: `vang 40 30`).
    - `mirrors`, `glass`: the expected fractions of mirror and glass spheres (the rest opaque).

    **Returns:** the deck's text: the spheres, two lights, a blue background, the eye
    outside the cube's corner looking at its centre, one `rend` line.
    """
    rng = np.random.default_rng(seed)
    side = (n * 4 / 3 * math.pi / 0.08) ** (1 / 3)
    centers: list[np.ndarray] = []
    radii: list[float] = []
    cells: dict[tuple[int, int, int], list[int]] = {}
    cell = 3.0  # ≥ the largest diameter: overlaps are only with neighbouring cells
    while len(centers) < n:
        r = float(rng.uniform(0.5, 1.5))
        c = rng.uniform(-side / 2 + r, side / 2 - r, 3)
        key = tuple(int(k) for k in np.floor(c / cell))
        near = (j for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                for j in cells.get((key[0] + dx, key[1] + dy, key[2] + dz), ()))
        if all(np.linalg.norm(c - centers[j]) > r + radii[j] + 0.05 for j in near):
            cells.setdefault(key, []).append(len(centers))
            centers.append(c)
            radii.append(r)
    lines = [f"# {n} random spheres (rtjax.bench.random_deck_text, seed {seed})"]
    for c, r in zip(centers, radii):
        lines.append("sphe %.4f %.4f %.4f %.4f" % (*c, r))
        u = rng.uniform()
        if u < mirrors:
            lines.append("mirr")
        elif u < mirrors + glass:
            lines.append("trpa %.2f %.2f 0.2 10" % (rng.uniform(0.6, 0.9), rng.uniform(1.3, 1.8)))
        else:
            lines.append("opaq %.3f %.3f %.3f 0.3 20" % tuple(rng.uniform(0.1, 1, 3)))
    lines += ["back 0 0 128", "plig 0.5 0.5 2 255 255 255", "plig -1 0.3 0.5 100 100 80", "elig 0.2",
              "eyep %.3f %.3f %.3f" % (1.6 * side, 1.3 * side, 0.9 * side), "refp 0 0 0", "vang 40 30",
              f"size {size}", "rend random.sunimg", "quit"]
    return "\n".join(lines) + "\n"


def random_scene(n: int, seed: int = 0, size: int = 400):
    """The `rtjax.Scene` of `random_deck_text(n, seed, size)` (float32, as a deck's)."""
    import rtjax

    return rtjax.parse_deck(random_deck_text(n, seed, size), f"<random {n}>").frames[0].scene
