"""Procedural textures for the Level 4 decks, written as Sun raster files (no downloads).

    python scripts/make_textures.py [OUTDIR]        # default: scenes/textures/

Every texture is an equirectangular map as DECK.md §4 reads it: column x covers
longitude u = (x + ½)/w, i.e. atan2(p_y, p_x) = 2π·u − π (the seam, u = 0 ≡ 1, is the
−x axis), row y colatitude v = (y + ½)/h (row 0 touches the north pole, +z).

The output is deterministic, byte for byte: the only randomness is a hand-written
integer hash (no NumPy generator, whose streams may change between versions), and the
files are checked against this script by tests/test_textures.py.

    checker.sunimg  64 × 32  8 × 4 squares of 8 × 8 texels, red and cream
    bands.sunimg    32 × 16  8 latitude bands of 2 rows, a rainbow from pole to pole
    planet.sunimg  128 × 64  oceans, continents from smooth noise on the sphere, polar caps
    tiny.sunimg      5 × 3   15 distinct colours (an odd size: padded Sun raster rows)
"""

from __future__ import annotations

import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from rtjax.sunraster import write_sunraster  # noqa: E402

DEFAULT_OUT = os.path.join(ROOT, "scenes", "textures")


def texel_directions(w: int, h: int) -> np.ndarray:
    """Unit vectors (h, w, 3) of the texel centres, by DECK.md §4 inverted."""
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    lon = 2 * np.pi * u - np.pi
    colat = np.pi * v
    lon, colat = np.meshgrid(lon, colat)
    return np.stack([np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon), np.cos(colat)], axis=-1)


def checker(w: int = 64, h: int = 32, square: int = 8) -> np.ndarray:
    x, y = np.meshgrid(np.arange(w), np.arange(h))
    odd = ((x // square) + (y // square)) % 2 == 1
    red, cream = np.array([200, 30, 40]), np.array([240, 230, 200])
    return np.where(odd[..., None], red, cream).astype(np.uint8)


def bands(w: int = 32, h: int = 16, rows: int = 2) -> np.ndarray:
    palette = np.array(
        [
            [230, 40, 40],
            [240, 140, 30],
            [240, 220, 40],
            [60, 190, 60],
            [40, 170, 200],
            [40, 70, 210],
            [130, 50, 190],
            [235, 235, 235],
        ]
    )
    band = (np.arange(h) // rows) % len(palette)
    return np.broadcast_to(palette[band][:, None, :], (h, w, 3)).astype(np.uint8)


def _hash01(i: np.ndarray) -> np.ndarray:
    """A deterministic integer hash of int64 array i to floats in [0, 1)."""
    x = (i.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    x ^= x >> np.uint64(31)
    x = (x * np.uint64(0xBF58476D1CE4E5B9)) & np.uint64(0xFFFFFFFFFFFFFFFF)
    x ^= x >> np.uint64(29)
    return (x >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def sphere_noise(p: np.ndarray, waves: int = 64, seed: int = 7) -> np.ndarray:
    """Smooth noise on the unit sphere: a sum of plane waves in 3D with hashed
    directions, frequencies and phases, so it is seamless in longitude and at the poles."""
    k = np.arange(waves) + 1000 * seed
    a, b, c, f, ph = (_hash01(5 * k + j) for j in range(5))
    z = 2 * a - 1
    t = 2 * np.pi * b
    direction = np.stack([np.sqrt(1 - z * z) * np.cos(t), np.sqrt(1 - z * z) * np.sin(t), z], axis=-1)
    freq = 3 + 15 * f
    amp = freq**-0.75
    phase = 2 * np.pi * ph
    proj = p @ direction.T  # (..., waves)
    n = np.sum(amp * np.sin(freq * proj + phase) * (0.5 + c), axis=-1)
    return (n - n.mean()) / n.std()


def planet(w: int = 128, h: int = 64) -> np.ndarray:
    p = texel_directions(w, h)
    height = sphere_noise(p)
    lat = np.degrees(np.arcsin(np.clip(p[..., 2], -1, 1)))
    ocean_deep, ocean = np.array([15, 40, 120]), np.array([40, 90, 180])
    lowland, highland, mountain = np.array([60, 150, 60]), np.array([120, 130, 60]), np.array([140, 110, 80])
    ice = np.array([245, 248, 255])
    sea = 0.25  # height above which there is land: about 40 % of the surface
    img = np.where(height[..., None] < -0.6, ocean_deep, ocean).astype(float)
    land = height > sea
    img = np.where(land[..., None], lowland, img)
    img = np.where((height > sea + 1.1)[..., None], highland, img)
    img = np.where((height > sea + 1.8)[..., None], mountain, img)
    # polar caps: beyond 68° latitude, a little further where there is land
    cap = np.abs(lat) > 72 - 8 * land
    img = np.where(cap[..., None], ice, img)
    return np.round(img).astype(np.uint8)


def tiny(w: int = 5, h: int = 3) -> np.ndarray:
    y, x = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return np.stack([40 + 50 * x, 40 + 80 * y, 220 - 20 * x - 40 * y], axis=-1).astype(np.uint8)


TEXTURES = {
    "checker.sunimg": checker,
    "bands.sunimg": bands,
    "planet.sunimg": planet,
    "tiny.sunimg": tiny,
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = argv[0] if argv else DEFAULT_OUT
    os.makedirs(out, exist_ok=True)
    for name, make in TEXTURES.items():
        image = make()
        write_sunraster(os.path.join(out, name), image)
        print(f"{os.path.join(out, name)}: {image.shape[1]} x {image.shape[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
