"""`Problem`: a fit set up from its options — the scene at the target's size, the free
parameters and their start, the Jacobian mode, the pyramid of levels and the objective."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .objective import (DENOISE, EXACT_SCALE, Objective, Samples, load_target, make_levels, match_size, nuisance_y0,
                        prepare_mask, schedule_widths)
from .matrixfree import MATRIX_FREE_ABOVE
from .options import FitOptions
from .photo import Photo
from .select import Selection
from .texels import appearance_only, texel_levels


@dataclasses.dataclass(frozen=True)
class Problem:
    """What every fitting driver starts from.

    - `scene`: the start scene at the target's size.
    - `selection`: the free parameters (`Selection`).
    - `y0`: their start in the solver's coordinates: {"scene": ..., "nuisance": ...}.
    - `jac`: 'fwd', 'bwd' or 'matfree' (`solvers.Stepper`).
    - `widths`: each level's width in pixels, coarse to fine.
    - `pyramid`: each level's `Samples`.
    - `objective`: the residual function.
    """

    scene: rtjax.Scene
    selection: Selection
    y0: dict
    jac: str
    widths: list[int]
    pyramid: list[Samples]
    objective: Objective

    @classmethod
    def build(cls, scene: rtjax.Scene, target, free: str | Sequence[str], spheres: Sequence[int] | None,
              options: FitOptions) -> Problem:
        """The problem of fitting `free` (restricted to `spheres`) of `scene` to `target` (an
        image path or an (H, W, 3) array in 0..255) as `options` say."""
        target = load_target(target, assignment_order=options.assignment_order)
        full = match_size(scene, target)
        selection = Selection(full, free, spheres)
        y = {"scene": selection.y0()}
        dtype = jnp.result_type(full.params.centers)
        nuisance = options.nuisance
        if nuisance:
            y["nuisance"] = nuisance_y0(nuisance, jax.tree_util.tree_leaves(y["scene"])[0].dtype)
        photo = Photo(full) if options.photo else None
        if photo is not None:
            y["photo"] = photo.y0(jax.tree_util.tree_leaves(y["scene"])[0].dtype)
        jac = options.jac
        if jac is None:
            jac = "matfree" if selection.size() > MATRIX_FREE_ABOVE else "fwd"
        blurred = "blur" in nuisance or photo is not None
        if options.levels is None and not blurred and appearance_only(selection.families):
            # texels: the full-size image, every pixel, the plain render (`fitting.texels`)
            levels = texel_levels(target, prepare_mask(options.mask, *target.shape[:2]), dtype)
            objective = Objective(selection, options.depth, options.loss, options.loss_scale)
            return cls(full, selection, y, jac, [full.structure.width] * len(levels), levels, objective)
        widths = schedule_widths(full.structure.width, options.levels, blurred=blurred)
        given = options.edges or (1.0,)
        # one value: every level; several: one per level in order, the last repeating
        per_level = [given[min(i, len(given) - 1)] for i in range(len(widths))]
        exact, whole = [False] * len(widths), [False] * len(widths)
        polish, exact_polish = options.polish, options.exact_polish
        if blurred:  # a photo: the full-size level is the whole image through `objective.camera`
            whole[-1] = True
        elif polish and exact_polish and len(widths) > 1:
            # matched at pixel centres, the full-size level needs no box-filtered one before it
            per_level[-1], exact[-1] = float(polish), True
        elif polish:
            widths, per_level, exact = widths + [widths[-1]], per_level + [float(polish)], exact + [bool(exact_polish)]
        pyramid = make_levels(target, prepare_mask(options.mask, *target.shape[:2]), widths, per_level, dtype, exact=exact,
                              denoise=DENOISE if blurred else 0.0, whole=whole)
        if pyramid[-1].exact:  # the same samples again, at a narrow robust scale
            pyramid.append(pyramid[-1]._replace(scale=jnp.asarray(EXACT_SCALE, dtype)))
            widths = widths + [widths[-1]]
        objective = Objective(selection, options.depth, options.loss, options.loss_scale, photo)
        return cls(full, selection, y, jac, widths, pyramid, objective)

    def photo_values(self, y: dict) -> dict[str, object]:
        """A photo fit's appearance and camera parameters at `y` in their own units
        (floats and nested lists); empty for other fits."""
        photo = self.objective.photo
        if photo is None:
            return {}
        return {k: np.asarray(v, np.float64).tolist() for k, v in photo.values(y["photo"]).items()}
