"""What a `rtjax bench` run measures: the reference, the knob values, the repeats."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Config:
    """What a bench run measures. `Config.full()` and `Config.quick()` are the CLI's.

    **Arguments** (the knob table):

    - `ref_depth`, `ref_spp`: the float64 reference's depth and K of its K×K samples per pixel.
    - `dtypes`, `depths`, `spps`, `edges`, `scales`: the values each knob takes alone
      from the default render (`depths` only for decks with mirrors or glass).
    - `subdivides`: the 1-pixel silhouette-aware mode with these halvings of the box in
      the pixels an edge may cross (`render`'s `subdivide`).
    - `repeats`: timed renders after the compiling one (their median is reported).
    - `derivatives`, `derivative_scale`, `lm_step`: whether derivatives are timed, at
      which image scale, and whether one Levenberg–Marquardt step is among them.
    - `numpy`, `numpy_repeats`: whether the NumPy reference (`rtjax.reference`) is timed, how often.
    - `width`: render the deck at this width instead of its own.

    **Arguments** (`--scale`):

    - `sphere_counts`, `brute_counts`, `scale_width`: random scenes of these sizes at this
      width, and those also rendered brute force (every ray against every sphere).
    - `widths`: the deck at these widths.
    - `memory_depths`: depths of the gradient memory analysis.
    - `scale_repeats`: timed renders per point.
    """

    ref_depth: int = 16
    ref_spp: int = 16
    dtypes: tuple[str, ...] = ("float32", "float64")
    depths: tuple[int, ...] = (0, 1, 2, 3, 4, 6, 8, 10, 12)
    spps: tuple[int, ...] = (1, 2, 4, 8)
    edges: tuple[float, ...] = (0.5, 1.0, 2.0)
    subdivides: tuple[int, ...] = (1, 2)
    scales: tuple[float, ...] = (0.25, 0.5, 1.0)
    repeats: int = 5
    derivatives: bool = True
    derivative_scale: float = 1.0
    lm_step: bool = True
    numpy: bool = True
    numpy_repeats: int = 3
    width: int | None = None
    sphere_counts: tuple[int, ...] = (8, 16, 32, 64, 128, 256, 512, 1000)
    brute_counts: tuple[int, ...] = (64, 128, 256, 512, 1000)
    scale_width: int = 400
    widths: tuple[int, ...] = (50, 100, 200, 400, 800)
    memory_depths: tuple[int, ...] = (0, 1, 2, 4, 8, 12)
    scale_repeats: int = 3

    @classmethod
    def full(cls) -> "Config":
        """`rtjax bench`: the defaults above."""
        return cls()

    @classmethod
    def quick(cls) -> "Config":
        """`rtjax bench --quick`: a smaller reference (8×8 samples, depth 12), fewer
        depths, derivatives at ¼ size, fewer repeats."""
        return cls(ref_depth=12, ref_spp=8, depths=(0, 1, 2, 4, 10, 12), spps=(1, 2, 4), repeats=3,
                   derivative_scale=0.25, numpy_repeats=1, sphere_counts=(8, 32, 128, 1000), brute_counts=(128, 1000),
                   widths=(100, 200, 400), memory_depths=(0, 2, 10), scale_repeats=2)
