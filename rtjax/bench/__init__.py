"""`rtjax bench`: the speed/accuracy trade of each knob and the cost of scale, measured.

On a deck's first frame, every knob is varied alone from the default render (float32,
the deck's default depth, one sample per pixel, pixel centres, full size) and compared
with a reference render (float64, a generous depth, K×K samples per pixel, full size).
Per setting: compile time (first call minus the median of the later calls), the median
of several timed renders after compile, and the error of the image as written to a file
(8-bit levels): PSNR, RMS and max level difference, and the fraction of pixels off by
≥ 1 level in some channel (`rtjax.bench.settings`). Derivatives (reverse gradient of the
mean image, forward Jacobian in the centres, one Levenberg–Marquardt step of optimistix
on the image residual) are timed as ratios to the plain forward render timed in the
same run, at the same size (`rtjax.bench.derivatives`). The independent NumPy float64
renderer `rtjax.reference` renders the default settings in the same run, so its
speed-up is a ratio measured on this machine, not a claim.

`--scale` adds render time against the number of spheres and the pixel count, and the
peak memory of the reverse gradient against depth (`rtjax.bench.scale`).

Timings are wall-clock medians on whatever else the machine is running; ratios within
one run are steadier than times across runs. float64 needs
`jax.config.update("jax_enable_x64", True)` before any JAX computation (`rtjax bench`
does it; float32 renders of a deck stay float32).

This module runs the measurements and writes their outputs; it also gathers the
bench's public names: `Config`, `run`, `main_bench`, `table_text`, `write_outputs`,
`pareto_plot`, `scale_plot`, `quantize`, `image_errors`, `random_deck_text`, `random_scene`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence

import numpy as np

from .config import Config as Config
from .derivatives import measure_derivatives
from .measure import image_errors as image_errors, machine, quantize as quantize
from .plots import pareto_plot as pareto_plot, scale_plot as scale_plot
from .scale import measure_scale
from .settings import KNOBS as KNOBS, Setting as Setting, measure_numpy, measure_settings
from ..random_scenes import random_deck_text as random_deck_text, random_scene as random_scene


def run(deck_path: str, cfg: Config | None = None, *, scale: bool = False, log: Callable[[str], None] = print) -> dict:
    """Measure a deck's first frame.

    **Arguments:**

    - `deck_path`: the deck; its first frame is measured.
    - `cfg`: what to measure (`Config.full()` when None).
    - `scale`: also measure against spheres, pixels and depth (`rtjax.bench.scale`).
    - `log`: called with each progress line.

    **Returns:** the JSON-ready result (NaN and infinities as None): the deck, its size,
    the config and the machine; `settings` (one row per knob setting), `reference`,
    `derivatives`, `numpy` (or `numpy_note`), `scale` (with `scale=True`) and `total_s`.

    **Raises:** `RtjaxError` when float64 is off (`jax_enable_x64`), `DeckError` for a
    bad deck or one with no `rend` line.
    """
    import jax

    import rtjax

    if not jax.config.jax_enable_x64:
        raise rtjax.RtjaxError("rtjax bench compares with float64 renders: call jax.config.update('jax_enable_x64', True) "
                               "before any JAX computation")
    cfg = cfg or Config.full()
    deck = rtjax.load_deck(deck_path)
    if not deck.frames:
        raise rtjax.DeckError(deck.path, None, "the deck has no rend line: nothing to measure")
    scene = deck.frames[0].scene
    if cfg.width is not None:
        scene = scene.resized(cfg.width)
    st = scene.structure
    started = time.perf_counter()
    result: dict = {"deck": deck_path, "frame": 0, "width": st.width, "height": st.height, "n_spheres": st.n_spheres,
                    "default_depth": st.default_depth, "config": dataclasses.asdict(cfg), "machine": machine()}
    log(f"{deck_path}: {st.n_spheres} spheres, {st.width}×{st.height}, "
        f"{jax.default_backend()} with {os.cpu_count()} cores (timings: medians of {cfg.repeats} runs after compile)")
    rows, ref = measure_settings(scene, cfg, log)
    result["settings"] = rows
    result["reference"] = {k: v for k, v in ref.items() if k != "image"}
    default = next(r for r in rows if r["knob"] == "default")
    if cfg.derivatives:
        result["derivatives"] = measure_derivatives(scene, cfg, log)
    if cfg.numpy:
        default_img = np.asarray(rtjax.render(scene))
        np_result = measure_numpy(deck_path, st.width, st.default_depth, cfg, default_img, log)
        np_result["speedup"] = np_result["median_s"] / default["median_s"]
        result["numpy"] = np_result
    else:
        result["numpy_note"] = "NumPy timing not asked for"
    if scale:
        result["scale"] = measure_scale(scene, cfg, log)
    result["total_s"] = time.perf_counter() - started
    return _jsonable(result)


def _jsonable(x):
    """`x` with NumPy scalars as Python ones, tuples as lists, non-finite floats as None."""
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def table_text(result: dict) -> str:
    """The knob table, the derivative costs, the NumPy ratio and (with `--scale`) the
    scale figures of a `run` result, as plain text."""
    lines = [f"{result['deck']}: {result['n_spheres']} spheres, {result['width']}×{result['height']}; "
             f"error against the reference, as 8-bit files"]
    head = f"{'knob':9s} {'setting':30s} {'size':>9s} {'render ms':>10s} {'compile s':>9s} {'PSNR dB':>8s} {'rms lv':>7s} {'max lv':>6s} {'off ≥1':>7s}"
    lines += [head, "-" * len(head)]
    for r in result["settings"]:
        psnr = "∞" if r["psnr_db"] is None else f"{r['psnr_db']:.1f}"
        lines.append(f"{r['knob']:9s} {r['label']:30s} {str(r['width']) + '×' + str(r['height']):>9s} {1e3 * r['median_s']:10.1f} "
                     f"{r['compile_s']:9.1f} {psnr:>8s} {r['rms_levels']:7.2f} {r['max_levels']:6d} {100 * r['frac_off']:6.2f}%")
    d = result.get("derivatives")
    if d:
        lines.append("")
        lines.append(f"derivatives at {d['width']}×{d['height']} (ratios to the forward render of the same size, same run):")
        lines.append(f"  forward render            {1e3 * d['forward']['median_s']:9.1f} ms   compile {d['forward']['compile_s']:5.1f} s")
        names = {"grad": "reverse gradient (mean)", "jacfwd_centers": f"jacfwd, {d['n_params_centers']} centre coords",
                 "lm_step": "one LM step (centres)"}
        for k, name in names.items():
            if k in d:
                lines.append(f"  {name:25s} {1e3 * d[k]['median_s']:9.1f} ms   compile {d[k]['compile_s']:5.1f} s   ×{d[k]['ratio']:.1f}")
    n = result.get("numpy")
    if n:
        agree = n["rtjax_default_vs_numpy"]
        lines.append("")
        lines.append(f"NumPy float64 reference renderer (rtjax.reference), depth {n['depth']}, 1×1: {1e3 * n['median_s']:.0f} ms; "
                     f"rtjax default {1e3 * _default(result)['median_s']:.1f} ms: {n['speedup']:.1f}× faster "
                     f"(images differ by ≤ {agree['max_levels']} levels, {100 * agree['frac_off']:.2f}% of pixels)")
    elif result.get("numpy_note"):
        lines.append("")
        lines.append(result["numpy_note"])
    s = result.get("scale")
    if s:
        lines.append("")
        lines.append("render time against spheres (random scenes, default settings):")
        for r in s["spheres"]:
            extra = ""
            if "brute" in r:
                extra = f"   brute force {1e3 * r['brute']['median_s']:.0f} ms, identical: {r['identical_to_brute']}"
            lines.append(f"  {r['n']:5d} spheres {r['width']}×{r['height']}  {1e3 * r['median_s']:9.1f} ms  compile {r['compile_s']:5.1f} s{extra}")
        lines.append("render time against pixels (the deck at several widths):")
        for r in s["pixels"]:
            lines.append(f"  {r['width']:5d}×{r['height']:<5d} {r['pixels']:8d} px  {1e3 * r['median_s']:9.1f} ms")
        lines.append("peak memory of the reverse gradient (XLA compiled memory analysis: temporaries + arguments + outputs):")
        for r in s["memory"]:
            lines.append(f"  depth {r['depth']:2d}  {r['grad_peak_bytes'] / 2**20:8.1f} MiB   (forward {r['forward_peak_bytes'] / 2**20:.1f} MiB)")
    return "\n".join(lines)


def _default(result: dict) -> dict:
    """The default setting's row of a `run` result."""
    return next(r for r in result["settings"] if r["knob"] == "default")


