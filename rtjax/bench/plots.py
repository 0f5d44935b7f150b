"""The bench's plots: error against render time with the Pareto front, and the `--scale`
panels. Each draws on a `matplotlib.figure.Figure` of its own (not pyplot), so the
caller's backend, a notebook's say, is left as it is.
"""

from __future__ import annotations

import math
import os

from ..spheres import CULL_ABOVE


def pareto_plot(result: dict, path: str) -> None:
    """Plot a bench result's error against render time and save it as a PNG.

    **Arguments:**

    - `result`: what `rtjax.bench.run` returns.
    - `path`: the PNG written.

    Error is the RMS level difference (log), time the median render (ms, log); one
    labelled point per distinct setting, coloured by knob, and the Pareto front (nothing
    both faster and more accurate) joined by a line.
    """
    from matplotlib.figure import Figure

    seen, pts = set(), []
    for r in result["settings"]:
        key = (r["dtype"], r["depth"], r["spp"], r["edges"], r["subdivide"], r["scale"])
        if r["knob"] == "reference" or key in seen:
            continue
        seen.add(key)
        pts.append((1e3 * r["median_s"], max(r["rms_levels"], 1e-3), r["label"], r["knob"]))
    colours = {"default": "black", "dtype": "tab:purple", "depth": "tab:blue", "spp": "tab:green", "edges": "tab:orange",
               "subdivide": "tab:brown", "scale": "tab:red"}
    fig = Figure(figsize=(9, 6), dpi=110)
    ax = fig.subplots()
    for knob, colour in colours.items():
        sel = [p for p in pts if p[3] == knob]
        if sel:
            ax.scatter([p[0] for p in sel], [p[1] for p in sel], color=colour, label=knob, zorder=3, s=28)
    for x, y, label, _ in pts:
        ax.annotate(label, (x, y), textcoords="offset points", xytext=(5, 4), fontsize=7.5)
    front, best = [], math.inf
    for x, y, _, _ in sorted(pts):
        if y < best:
            front.append((x, y))
            best = y
    ax.plot([p[0] for p in front], [p[1] for p in front], color="grey", lw=1, ls="--", zorder=2, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("render time after compile, median (ms)")
    ax.set_ylabel("RMS error against the reference (8-bit levels)")
    ref = next(r for r in result["settings"] if r["knob"] == "reference")
    ax.set_title(f"{os.path.basename(result['deck'])} {result['width']}×{result['height']}: each knob alone from the default\n"
                 f"reference: float64, depth {ref['depth']}, {ref['spp']}×{ref['spp']} samples per pixel", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path)


def scale_plot(result: dict, path: str) -> None:
    """Plot a `--scale` bench result as three panels and save them as a PNG.

    **Arguments:**

    - `result`: what `rtjax.bench.run(..., scale=True)` returns.
    - `path`: the PNG written.

    The panels: render time against spheres (culled and brute force, log-log), render
    time against pixels (log-log), gradient and forward memory against depth (log).
    """
    from matplotlib.figure import Figure

    s = result["scale"]
    fig = Figure(figsize=(14, 4.3), dpi=110)
    axes = fig.subplots(1, 3)
    ax = axes[0]
    ax.plot([r["n"] for r in s["spheres"]], [1e3 * r["median_s"] for r in s["spheres"]], "o-", label=f"rtjax (culled beyond {CULL_ABOVE})")
    brute = [r for r in s["spheres"] if "brute" in r]
    if brute:
        ax.plot([r["n"] for r in brute], [1e3 * r["brute"]["median_s"] for r in brute], "s--", label="brute force")
    ax.axhline(2000, color="grey", lw=0.8, ls=":", label="2 s")
    ax.set(xscale="log", yscale="log", xlabel="spheres (random scene)", ylabel="render ms (median)",
           title=f"time against spheres ({s['spheres'][0]['width']}×{s['spheres'][0]['height']})")
    ax.legend(fontsize=8)
    ax = axes[1]
    ax.plot([r["pixels"] for r in s["pixels"]], [1e3 * r["median_s"] for r in s["pixels"]], "o-")
    for r in s["pixels"]:
        ax.annotate(f"{r['width']}×{r['height']}", (r["pixels"], 1e3 * r["median_s"]), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set(xscale="log", yscale="log", xlabel="pixels", ylabel="render ms (median)", title=f"time against pixels ({os.path.basename(result['deck'])})")
    ax = axes[2]
    mem = s["memory"]
    ax.plot([r["depth"] for r in mem], [r["grad_peak_bytes"] / 2**20 for r in mem], "o-", label="reverse gradient")
    ax.plot([r["depth"] for r in mem], [r["forward_peak_bytes"] / 2**20 for r in mem], "s--", label="forward")
    ax.set(xlabel="depth", ylabel="peak MiB (XLA memory analysis)", title="memory against depth")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    for a in axes:
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
