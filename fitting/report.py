"""What a fit leaves behind: the summary table, the JSON report, the convergence plot,
the fitted deck and the fitted image; for a multi-start fit, its summary line and report entry."""

from __future__ import annotations

import json
import math
import os

import numpy as np

import rtjax

from .objective import NUISANCE_START
from .solve import FitResult, MultiStartResult


def _fmt(v) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"
    return f"{v:.6g}"


def table_text(result: FitResult) -> str:
    """A fixed-width table: parameter, start → fitted, then the solver's result."""
    rows = result.table()
    for name, value in result.nuisance.items():
        rows.append((f"nuisance {name}", NUISANCE_START[name], value))
    width = max([len(r[0]) for r in rows] + [9])
    lines = [f"{'parameter':<{width}}  start → fitted"]
    lines += [f"{name:<{width}}  {_fmt(a)} → {_fmt(b)}" for name, a, b in rows]
    loss = result.loss
    if result.texels is not None:
        lines += result.texels.lines()
    lines.append(
        f"solver {result.solver}: {result.result} ({result.message}) after {result.steps} iterations, "
        f"{result.times['total']:.1f} s; final RMS residual {math.sqrt(2 * loss) * 255:.3g} levels"
        if math.isfinite(loss)
        else f"solver {result.solver}: {result.result} ({result.message})"
    )
    if result.verdict is not None:
        lines += verdict_lines(result)
    return "\n".join(lines)


def verdict_lines(result: FitResult) -> list[str]:
    """A judged fit's per-sphere uncertainty and its verdict (`fitting.verdict`)."""
    v = result.verdict
    lines = [f"sphere {s['index']} ({s['kind']}): moved {s['moved_px']:.2f} px, σ {s['sigma_units']:.3g} units "
             f"= {s['sigma_px']:.3g} px, bias {s['bias_px']:.3g} px" for s in v.spheres]
    return lines + [("verdict: " if v.ok else "verdict: FAILED: ") + v.message]


def report_dict(result: FitResult, deck: str | None = None, target: str | None = None) -> dict:
    """Everything worth keeping about a fit, JSON-ready."""
    return {
        "deck": deck,
        "target": target,
        "solver": result.solver,
        "result": result.result,
        "message": result.message,
        "converged": result.converged,
        "iterations": result.steps,
        "loss": result.loss,
        "rmse_levels": math.sqrt(2 * result.loss) * 255 if math.isfinite(result.loss) else None,
        "times": result.times,
        "free": list(result.selection.families),
        "parameters": [{"name": n, "start": a, "fitted": b} for n, a, b in result.table()],
        "nuisance": result.nuisance,
        "history": result.history,
        "texels": result.texels.summary() if result.texels is not None else None,
        **({"photo": result.photo} if result.photo else {}),
        **({"verdict": result.verdict.as_dict()} if result.verdict is not None else {}),
    }


def write_json(path: str, data: dict) -> None:
    rtjax.atomic_write(path, (json.dumps(data, indent=2, allow_nan=True) + "\n").encode())


