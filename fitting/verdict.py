"""A photo fit's verdict: whether its result can be believed, and how well its centres
are determined.

A fit to a photo (`FitOptions.photo`) or with a camera model (`FitOptions.nuisance`)
can converge to nonsense: a camera blurred flat, a gain at the end of its range, spheres
moved where the data no longer pins them. `judge` looks at the fit's end on its
full-size level and names every such cause:

- a camera or appearance parameter ended at an end of its plausible range
  (`fitting.photo.RANGES`; for `nuisance` fits, the same ranges applied to their
  unbounded values): the model could not explain the photo without running away;
- the residual is no better than a trivial explanation: a flat image of the target's
  mean colour, or the start's geometry under the fitted appearance and camera (the
  geometry moved without explaining anything);
- a free centre is determined more loosely than the goal a fit of a photo is held to:
  `CONFIDENCE` times its σ exceeds `LIMITS` (pixel footprints at its distance), or
  the Jacobian at the end is not finite (a singular render), so that no σ exists.

The uncertainty comes from the Jacobian J and residuals r at the end, over all n free
coordinates (appearance and camera included, so that they are marginalised out): the
Gauss–Newton covariance s²(JᵀJ)⁻¹, s² = Σr²/(m − n) ('sigma_statistical'), which takes
the m residuals as independent, and the cluster-robust (sandwich) covariance
(JᵀJ)⁻¹(Σ_b g_b g_bᵀ)(JᵀJ)⁻¹, g_b the sum of Jᵢrᵢ over the residuals in block b of
`CLUSTER` × `CLUSTER` pixels ('sigma'), which lets residuals within a block be
correlated: a photo's are (blur, JPEG, shading the model lacks), and where the
shading the model lacks pulls a silhouette one way and a shadow another, the blocks'
pulls disagree and the sandwich grows. Neither covers a bias: shading the model lacks
pulls every block the same way (depth along the view, mostly). A bias estimate is
added to the sandwich σ in quadrature ('bias_px'): the shift of the optimum, one
Gauss–Newton step from the end, when only the `EDGE_SHARE` of pixels where the free
centres' Jacobian is largest (silhouettes, shadow and reflection edges) keep their
weight, the others `OTHER_WEIGHT` of it: where the interior shading disagrees with the
edges the two optima differ. Reported per sphere in scene units and in pixels (the pixel
footprint at the sphere's distance from the eye is distance × 2·tan(ha/2)/width).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from .objective import robust
from .photo import RANGES

#: The loosest uncertainty (1σ, pixel footprints) a free centre may have, per material
#: kind: glass is seen through its refraction, its outline faint.
LIMITS = {"opaq": 1.0, "mirr": 1.0, "tmap": 1.0, "trpa": 3.0}
#: Residuals within blocks this many pixels wide are taken as correlated any way
#: (`uncertainty`'s cluster-robust covariance).
CLUSTER = 16
#: The share of pixels, those with the largest Jacobian of the free centres, that keep
#: their weight in the bias estimate (`uncertainty`).
EDGE_SHARE = 0.2
#: The weight of the other pixels in the bias estimate.
OTHER_WEIGHT = 1e-3
#: A centre is determined when this many of its σ (the cluster-robust one along its
#: worst direction, with the bias estimate in quadrature) are within its goal (`LIMITS`).
CONFIDENCE = 3.0
#: A fit's loss must be below this share of a flat image's (the target's mean colour).
FLAT_SHARE = 0.5
#: ...and below the start geometry's (with the fitted appearance) once any centre moved
#: more than this many pixel footprints.
MOVED_PX = 0.5
#: A centre's σ is along the view (`undetermined`) when σ along the view is at least this
#: share of σ along its worst direction.
ALONG_VIEW = 0.9
#: How close to an end of its range (as a share of the range) a parameter counts as at it.
AT_BOUND = 0.01


@dataclasses.dataclass
class Verdict:
    """What `judge` found.

    - `ok`: no cause.
    - `causes`: one line per cause, each naming it.
    - `losses`: ½·mean(r²) on the full-size level at the end ('end'), at the start's
      geometry with the fitted appearance ('start'), and of a flat image ('flat').
    - `spheres`: per free centre (`uncertainty`): index, kind, σ per axis, along the
      worst direction (scene units and pixels) and along the view (pixels), the
      Gauss–Newton σ, the bias estimate and the σ the verdict uses (pixels), how far it
      moved (scene units and pixels), its footprint (scene units per pixel) and goal
      (pixels).
    - `bounds`: the parameters that ended at a bound, with their values.
    """

    ok: bool
    causes: list[str]
    losses: dict[str, float]
    spheres: list[dict]
    bounds: dict[str, float]

    @property
    def message(self) -> str:
        if self.ok:
            return "supported: every parameter inside its range, the residual below the trivial ones', every centre determined"
        return "; ".join(self.causes)

    def as_dict(self) -> dict:
        return {"ok": self.ok, "message": self.message, "causes": self.causes, "losses": self.losses,
                "spheres": self.spheres, "bounds": self.bounds}


def footprints(params, width: int) -> np.ndarray:
    """Each sphere's pixel footprint (scene units per pixel) at its distance from the eye."""
    eye = np.asarray(params.eye, np.float64)
    distance = np.linalg.norm(np.asarray(params.centers, np.float64) - eye, axis=1)
    return distance * 2 * math.tan(math.radians(float(np.asarray(params.vang)[0])) / 2) / width


