"""Scenes for the silhouette mode's derivatives (issue 21), with mirrors and glass and one
without, and what to vary in them: shared by `scripts/edges_yardstick.py`, which computes their
supersampled finite differences with the independent reference renderer
(`rtjax.reference`) into `tests/data/edges_yardstick.npz`, and `tests/test_edges_chain.py`,
which checks `render(..., edges=1)`'s derivatives against them.

A parameter is (name, what, index, axis, world size of one pixel's image motion): `what`
is "center" (sphere `index`, axis 0–2), "radius" (sphere `index`), "light" (light
`index`'s direction, axis 0–2) or "eye" (axis 0–2). Finite differences step by
`STEPS` × that size.
"""

from __future__ import annotations

FLOOR = "sphe 0 0 -10015 10000\nopaq 0.8 0.8 0.7 0 1\n"

DECKS = {
    # the held-out-like scene: a floor, an opaque sphere, a mirror and a glass
    # sphere (n = 1.5), each clear of the floor, one light, shadows on the floor
    "heldout": (
        FLOOR
        + "sphe -13 -4 -7 6\nopaq 0.9 0.5 0.2 0.4 10\n"
        + "sphe 9 8 -5 8\nmirr\n"
        + "sphe 1 -17 -9 5\ntrpa 0.85 1.5 0.2 10\n"
        + "plig 0.5 -0.4 1 180 170 160\nelig 0.15\nback 30 40 90\n"
        + "eyep 0 -100 12\nrefp 0 0 -7\nvang 30 30\nsize 48\nrend x.ras\n",
        6,
    ),
    # spheres that cut into one another (an opaque one into a mirror, a glass one into the
    # opaque one) and one that touches the floor: intersection curves are edges
    "overlap": (
        FLOOR
        + "sphe -6 0 -6 7\nopaq 0.9 0.5 0.2 0.4 10\n"
        + "sphe 5 4 -5 8\nmirr\n"
        + "sphe -3 -9 -10 5\ntrpa 0.85 1.5 0.2 10\n"
        + "sphe 14 -10 -11 4\nopaq 0.3 0.7 0.9 0.4 10\n"
        + "plig 0.5 -0.4 1 180 170 160\nelig 0.15\nback 30 40 90\n"
        + "eyep 0 -100 14\nrefp 0 0 -7\nvang 24 24\nsize 48\nrend x.ras\n",
        6,
    ),
    # a glass sphere of high index (2.4) seen near its rim, in front of an opaque sphere
    # and the floor. (Named for total internal reflection, which no ray meets here: a
    # chord of a sphere makes equal angles at both ends, so a ray that refracted in
    # refracts out; the reference counts 0 TIR events in all four scenes.)
    "tir": (
        FLOOR
        + "sphe 0 -20 -3 9\ntrpa 0.9 2.4 0.2 10\n"
        + "sphe 6 15 -4 8\nopaq 0.9 0.5 0.2 0.4 10\n"
        + "plig 0.5 -0.4 1 180 170 160\nelig 0.15\nback 30 40 90\n"
        + "eyep 0 -100 30\nrefp 0 0 -5\nvang 22 22\nsize 40\nrend x.ras\n",
        6,
    ),
    # 32 pixels: small spheres, a mirror and glass, so that pixels hold several edges
    "crowded": (
        FLOOR
        + "sphe -9 0 -9 4\nopaq 0.9 0.5 0.2 0.4 10\n"
        + "sphe 0 6 -8 6\nmirr\n"
        + "sphe 6 -10 -10 4\ntrpa 0.85 1.5 0.2 10\n"
        + "sphe -2 -14 -12 2.5\nopaq 0.3 0.7 0.9 0.4 10\n"
        + "plig 0.5 -0.4 1 180 170 160\nelig 0.15\nback 30 40 90\n"
        + "eyep 0 -100 40\nrefp 0 0 -8\nvang 20 20\nsize 32\nrend x.ras\n",
        6,
    ),
    # the eye inside a glass sphere (n = 1.5), 14 units off its centre: rays more than
    # r/n = 13.3 units from the centre are totally reflected where they meet it, so the
    # left of the image sees the glass from inside and the right sees out, a sphere and
    # its shadow compressed near that boundary (24 pixels)
    "inside": (
        FLOOR
        + "sphe 0 0 6 20\ntrpa 0.9 1.5 0.2 10\n"
        + "sphe 10 48 -2 6\nopaq 0.9 0.5 0.2 0.4 10\n"
        + "plig -0.4 -0.8 0.6 190 180 170\nelig 0.2\nback 40 60 110\n"
        + "eyep 14 0 6\nrefp 31.1 47 -1.5\nvang 32 32\nsize 24\nrend x.ras\n",
        6,
    ),
    # no mirror, no glass: three opaque spheres clear of the floor, 40 pixels, the camera
    # off to the side; where an outline lies over its own shadow a pixel holds two edges
    "opaque": (
        FLOOR
        + "sphe -10 -6 -10 5\nopaq 0.9 0.9 0.2 0.3 8\n"
        + "sphe 6 6 -6 9\nopaq 0.3 0.5 0.9 0.4 20\n"
        + "sphe 8 -16 -11 4\nopaq 0.8 0.3 0.3 0.2 10\n"
        + "plig 0.3 -0.8 1 200 190 180\nelig 0.1\nback 20 30 70\n"
        + "eyep -15 -90 25\nrefp 0 0 -8\nvang 28 28\nsize 40\nrend x.ras\n",
        0,
    ),
}

#: Samples per pixel (k × k) of the stored supersampled image.
SPP = 16
#: The stored finite differences, (k × k samples a pixel, step in pixels of image
#: motion). The fine ones, the finest first: a derivative image is the limit of small
#: steps, and a step of 0.3 px still averages it where edges crowd (inside glass); the
#: second confirms the first. The coarse ones: the issue's own measurement.
FINE = ((64, 0.04), (48, 0.05))
COARSE = ((16, 0.3), (16, 0.6), (24, 0.3))


def yardstick_key(k: int, step: float) -> str:
    """The stored name of the finite differences at k × k samples and `step` px."""
    return f"fd{k}_{step}"


def small_spheres(name: str) -> list[int]:
    """The spheres whose centre and radius are varied: all but the floor (sphere 0)."""
    return list(range(1, DECKS[name][0].count("sphe ")))


def parameters(name: str, eye, refp, ha: float, width: int, centers) -> list[tuple]:
    """The varied parameters of scene `name` (see the module's docstring)."""
    import math

    def px(point):  # a pixel's width in the world at that point's distance
        dist = math.dist(eye, point)
        return 2 * dist * math.tan(math.radians(ha) / 2) / width

    out = []
    for k in small_spheres(name):
        for axis, a in (("x", 0), ("y", 1), ("z", 2)):
            out.append((f"{k}{axis}", "center", k, a, px(centers[k])))
        out.append((f"{k}r", "radius", k, 0, px(centers[k])))
    if name == "heldout":
        # the light: a shadow edge moves by about (distance from occluder to floor) ×
        # (the direction's turn); the camera: the scene moves by a pixel per pixel
        # width at the reference point's distance
        out += [("light x", "light", 0, 0, px(refp) / 12), ("light y", "light", 0, 1, px(refp) / 12)]
        out += [("eye x", "eye", 0, 0, px(refp)), ("eye z", "eye", 0, 2, px(refp))]
    return out
