"""Residuals: render(parameters) − target, per pixel and channel.

The model image is the silhouette-aware render (so residuals have derivatives through
edges), optionally passed through a camera model whose nuisance parameters (exposure
gain, gamma, blur, JPEG's chroma blur) a photo-like target may need; residuals can be
masked and made robust to outliers (Huber or Cauchy, as √(2ρ(r)) so least-squares
solvers minimise Σρ). A pyramid of area-averaged targets gives the coarse-to-fine
schedule.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .errors import FitError
from .select import Selection

#: The camera model's nuisance parameters (`camera`); `nuisance=("camera",)`: all of them.
NUISANCE = ("gain", "gamma", "blur", "chroma", "order")
#: Start values of the nuisance parameters (the solver moves their logs; the logit of
#: 'order', a share): no gain or gamma change; a Gaussian blur of σ = 0.3 pixels; a
#: further chroma blur of 0.5 pixels; the blur half before, half after the response.
NUISANCE_START = {"gain": 1.0, "gamma": 1.0, "blur": 0.3, "chroma": 0.5, "order": 0.5}
#: The whole-image levels' render (`rtjax.render`'s options): the silhouette-aware mode
#: with 1-pixel boxes, one box per pixel whatever the image's size (the fits were measured
#: so; on small images sub-boxes cost the gradient's compile half as much again).
WHOLE_IMAGE_RENDER = {"edges": 1.0, "subdivide": 0}
#: Static radius (pixels) of the Gaussian kernels `camera` applies: exact to σ ≈ 2.7.
BLUR_RADIUS = 8
#: JPEG's RGB → YCbCr (ITU-R BT.601, full range), and the projection of an RGB colour
#: on its chroma (the part Cb and Cr carry, with Y = 0).
YCBCR = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
CHROMA = np.linalg.inv(YCBCR) @ np.diag([0.0, 1.0, 1.0]) @ YCBCR
LOSSES = ("l2", "huber", "cauchy")
#: Levels coarser than the image widen the robust loss's scale by this factor (not with
#: a fitted blur): their area-averaged pixels mix both sides of edges, so residuals of
#: tens of levels are signal there, not outliers.
COARSE_SCALE = 3.0
#: A fit matched at pixel centres ends with a refinement on the same samples whose robust
#: scale is this factor of the fit's (`fitting.problem.Problem`): at the truth its
#: residuals are the target's rounding alone, and the few samples the sided model cannot
#: match no longer outweigh the rest.
EXACT_SCALE = 0.1
#: ...which takes over once the wider level's RMS residual is below this fraction of the
#: fit's scale, or it converged (`fitting.solve.level_budget`).
NARROW_BELOW = 0.3
#: With a fitted blur (a photo-like target), edges are found on the target blurred by
#: this many pixels (`make_levels`' `denoise`): noise and JPEG blocks would look like edges.
DENOISE = 1.0


def load_target(target, *, assignment_order: bool = False) -> np.ndarray:
    """A target image as float (H, W, 3) in 0..255: a path (Sun raster or anything
    OpenImageIO reads) or an array."""
    if isinstance(target, (str, bytes)) or hasattr(target, "__fspath__"):
        return np.asarray(rtjax.load_image(target, assignment_order=assignment_order), np.float64)  # finite, or refused
    a = np.asarray(target, np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise FitError(f"target image has shape {a.shape}; expected (height, width, 3)")
    bad = int(np.count_nonzero(~np.isfinite(a)))
    if bad:  # every residual would be NaN
        raise FitError(f"target image has {bad} non-finite values (NaN or infinity); a target must be finite "
                       "everywhere (give such pixels any value and a mask)")
    return a


def match_size(scene: rtjax.Scene, target: np.ndarray) -> rtjax.Scene:
    """The scene at the target's size: the deck's image size follows the target when
    the aspect ratio agrees (the height the deck's `vang` gives for the target's width);
    otherwise a clear error."""
    h, w = target.shape[:2]
    s = scene.structure
    if (h, w) == (s.height, s.width):
        return scene
    ha, va = (float(x) for x in np.asarray(scene.params.vang))
    expect = rtjax.image_height(w, ha, va)
    if abs(expect - h) > 1:
        raise FitError(
            f"the target is {w}×{h} (aspect {w / h:.3f}) but the deck's view (vang {ha:g} {va:g}) is "
            f"{s.width}×{s.height} (aspect {s.width / s.height:.3f}): the aspect ratios differ"
        )
    return scene.resized(w, h)


def area_matrix(n_out: int, n_in: int) -> np.ndarray:
    """(n_out, n_in) weights averaging each output cell's footprint on the input grid."""
    edges = np.linspace(0, n_in, n_out + 1)
    m = np.zeros((n_out, n_in))
    for i in range(n_out):
        lo, hi = edges[i], edges[i + 1]
        for j in range(int(np.floor(lo)), min(n_in, int(np.ceil(hi)))):
            m[i, j] = min(hi, j + 1) - max(lo, j)
        m[i] /= m[i].sum()
    return m


