"""Fits to several views at once: one target per frame of a deck, the free parameters shared.

A deck's `rend` frames may show one scene from several cameras (or in several states);
a target per frame sees more of it than any one view (the far side of a texture, say).
The residuals of all frames are fitted together: each frame renders its own scene (its
own camera, size and fixed parameters) with the same free values, and the solver sees
one residual vector, the frames' end to end.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp

import rtjax

from .errors import FitError
from .objective import Objective, Samples
from .options import FitOptions
from .problem import Problem
from .select import Selection


class FrameSamples(NamedTuple):
    """One pyramid level of a multi-frame fit: each frame's `Samples` at that level."""

    frames: tuple[Samples, ...]

    @property
    def scale(self):
        """The level's robust scale factor (the same in every frame)."""
        return self.frames[0].scale

    @property
    def whole(self) -> bool:
        """Whether a frame's model renders its whole full-size image (a photo's level)."""
        return any(s.whole for s in self.frames)

    @property
    def target(self):
        """Every frame's target samples end to end."""
        return jnp.concatenate([s.target for s in self.frames])


@dataclasses.dataclass
class FrameObjective:
    """The residual function of a multi-frame fit: each frame's `Objective` (their
    selections share the first frame's start, so one y means the same values in all)."""

    objectives: list[Objective]
    photo: None = None  # photo fits take one target (`Objective.photo`)

    @property
    def scenes(self) -> list[rtjax.Scene]:
        """Each frame's start scene, at its target's size."""
        return [o.selection.scene for o in self.objectives]

    def start(self) -> list:
        """Each frame's `Objective.start`."""
        return [o.start() for o in self.objectives]

    def at(self, start: list) -> "FrameObjective":
        return dataclasses.replace(self, objectives=[o.at(s) for o, s in zip(self.objectives, start)])

    def residuals(self, y: dict, samples: FrameSamples):
        return jnp.concatenate([o.residuals(y, s) for o, s in zip(self.objectives, samples.frames)])


def same_scene(scenes: Sequence[rtjax.Scene]) -> None:
    """`FitError` unless the frames have the same spheres' kinds, lights and textures."""
    first = scenes[0].structure
    for k, scene in enumerate(scenes[1:], 1):
        s = scene.structure
        if (s.kinds, s.n_lights, s.texture_shapes) != (first.kinds, first.n_lights, first.texture_shapes):
            raise FitError(f"frame {k} differs from frame 0 in its spheres, lights or textures: a fit of several "
                           f"frames shares their free parameters, so their scenes must have the same parts")


def build_frames(scenes: Sequence[rtjax.Scene], targets: Sequence, free: str | Sequence[str],
                 spheres: Sequence[int] | None, options: FitOptions) -> Problem:
    """The `Problem` of fitting `free` of every scene in `scenes` to its target in
    `targets` (one each, in order), the free values shared: its `objective` is a
    `FrameObjective`, its pyramid's levels `FrameSamples`, its `scene` and `selection`
    the first frame's."""
    scenes, targets = list(scenes), list(targets)
    if not scenes:
        raise FitError("no frames to fit")
    if len(scenes) != len(targets):
        raise FitError(f"{len(targets)} targets for {len(scenes)} frames: give one target per frame")
    if options.photo:
        raise FitError("a photo fit takes one photo: fit several frames without photo")
    same_scene(scenes)
    problems = [Problem.build(scene, target, free, spheres, options) for scene, target in zip(scenes, targets)]
    first = problems[0]
    for k, p in enumerate(problems[1:], 1):
        if len(p.pyramid) != len(first.pyramid):
            raise FitError(f"frame {k}'s target is {p.widths[-1]} pixels wide, frame 0's {first.widths[-1]}: "
                           f"their coarse-to-fine schedules differ; give targets of one width (or --levels)")
        p.selection.start = first.selection.start  # one y, the same values in every frame
    pyramid = [FrameSamples(tuple(p.pyramid[i] for p in problems)) for i in range(len(first.pyramid))]
    objective = FrameObjective([p.objective for p in problems])
    return Problem(first.scene, first.selection, first.y0, first.jac, first.widths, pyramid, objective)


def fitted_scenes(scenes: Sequence[rtjax.Scene], selection: Selection, y: dict) -> list[rtjax.Scene]:
    """Each of `scenes` with the free values of `y` (a fit's `FitResult.y`, whose
    `selection` is given), its other parameters as they were."""
    out = []
    for scene in scenes:
        own = Selection(scene, selection.families, None)
        own.index, own.transform, own.start = selection.index, selection.transform, selection.start
        out.append(own.scene_at(y["scene"]))
    return out