def plot_convergence(result: FitResult, path: str) -> None:
    """Loss per iteration (log scale), the pyramid levels shaded, written atomically as PNG.
    Drawn on a `matplotlib.figure.Figure` of its own (not pyplot): the caller's backend, a
    notebook's say, is left as it is."""
    from matplotlib.figure import Figure

    h = result.history
    fig = Figure(figsize=(6.4, 3.6), dpi=100)
    ax = fig.subplots()
    if h:
        steps = [r["step"] for r in h]
        ax.semilogy(steps, [max(r["loss"], 1e-300) for r in h], "o-", ms=3, label="loss")
        ax.semilogy(steps, [max(r["best_loss"], 1e-300) for r in h], "-", lw=1, alpha=0.6, label="best so far")
        widths = [r["width"] for r in h]
        start = 0
        for i in range(1, len(h) + 1):
            if i == len(h) or widths[i] != widths[start]:
                ax.axvspan(steps[start] - 0.5, steps[i - 1] + 0.5, alpha=0.08 * (1 + (start > 0)), color="C2")
                ax.text((steps[start] + steps[i - 1]) / 2, 1.0, f"{widths[start]} px", transform=ax.get_xaxis_transform(),
                        ha="center", va="bottom", fontsize=8)
                start = i
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (½·mean residual², level/255 units)")
    ax.set_title(f"{result.solver}: {result.result}", fontsize=10, pad=14)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with rtjax.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def save_outputs(result: FitResult, outdir: str, stem: str, deck_path: str | None = None, target_path: str | None = None,
                 image_name: str | None = None, frames=None) -> dict[str, str]:
    """Fitted deck, fitted image (Sun raster), JSON report and convergence plot in outdir.
    `frames`: a multi-frame fit's fitted scenes (`frames.fitted_scenes`), the deck's
    frames in order (`rend` {stem}_frameK.sunimg after the first); the image is the first's."""
    os.makedirs(outdir, exist_ok=True)
    image_name = image_name or f"{stem}.sunimg"
    paths = {
        "deck": os.path.join(outdir, f"{stem}.dat"),
        "image": os.path.join(outdir, image_name),
        "report": os.path.join(outdir, f"{stem}.json"),
        "plot": os.path.join(outdir, f"{stem}_convergence.png"),
    }
    header = f"fitted by rtjax fit ({result.solver}, {result.result}, {result.steps} iterations)"
    if deck_path:
        header += f"\nfrom {os.path.basename(deck_path)}" + (f" to {os.path.basename(target_path)}" if target_path else "")
    scenes = list(frames) if frames else [result.scene]
    if "textures" in result.selection.families:
        # fitted texels are new images: write them beside the deck and point `tmap` at them
        names = []
        for k, texels in enumerate(result.scene.params.textures):
            names.append(f"{stem}_texture{k}.sunimg")
            rtjax.save_image(os.path.join(outdir, names[-1]), np.asarray(texels))
            paths[f"texture{k}"] = os.path.join(outdir, names[-1])
        scenes = [rtjax.Scene(s.structure.replace(texture_files=tuple(names)), s.params) for s in scenes]
    if frames:
        outputs = [image_name] + [f"{stem}_frame{k}.sunimg" for k in range(1, len(scenes))]
        rtjax.save_deck(paths["deck"], [rtjax.Frame(s, o, 0) for s, o in zip(scenes, outputs)], header=header)
    else:
        rtjax.save_deck(paths["deck"], scenes[0], image_name, header=header)
    image = rtjax.render(result.scene)
    rtjax.save_image(paths["image"], np.asarray(image))
    write_json(paths["report"], report_dict(result, deck_path, target_path))
    plot_convergence(result, paths["plot"])
    return paths


def summary_line(result: MultiStartResult) -> str:
    """One line: starts, devices, how many converged, which was kept."""
    devices = f"{result.devices} device{'s' if result.devices != 1 else ''}"
    return (f"multi-start: {result.starts} starts on {devices}, {result.converged} of {result.starts} converged; "
            f"kept start {result.index} (loss {result.losses[result.index]:.4e}, {result.results[result.index]})")


def report_entry(result: MultiStartResult) -> dict:
    """The multi-start part of the JSON report."""
    return {
        "starts": result.starts,
        "devices": result.devices,
        "converged": result.converged,
        "kept": result.index,
        "losses": result.losses,
        "results": result.results,
        "start_values": [result.best.selection.values(s.params) for s in result.start_scenes],
        "seconds": result.times["total"],
    }


def add_to_report(path: str, result: MultiStartResult) -> None:
    """Add `report_entry` to a fit's JSON report (written by `save_outputs`)."""
    with open(path) as f:
        data = json.load(f)
    entry = report_entry(result)
    entry["start_values"] = [{k: np.asarray(v).tolist() if not isinstance(v, tuple) else "texels"
                              for k, v in values.items()} for values in entry["start_values"]]
    data["multistart"] = entry
    write_json(path, data)
