"""`FitOptions`: how a fit runs (solver, schedule, objective), one record for every driver."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .errors import FitError
from .objective import LOSSES, nuisance_names
from .solvers import SOLVERS


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """The settings of `fitting.fit` and `fitting.fit_multistart`, checked when made
    (`FitError` for a bad one); `nuisance` and `edges` are kept in their normal form.

    **Fields:**

    - `solver`: 'lm' (Levenberg–Marquardt, default), 'gn' (Gauss–Newton), 'dogleg' (least
      squares) or 'bfgs' (minimisation of the same loss).
    - `max_steps`: iterations in all, across the coarse-to-fine levels.
    - `levels`: the pyramid's widths (`objective.schedule_widths`): None (default: an
      eighth, a quarter and the full width), an int ≥ 1 (that many levels halving the
      width, none below 48 pixels; 1: full size only) or a list of widths ≥ 1. None with
      textures free (and only `texels.APPEARANCE` families): the full-size image, every
      pixel, plain renders (`texels.texel_levels`). Every level but a
      full-size one matched at pixel centres renders as many samples as the coarsest has
      pixels, so one compiled step serves them.
    - `edges`: edge width of the silhouette-aware render in pixels of each level (None:
      1): one value, or one per level (the last repeating); kept as a tuple.
    - `polish`: the edge width (pixels) of the full-size fit, default 1; None: no special
      full-size level.
    - `exact_polish`: match the full-size level at pixel centres, as `rtjax render` makes
      targets (`Objective.model`; default): unbiased at the truth, it takes all of the
      target's edge pixels and hands over, close to the target, to a refinement with a
      narrower robust scale (`objective.EXACT_SCALE`, `solve.level_budget`). False: a
      last full-size level box-filters edges `polish` wide (then use a narrow one such
      as 0.02), for targets that are themselves antialiased.
    - `depth`: the render's ray depth (None: the scene's).
    - `loss`: 'cauchy' (default, robust), 'huber' or 'l2'; `loss_scale` its scale in
      levels, > 0 (levels coarser than the image use `objective.COARSE_SCALE` times it unless
      a blur is fitted).
    - `mask`: an image or array whose dark (0) pixels are ignored; None: all count.
    - `nuisance`: camera parameters fitted with the scene for photo-like targets: 'gain'
      and 'gamma' (response 255·(gain·I/255)^γ), 'blur' (a Gaussian σ in pixels),
      'chroma' (a further blur of the chroma, as JPEG's 4:2:0 subsampling makes) and
      'order' (the share of the blur after the response); 'camera': all five
      (`objective.camera`). With a blur the coarse levels widen the edges' box filter,
      and the full-size level is the whole image through `camera` (`polish` is not
      used). Kept as a tuple in `objective.NUISANCE`'s order.
    - `rtol`, `atol`: the solver's tolerances.
    - `jac`: 'fwd' (the Jacobian by forward mode, one batched pass per step), 'bwd'
      (reverse mode, materialised), 'matfree' (no Jacobian: LSMR on J·v and Jᵀ·w,
      for many free parameters such as texels; `fitting.matrixfree`) or
      None (default: 'fwd' up to `matrixfree.MATRIX_FREE_ABOVE` free parameters, else
      'matfree').
    - `assignment_order`: a Sun raster target holds R,G,B in the assignment's order.
    - `smooth`: with textures free, the weight of a smoothness prior on the texels
      (`texels.Smoothed`; 0, default: none).
    """

    solver: str = "lm"
    max_steps: int = 30
    levels: int | Sequence[int] | None = None
    edges: float | Sequence[float] | None = None
    polish: float | None = 1.0
    exact_polish: bool = True
    depth: int | None = None
    loss: str = "cauchy"
    loss_scale: float = 10.0
    mask: object = None
    nuisance: Sequence[str] = ()
    rtol: float = 1e-5
    atol: float = 1e-7
    jac: str | None = None
    assignment_order: bool = False
    smooth: float = 0.0
    photo: bool = False

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise FitError(f"unknown solver {self.solver!r}; choose from {', '.join(SOLVERS)}")
        if self.loss not in LOSSES:
            raise FitError(f"unknown loss {self.loss!r}; choose from {', '.join(LOSSES)}")
        if self.jac not in (None, "fwd", "bwd", "matfree"):
            raise FitError(f"unknown jac {self.jac!r}; choose from fwd, bwd, matfree")
        if not self.smooth >= 0:
            raise FitError(f"smooth must be ≥ 0, not {self.smooth}")
        if int(self.max_steps) < 1:
            raise FitError(f"max_steps must be ≥ 1, not {self.max_steps}")
        if self.levels is not None:
            given = list(np.ravel(self.levels))
            if not given or any(int(k) != k or k < 1 for k in given):
                raise FitError(f"levels must be a count ≥ 1 or widths ≥ 1 pixel, not {self.levels}")
        if self.polish is not None and not self.polish > 0:
            raise FitError(f"polish must be an edge width > 0 pixels (or None: no full-size level of its own), "
                           f"not {self.polish}")
        if not 0 < self.loss_scale < np.inf:
            raise FitError(f"loss_scale must be a number of levels > 0, not {self.loss_scale}")
        object.__setattr__(self, "nuisance", nuisance_names(self.nuisance or ()))
        if self.photo and self.nuisance:
            raise FitError("a photo fit has its own camera model (fitting.photo): give photo or nuisance, not both")
        if self.edges is not None:
            given = tuple(float(e) for e in np.ravel(self.edges))
            if not given or min(given) <= 0:
                raise FitError(f"edge widths must be > 0, not {self.edges}")
            object.__setattr__(self, "edges", given)