def bounds_reached(y: dict, photo=None) -> dict[str, float]:
    """The camera and appearance parameters (photo fits: y['photo'], named by `photo`,
    a `fitting.photo.Photo`, where given; nuisance fits: y['nuisance'], unbounded,
    against the same ranges) that ended at an artificial end of their range, with
    their values."""
    out = {}
    for k, u in y.get("photo", {}).items():
        r = RANGES[k]
        share = np.atleast_1d(r.share(np.asarray(u)))
        value = np.atleast_1d(np.asarray(r.value(jnp.asarray(u)), np.float64))
        for n, (z, v) in enumerate(zip(share.ravel(), value.ravel())):
            if (r.flags[0] and z < AT_BOUND) or (r.flags[1] and z > 1 - AT_BOUND):
                out[photo.label(k, n, share.size) if photo is not None else k if share.size == 1 else f"{k}[{n}]"] = float(v)
    for k, u in y.get("nuisance", {}).items():
        if k not in RANGES:
            continue
        r, v = RANGES[k], float(np.exp(np.asarray(u)))
        lo, hi = r.lo + AT_BOUND * (r.hi - r.lo), r.hi - AT_BOUND * (r.hi - r.lo)
        if (r.flags[0] and v < lo) or (r.flags[1] and v > hi):
            out[k] = v
    return out


def judge(problem, steps, y: dict, end: tuple[float, object] | None = None) -> Verdict:
    """The verdict on a fit of `problem` (a `fitting.problem.Problem`) that ended at `y`.

    `steps`: the fit's `solve.Steps` (one start's or several starts'); its `evaluate`
    runs the full-size level at `y` and at the start's geometry with the fit's own
    compiled programs (nothing new is compiled; several starts' evaluate both in one
    call); the Jacobian comes from the step's linearisation (forward-mode fits; 'bwd'
    fits report no uncertainty). `end`: (loss, solver state) of the fit's last step on
    that level where it ended at `y` (`solve.Single.end`): the same numbers, one
    full-size evaluation saved."""
    level = problem.pyramid[-1]
    objective = problem.objective
    points = [dict(y, scene=problem.y0["scene"])] if end is not None else [y, dict(y, scene=problem.y0["scene"])]
    evaluated = steps.evaluate(points, level)
    end, state = end if end is not None else evaluated[0]
    start = evaluated[-1][0]
    target = np.asarray(level.target, np.float64)
    weight = np.asarray(level.weight, np.float64)
    mean = (target * weight).sum(0) / max(weight.sum(), 1e-12)
    scale = objective.loss_scale * float(level.scale) / 255
    r = np.asarray(robust(jnp.asarray((mean - target) * weight / 255), objective.loss, scale))
    flat = float(0.5 * np.mean(r**2))
    losses = {"end": end, "start": start, "flat": flat}

    causes, spheres = [], []
    if problem.jac == "fwd" and hasattr(state.f_info, "jac"):  # a least-squares solver's forward-mode Jacobian
        jac = np.asarray(state.f_info.jac.as_matrix(), np.float64)
        residual = np.asarray(state.f_info.residual, np.float64).ravel()
        bad = int(np.count_nonzero(~np.isfinite(jac))) + int(np.count_nonzero(~np.isfinite(residual)))
        if bad:
            causes.append(f"undetermined: the Jacobian and residuals at the end hold {bad} non-finite values "
                          "(the render is singular there): no uncertainty can be given")
        else:
            spheres = uncertainty(problem, jac, residual, y)
    bounds = bounds_reached(y, objective.photo)
    if bounds:
        causes.append("ran away: " + ", ".join(f"{k} = {v:.4g}" for k, v in bounds.items())
                      + " ended at a bound of the plausible range: the model cannot explain the photo")
    rms = {k: math.sqrt(2 * v) * 255 if math.isfinite(v) else math.inf for k, v in losses.items()}
    if not end < FLAT_SHARE * flat:
        causes.append(f"no better than a flat image: RMS residual {rms['end']:.3g} levels against a flat image's "
                      f"{rms['flat']:.3g}")
    moved = max((s["moved_px"] for s in spheres), default=0.0)
    if moved > MOVED_PX and not end < start:
        causes.append(f"no better than the start: centres moved up to {moved:.2f} px but the RMS residual "
                      f"{rms['end']:.3g} levels is not below the start geometry's {rms['start']:.3g}")
    loose = [s for s in spheres if not CONFIDENCE * s["sigma_total_px"] <= s["limit_px"]]
    if loose:
        causes.append(undetermined(loose))
    return Verdict(ok=not causes, causes=causes, losses=losses, spheres=spheres, bounds=bounds)