def downsample(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-average an (H, W, C) image to (height, width, C)."""
    a = area_matrix(height, image.shape[0])
    b = area_matrix(width, image.shape[1])
    return np.einsum("jw,iwc->ijc", b, np.einsum("ih,hwc->iwc", a, image))  # two small products, not one 5-index sum


def schedule_widths(width: int, levels: int | Sequence[int] | None, blurred: bool = False) -> list[int]:
    """Image widths from coarse to fine, ending at the full width.

    Default: an eighth, a quarter and the full width (a quarter, a half and the full
    width where an eighth would be below 48 pixels): the coarse levels do the
    travelling, cheaply, and the full-size level, matched at pixel centres, the rest.
    `blurred` (a fitted blur, whose full-size level renders the whole image through
    `camera`): three levels halving the width, so that a half-size level brings it
    closer first. An int k gives k levels halving the width (none below 48 pixels); a
    sequence is taken as given (sorted, capped at the full width)."""
    if levels is None and blurred:
        levels = 3
    if levels is None:
        k = next((k for k in (3, 2, 1) if width >> k >= 48), 0)
        return sorted({width >> k, width >> max(k - 1, 0), width}) if k else [width]
    if isinstance(levels, int):
        k = int(levels)
        out = [width]
        while len(out) < k and out[0] // 2 >= 48:
            out.insert(0, out[0] // 2)
        return out
    out = sorted({min(int(w), width) for w in levels if int(w) >= 1})
    if not out or out[-1] != width:
        out.append(width)
    return out


def robust(r, loss: str, scale: float):
    """Residuals r' with Σr'² = 2Σρ(r): plain (l2), Huber or Cauchy with scale `scale`."""
    if loss == "l2":
        return r
    a = jnp.abs(r)
    if loss == "huber":
        rho = jnp.where(a <= scale, 0.5 * r * r, scale * (a - 0.5 * scale))
    elif loss == "cauchy":
        rho = 0.5 * scale**2 * jnp.log1p((r / scale) ** 2)
    else:
        raise FitError(f"unknown loss {loss!r}; choose from {', '.join(LOSSES)}")
    ok = rho > 0
    return jnp.where(ok, jnp.sign(r) * jnp.sqrt(jnp.where(ok, 2 * rho, 1)), 0)


def nuisance_values(nuisance: dict, *, logs: bool = True) -> dict:
    """The nuisance parameters in their own units from the solver's coordinates (logs;
    the logit of 'order'), or as given (`logs=False`)."""
    if not logs:
        return {k: jnp.asarray(v) for k, v in nuisance.items()}
    return {k: jax.nn.sigmoid(v) if k == "order" else jnp.exp(v) for k, v in nuisance.items()}


def apply_nuisance(image, nuisance: dict, *, logs: bool = False):
    """A camera's response: 255·(gain·I/255)^γ, per colour, in the units
    `FitResult.nuisance` gives (`logs=True`: the solver's coordinates). The other
    entries act on whole images (`camera`) or on the render's edges (`Objective.model`)."""
    if not nuisance:
        return image
    x = image / 255
    value = nuisance_values(nuisance, logs=logs)
    if "gain" in value:
        x = x * value["gain"]
    if "gamma" in value:
        pos = x > 1e-6
        xs = jnp.where(pos, x, 1)
        x = jnp.where(pos, jnp.exp(value["gamma"] * jnp.log(xs)), 0)
    return 255 * jnp.clip(x, 0, 1)


def gaussian_blur(image, sigma, radius: int = BLUR_RADIUS):
    """`smooth` in JAX, differentiable in σ (traced), truncated at a static `radius`."""
    return _gaussian(jnp, jnp.asarray(image), sigma, radius)


def camera(image, nuisance: dict, *, logs: bool = False):
    """A photo of a render (H, W, 3): what a fit with nuisance parameters matches a
    photo-like target with. 'blur' (σ, pixels): a Gaussian blur, taken a share 'order'
    after the response (`apply_nuisance`) and the rest before it (a lens blurs light
    before a camera's response; an image editor blurs its output; default: before);
    'chroma' (σ, pixels): a further blur of the output's chroma alone (Cb, Cr of JPEG's
    YCbCr), as JPEG's 4:2:0 chroma subsampling makes (about 1 pixel). Units as
    `apply_nuisance`."""
    value = nuisance_values(nuisance, logs=logs)
    given = {k: v for k, v in value.items() if k in ("gain", "gamma")}
    if "blur" in value:
        out = apply_nuisance(gaussian_blur(image, value["blur"]), given)
        if "order" in value:
            late = gaussian_blur(apply_nuisance(image, given), value["blur"])
            out = out + value["order"] * (late - out)
    else:
        out = apply_nuisance(image, given)
    if "chroma" in value:
        out = chroma_blur(out, value["chroma"])
    return out


def chroma_blur(image, sigma):
    """`image` (H, W, 3) with its chroma alone (Cb, Cr of JPEG's YCbCr) blurred by σ
    pixels: what JPEG's 4:2:0 chroma subsampling does to a photo."""
    return image + (gaussian_blur(image, sigma) - image) @ jnp.asarray(CHROMA.T, image.dtype)


class Samples(NamedTuple):
    """One pyramid level: K image positions (pixels of the full image), the spacing they
    stand for, and the target (and mask weight) there. K is the same on every level but
    an exact or a whole one, so one compiled residual function serves them all (`exact`
    and `whole` are static: such a level has its own)."""

    xy: jnp.ndarray  # (K, 2)
    step: jnp.ndarray  # ()
    target: jnp.ndarray  # (K, 3)
    weight: jnp.ndarray  # (K, 1)
    width: jnp.ndarray  # () edge width in this level's pixels
    exact: bool  # matched at pixel centres (see `Objective.model`)
    scale: jnp.ndarray = 1.0  # () the robust loss's scale, as a factor of the fit's (`EXACT_SCALE`)
    whole: bool = False  # the model renders the whole full-size image, then looks at xy (a photo's `camera` model)
    plain: bool = False  # the model is the plain render at the samples (no edge filter: `texels.plain_level`)


def level_grid(width: int, height: int, w: int) -> tuple[int, np.ndarray, float]:
    """A level of `w` pixels across: its height, the positions of its pixel centres in
    full-image pixels (h·w, 2), and its pixel size in full-image pixels."""
    h = max(1, int(round(height * w / width)))
    fx, fy = width / w, height / h
    i, j = np.meshgrid(np.arange(w), np.arange(h), indexing="xy")
    xy = np.stack([(i.ravel() + 0.5) * fx, (j.ravel() + 0.5) * fy], -1)
    return h, xy, fx


def edge_band(image: np.ndarray, threshold: float = 6.0, grow: int = 2) -> np.ndarray:
    """Pixels (H, W) near a colour edge of `image`: the largest difference to a
    neighbour exceeds `threshold` levels, grown by `grow` pixels."""
    img = image.astype(np.float64)
    contrast = np.zeros(img.shape[:2])
    for axis in (0, 1):
        diff = np.abs(np.diff(img, axis=axis)).max(axis=2)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        contrast = np.maximum(contrast, np.pad(diff, pad))
        pad[axis] = (0, 1)
        contrast = np.maximum(contrast, np.pad(diff, pad))
    band = contrast > threshold
    for _ in range(grow):
        grown = band.copy()
        grown[1:] |= band[:-1]
        grown[:-1] |= band[1:]
        grown[:, 1:] |= band[:, :-1]
        grown[:, :-1] |= band[:, 1:]
        band = grown
    return band


def _gaussian(xp, image, sigma, radius: int):
    """A Gaussian blur of σ pixels over the first two axes, truncated at `radius`, edges
    extended, with NumPy or jax.numpy (`xp`): `smooth` and `gaussian_blur`."""
    k = xp.exp(-0.5 * (xp.arange(-radius, radius + 1, dtype=image.dtype) / sigma) ** 2)
    k = k / xp.sum(k)
    for axis in (0, 1):
        pad = [(0, 0)] * image.ndim
        pad[axis] = (radius, radius)
        padded = xp.pad(image, pad, mode="edge")
        n = image.shape[axis]
        image = sum(k[i] * padded[(slice(None),) * axis + (slice(i, i + n),)] for i in range(2 * radius + 1))
    return image


def smooth(image, sigma: float) -> np.ndarray:
    """A Gaussian blur of σ pixels over the first two axes, truncated at ⌈3σ⌉ (edges
    extended), in NumPy: finding a photo's edges (`make_levels`), making a photo-like
    target."""
    return _gaussian(np, np.asarray(image, np.float64), sigma, int(np.ceil(3 * sigma)))


def make_levels(target: np.ndarray, weight: np.ndarray, widths: Sequence[int], edges: Sequence[float], dtype, seed: int = 0,
                exact: Sequence[bool] = (), exact_share: float = 0.25, denoise: float = 0.0,
                whole: Sequence[bool] = ()) -> list[Samples]:
    """The coarse-to-fine pyramid as `Samples` of one size K (the coarsest level's pixel
    count): the coarsest level is its whole grid of area-averaged pixels; finer levels
    take K of their pixels, those near the target's edges first (where positions are
    decided), then a random spread of the rest. `exact`: per level, whether it is
    matched at pixel centres (default: none); such a level takes every pixel near an
    edge and as many others while the total stays within `exact_share` of its pixels
    (and at least K in all): at pixel centres, positions are decided by which side of
    each edge pixel centres fall on, so every one counts. `denoise` (σ in pixels): find
    edges on the target blurred by that much (a photo's noise and JPEG blocks would make
    nearly every pixel look like an edge). `whole`: per level, whether the model renders
    the whole full-size image (a photo's level, `Objective.model`); it takes its samples
    as an exact level does."""
    height, width = target.shape[:2]
    rng = np.random.default_rng(seed)
    levels = []
    k = None
    exact = list(exact) + [False] * (len(widths) - len(exact))
    whole = list(whole) + [False] * (len(widths) - len(whole))
    for w, e, x, every in zip(widths, edges, exact, whole):
        h, xy, step = level_grid(width, height, w)
        all_edges = x or every  # takes every edge pixel
        if every and (h, w) != (height, width):
            raise FitError(f"a whole level is the full-size image ({width} pixels wide), not {w}")
        small = target if (h, w) == (height, width) else downsample(target, h, w)
        wsmall = weight if (h, w) == (height, width) else downsample(weight, h, w)
        t, wt = small.reshape(-1, 3), wsmall.reshape(-1, 1)
        band = np.flatnonzero(edge_band(smooth(small, denoise) if denoise else small).ravel())
        size = k if k is not None else len(xy)
        if all_edges:  # every edge pixel, and as many others up to `exact_share` of them all
            size = max(size, len(band), min(2 * len(band), int(exact_share * len(xy))))
        else:
            k = size
        take = len(band) if all_edges else min(len(band), (3 * size) // 4)
        if len(xy) <= size:  # the coarsest level, or one no larger: all of it
            pick = np.arange(len(xy))
        else:
            rest = np.setdiff1d(np.arange(len(xy)), band)
            take = max(take, size - len(rest))  # a level so small that nearly every pixel is near an edge
            pick = np.concatenate([rng.choice(band, take, replace=False), rng.choice(rest, size - take, replace=False)])
        levels.append(Samples(*(jnp.asarray(a, dtype) for a in (xy[pick], step, t[pick], wt[pick], e)), bool(x),
                              jnp.asarray(1.0, dtype), bool(every)))
    return levels


class Start(NamedTuple):
    """What a residual function reads of its fit's start (`Objective.start`): the start
    scene's parameters, the free values' start, and a photo's footprints (or None)."""

    params: rtjax.Params
    values: dict
    footprint: np.ndarray | None


@dataclasses.dataclass
class Objective:
    """The residual function r(y, samples): one for every level (samples are arguments)."""

    selection: Selection
    depth: int | None
    loss: str
    loss_scale: float
    photo: object = None  # a `fitting.photo.Photo`: y["photo"] holds its parameters

    def start(self) -> Start:
        """The arrays this objective reads of its start. `solvers.Stepper` passes them to
        its compiled programs as arguments, not constants, so that a fit of the same
        structure from another start (another photo of the same deck, say) lowers to the
        same program and finds it in the compilation cache."""
        return Start(self.selection.scene.params, self.selection.start,
                     None if self.photo is None else self.photo.footprint)

    def at(self, start: Start) -> "Objective":
        """This objective from `start` (traced arrays, inside a compiled program)."""
        photo = None if self.photo is None else self.photo.at(start.footprint)
        return dataclasses.replace(self, selection=self.selection.at(start.params, start.values), photo=photo)

    def model(self, y: dict, samples: Samples):
        """The model's colours at the samples: the silhouette-aware render, or on an
        `exact` level its sided form, which matches a target sampled at pixel centres
        (as `rtjax render` makes them) exactly at the truth.

        A box-filtered edge pixel differs from such a target even at the truth: there
        the target holds the colour of whichever side the pixel's centre lies on. The
        sided form gives the colour at the pixel's centre where the target is nearer it
        than the colour traced on the edge's other side (exact at the truth, thin
        features and two-edge pixels included), and where the target shows the other
        side, centre + (1 − |x|)·(other − centre) (x: the centre's signed distance to
        the edge in box widths): a penalty linear in how far the centre lies on the
        wrong side, within one box width, whose derivative moves the edge across it.
        Shadow edges alike: `flipped` is the centre's colour across its nearest one.

        With a fitted blur (a photo-like target: no sharp edges to match) the coarse
        levels widen the edges' box filter to the blur's variance, and the full-size
        level is `whole`: the whole image, each pixel box-filtered at its edges
        (`rtjax.render`'s silhouette-aware mode, 1 pixel wide), through `camera` (the
        blur a true Gaussian, in the response's order, and JPEG's chroma blur), looked
        at in the level's pixels. A photo (`fitting.photo.Photo`) alike, with its
        appearance parameters in the scene and its own camera.

        Computed in `stages`' two stages, the render and the camera after it."""
        s = self.stages(y, samples)
        first, second = s.split(y)
        return s.camera(s.render(first), second)

    def _kind(self, y: dict, samples: Samples) -> str:
        """Which of `model`'s forms the level `samples` takes (static)."""
        if self.photo is not None:
            return "photo whole" if samples.whole else "photo"
        if samples.plain:
            return "plain"
        if samples.whole:
            return "whole"
        if "blur" in y.get("nuisance", {}):
            return "blurred"
        return "box" if not samples.exact else "sided"

    def stages(self, y: dict, samples: Samples) -> "Stages":
        """`residuals` on the level `samples` as a render and the camera after it
        (`Stages`), so that `solvers.with_dense_jacobian` pushes tangents through the
        render for the parameters it reads alone: the camera's (a photo's `CAMERA`, the
        nuisance parameters) act on its output only, but the blur of a level coarser
        than the image, which widens the render's edge filter."""
        kind = self._kind(y, samples)
        dtype = jax.tree_util.tree_leaves(y)[0].dtype  # the solver's float type (see Selection.y0)
        scale = self.loss_scale * samples.scale
        if not samples.exact and "blur" not in y.get("nuisance", {}) and self.photo is None:
            scale = scale * jnp.where(samples.step > 1, COARSE_SCALE, 1.0)  # a level coarser than the image

        def split(y):
            def after(group):  # the group's entries that only the camera reads
                return {k: v for k, v in y[group].items() if k != "blur" or samples.whole}

            groups = [g for g in ("photo", "nuisance") if g in y]
            camera_part = {g: after(g) for g in groups}
            if self.photo is not None:
                camera_part["photo"] = {k: v for k, v in camera_part["photo"].items() if k in self.photo.camera_keys}
            rest = {g: {k: v for k, v in y[g].items() if k not in camera_part[g]} for g in groups}
            return {**y, **rest}, camera_part

        def render(first):
            return self._render(kind, first, samples)

        def camera(rendered, second):
            return self._camera(kind, rendered, second, samples)

        def finish(rendered, second):
            r = (camera(rendered, second) - samples.target) * samples.weight / 255
            return robust(r, self.loss, scale / 255).astype(dtype)

        return Stages(split, render, camera, finish)

    def _render(self, kind: str, y: dict, samples: Samples):
        """The render stage of `model` (y: the part `stages` gives it)."""
        scene = rtjax.Scene(self.selection.scene.structure, self.selection.params(y["scene"]))
        if self.photo is not None:
            scene = rtjax.Scene(scene.structure, self.photo.scene(scene.params, y["photo"]))
        if kind in ("photo whole", "whole"):
            return rtjax.render(scene, depth=self.depth, **WHOLE_IMAGE_RENDER)
        if kind == "sided":
            return rtjax.edge_samples(scene, samples.xy, step=samples.step, depth=self.depth, edges=samples.width)
        edges = 0.0 if kind == "plain" else samples.width
        if kind in ("photo", "blurred"):
            # coarse levels: the blur widens the edges' box filter (a box √12·σ wide has
            # the same variance; widths add in quadrature)
            blur = self.photo.values(y["photo"])["blur"] if kind == "photo" else jnp.exp(y["nuisance"]["blur"])
            edges = jnp.sqrt(samples.width**2 + 12 * (blur / samples.step) ** 2)
        return rtjax.render_samples(scene, samples.xy, step=samples.step, depth=self.depth, edges=edges)

    def _camera(self, kind: str, rendered, y: dict, samples: Samples):
        """The camera stage of `model`: the render's output `rendered` to the model's
        colours at the samples (y: the part `stages` gives it)."""
        if kind in ("photo whole", "whole"):
            image = self.photo.camera(rendered, y["photo"]) if kind == "photo whole" else \
                camera(rendered, y["nuisance"], logs=True)
            i, j = (jnp.floor(samples.xy[:, a]).astype(jnp.int32) for a in (0, 1))
            return image[j, i]
        if kind == "photo":
            return self.photo.camera_at(rendered, samples.xy, y["photo"])
        nuisance = y.get("nuisance", {})
        if kind != "sided":
            return apply_nuisance(rendered, nuisance, logs=True)
        e = rendered
        centre, inside, outside, flipped = (apply_nuisance(c, nuisance, logs=True)
                                            for c in (e.centre, e.inside, e.outside, e.flipped))
        across = jnp.where((e.x > 0)[:, None], outside, inside)  # the silhouette's side the centre is not on
        # the side the target shows: the centre's, across the silhouette, or across the
        # shadow edge (whichever colour is nearest the target's)
        miss = [jnp.sum((samples.target - jax.lax.stop_gradient(c)) ** 2, -1) for c in (centre, across, flipped)]
        shows = jnp.argmin(jnp.stack(miss), axis=0)

        def towards(side, x):  # the share of the other side: 1 − |x| where the target shows it
            return jnp.where(shows == side, jnp.clip(1 - jnp.abs(x), 0, 1), 0)[:, None]

        return centre + towards(1, e.x) * (across - centre) + towards(2, e.shadow_x) * (flipped - centre)

    def residuals(self, y: dict, samples: Samples):
        """(model − target)·weight/255 at the samples, made robust (`robust`), in the
        solver's float type whatever the render's precision."""
        s = self.stages(y, samples)
        first, second = s.split(y)
        return s.finish(s.render(first), second)


class Stages(NamedTuple):
    """A residual function in two stages (`Objective.stages`): r(y) = finish(render(a), b)
    with (a, b) = split(y), where `render` reads only a and `finish` (the camera, then
    the residual) only b and the render's output; `camera` is finish's first part, the
    model's colours."""

    split: Callable[[dict], tuple[dict, dict]]
    render: Callable[[dict], object]
    camera: Callable[[object, dict], jnp.ndarray]
    finish: Callable[[object, dict], jnp.ndarray]


def nuisance_names(names: Sequence[str]) -> tuple[str, ...]:
    """The nuisance parameters asked for, in `NUISANCE`'s order ('camera': all)."""
    names = [n.strip() for n in names if n.strip()]
    bad = [n for n in names if n not in NUISANCE + ("camera",)]
    if bad:
        raise FitError(f"unknown nuisance parameter {bad[0]!r}; choose from {', '.join(NUISANCE)} or camera (all)")
    if "camera" in names:
        names = NUISANCE
    if ("chroma" in names or "order" in names) and "blur" not in names:
        raise FitError("the nuisance parameters chroma and order model a photo's blur: fit blur with them")
    return tuple(n for n in NUISANCE if n in names)


def nuisance_y0(names: Sequence[str], dtype) -> dict:
    """The nuisance parameters' start (`NUISANCE_START`) in the solver's coordinates."""
    start = {n: NUISANCE_START[n] for n in nuisance_names(names)}
    return {n: jnp.asarray(np.log(v / (1 - v)) if n == "order" else np.log(v), dtype) for n, v in start.items()}


def prepare_mask(mask, height: int, width: int) -> np.ndarray:
    """A mask (H, W) or (H, W, 1/3) of weights in [0, 1] (True: counted), or all ones."""
    if mask is None:
        return np.ones((height, width, 1))
    m = np.asarray(rtjax.load_image(mask) / 255 if isinstance(mask, str) else mask, np.float64)
    if m.ndim == 3:
        m = m.mean(axis=2)
    if m.shape != (height, width):
        size = f"{m.shape[1]}×{m.shape[0]}" if m.ndim == 2 else f"of shape {m.shape}"
        raise FitError(f"the mask is {size}, the target {width}×{height}")
    if not (np.all(np.isfinite(m)) and m.min() >= 0 and m.max() <= 1):
        raise FitError("the mask's weights must be numbers in [0, 1] (0: ignored, 1: counted)")
    if not m.any():
        raise FitError("the mask leaves no pixel to fit: every weight is 0")
    return m[..., None]