def write_outputs(result: dict, outdir: str, stem: str) -> dict[str, str]:
    """Write a `run` result to `outdir` (created if need be).

    **Returns:** the paths written: `json` (bench_<stem>.json), `plot` (bench_<stem>.png,
    `pareto_plot`) and, for a `--scale` result, `scale_plot` (bench_<stem>_scale.png).
    """
    from ..atomic import atomic_write

    os.makedirs(outdir, exist_ok=True)
    paths = {"json": os.path.join(outdir, f"bench_{stem}.json"), "plot": os.path.join(outdir, f"bench_{stem}.png")}
    atomic_write(paths["json"], (json.dumps(result, indent=1, allow_nan=False) + "\n").encode("utf-8"))
    pareto_plot(result, paths["plot"])
    if "scale" in result:
        paths["scale_plot"] = os.path.join(outdir, f"bench_{stem}_scale.png")
        scale_plot(result, paths["scale_plot"])
    return paths


def main_bench(deck: str, *, quick: bool, scale: bool, outdir: str, log: Callable[[str], None] = print,
               cfg: Config | None = None) -> dict[str, str]:
    """What `rtjax bench` runs: measure, log the table, write the JSON and the plots.

    **Arguments:**

    - `deck`: the deck's path; its file name (without extension) names the outputs.
    - `quick`, `scale`: the command's `--quick` and `--scale`.
    - `outdir`: the command's `-o`.
    - `log`: called with each line.
    - `cfg`: replaces the config `quick` chooses.

    **Returns:** the paths written (`write_outputs`).
    """
    cfg = cfg or (Config.quick() if quick else Config.full())
    result = run(deck, cfg, scale=scale, log=log)
    stem = os.path.splitext(os.path.basename(deck))[0]
    log("")
    log(table_text(result))  # before writing: should that fail, the figures are on screen
    paths = write_outputs(result, outdir, stem)
    log("wrote " + ", ".join(paths.values()) + f"  ({result['total_s']:.0f} s in all)")
    return paths


__all__: Sequence[str] = ["Config", "Setting", "run", "table_text", "pareto_plot", "scale_plot", "write_outputs",
                          "random_deck_text", "random_scene", "image_errors", "quantize", "main_bench"]