def undetermined(loose: list[dict]) -> str:
    """The verdict's cause for spheres (`uncertainty`'s entries) not determined to their
    goal: each one's σ (the bias estimate in quadrature; σ and bias apart in the report),
    goal and move, marking whether its worst direction is along the view (`ALONG_VIEW`:
    a centre's outline fixes it across the view, and only its size and what it touches
    or shades fix its depth); if every one's is, one closing clause says so instead."""
    def along(s):
        return s["sigma_depth_px"] >= ALONG_VIEW * s["sigma_px"]

    everywhere = all(along(s) for s in loose)
    text = "undetermined: " + ", ".join(
        f"sphere {s['index']} (σ {s['sigma_total_px']:.3g} px{' along the view' if along(s) and not everywhere else ''}, "
        f"{CONFIDENCE:g}σ over its goal of {s['limit_px']:g}; moved {s['moved_px']:.2f} px)" for s in loose)
    if everywhere:
        text += "; what the photo leaves open is depth along the view (across it the outlines fix a centre far better)"
    return text


def uncertainty(problem, jac: np.ndarray, r: np.ndarray, y: dict) -> list[dict]:
    """Per free centre at `y`, σ from the cluster-robust covariance (per axis, 'sigma';
    along the worst direction in scene units and pixels, 'sigma_units', 'sigma_px';
    along the view, 'sigma_depth_px') and from the Gauss–Newton one
    ('sigma_statistical_px'), the bias estimate ('bias_px', `EDGE_SHARE`) and σ with
    it in quadrature ('sigma_total_px', what the verdict uses); `jac` (m × n) and the
    residuals `r` (m) are a solver's linearisation at `y`, finite."""
    selection = problem.selection
    if "centers" not in selection.index:
        return []
    m, n = jac.shape
    flat, unravel = jax.flatten_util.ravel_pytree(y)
    where = unravel(jnp.arange(flat.size, dtype=flat.dtype))
    columns = np.asarray(where["scene"]["centers"], np.float64).astype(int).reshape(-1, 3)
    s2 = float(r @ r) / max(m - n, 1)
    normal = jac.T @ jac
    ridge = 1e-12 * max(float(np.trace(normal)) / max(n, 1), 1e-300)
    inverse = np.linalg.inv(normal + ridge * np.eye(n))
    cov = s2 * inverse
    # cluster-robust (sandwich) covariance: residuals within a CLUSTER-pixel block may be
    # correlated any way; blocks are taken as independent
    xy = np.asarray(problem.pyramid[-1].xy, np.float64)
    block = (xy[:, 1] // CLUSTER).astype(np.int64) * (int(problem.scene.structure.width // CLUSTER) + 1) \
        + (xy[:, 0] // CLUSTER).astype(np.int64)
    scores = jac * r[:, None]
    sums = np.zeros((int(block.max()) + 1, n))
    np.add.at(sums, np.repeat(block, m // len(block)), scores)
    robust_cov = inverse @ (sums.T @ sums) @ inverse
    # the bias estimate: the Gauss-Newton shift of the optimum with the edge pixels alone weighted
    per_pixel = np.abs(jac[:, columns.ravel()]).reshape(len(block), -1).sum(1)
    edge = np.repeat(np.where(per_pixel > np.quantile(per_pixel, 1 - EDGE_SHARE), 1.0, OTHER_WEIGHT), m // len(block))
    weighted = jac.T @ (jac * edge[:, None])
    shift = -np.linalg.solve(weighted + ridge * np.eye(n), jac.T @ (edge * r))
    unit = selection.transform["centers"].scale  # scene units per solver unit (an affine family)
    width = problem.scene.structure.width
    start = np.asarray(selection.scene.params.centers, np.float64)
    fitted_params = selection.params(y["scene"])
    fitted = np.asarray(fitted_params.centers, np.float64)
    foot = footprints(fitted_params, width)
    eye = np.asarray(fitted_params.eye, np.float64)
    kinds = problem.scene.structure.kinds
    out = []
    for j, i in enumerate(selection.index["centers"]):
        stat = unit**2 * cov[np.ix_(columns[j], columns[j])]
        robust = unit**2 * robust_cov[np.ix_(columns[j], columns[j])]
        worst = math.sqrt(max(float(np.linalg.eigvalsh(robust).max()), 0.0))
        stat_worst = math.sqrt(max(float(np.linalg.eigvalsh(stat).max()), 0.0))
        view = (fitted[i] - eye) / np.linalg.norm(fitted[i] - eye)
        moved = float(np.linalg.norm(fitted[i] - start[i]))
        bias = unit * float(np.linalg.norm(shift[columns[j]])) / foot[i]
        out.append({
            "index": int(i), "kind": kinds[i],
            "sigma": np.sqrt(np.maximum(np.diag(robust), 0.0)).tolist(), "sigma_units": worst,
            "sigma_px": worst / foot[i], "sigma_statistical_px": stat_worst / foot[i],
            "sigma_depth_px": math.sqrt(max(float(view @ robust @ view), 0.0)) / foot[i],
            "bias_px": bias, "sigma_total_px": math.hypot(worst / foot[i], bias),
            "moved_units": moved, "moved_px": moved / foot[i],
            "footprint": float(foot[i]), "limit_px": LIMITS.get(kinds[i], 1.0),
        })
    return out
