"""Timings of batched and sharded rendering and of multi-start fitting (README "Several
devices and hosts"). Set the device count before JAX starts, e.g. on a CPU:

  XLA_FLAGS=--xla_force_host_platform_device_count=4 python scripts/devices.py [--fit] [-o devices.json]

Each figure is the median of `--repeat` warm runs (compiled beforehand; compile times
are reported separately). Every sharded or batched image is also compared with
`rtjax.render` (bit for bit in plain mode; the silhouette-aware mode is counted in
differing pixels, see the README).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import jax
import numpy as np

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)
from rtjax import batch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def warm(fn, repeat: int) -> tuple[float, float, object]:
    """(compile + first run, median warm run, result)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return first, statistics.median(times), out


def orbit(scene: rtjax.Scene, n: int) -> list[rtjax.Scene]:
    """n cameras round the vertical axis through the reference point."""
    refp = np.asarray(scene.params.refp, np.float64)
    eye = np.asarray(scene.params.eye, np.float64) - refp
    r, z = np.hypot(eye[0], eye[1]), eye[2]
    return [scene.replace(eye=refp + [r * np.cos(a), r * np.sin(a), z]) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--frames", type=int, default=16, help="frames of the camera path")
    ap.add_argument("--fit", action="store_true", help="also time multi-start fitting steps")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args()
    n = len(jax.devices())
    rows: list[dict] = []

    def row(what, first, median, same, **extra):
        rows.append({"what": what, "compile_and_first_s": round(first, 3), "warm_s": round(median, 4), "equal": same, **extra})
        print(f"{what:58s} first {first:6.2f} s   warm {median:7.4f} s   equal {same}", flush=True)

    sample = rtjax.load_deck(os.path.join(ROOT, "scenes", "ex2s3.dat")).frames[0].scene
    f, m, ref = warm(lambda: rtjax.render(sample), args.repeat)
    row("ex2s3 400x294, rtjax.render (one device)", f, m, True)
    for k in sorted({2, n} - {1}):
        if k <= n:
            f, m, out = warm(lambda k=k: batch.render_sharded(sample, devices=k), args.repeat)
            row(f"ex2s3 400x294, render_sharded, {k} devices", f, m, bool(np.array_equal(ref, out)))
    small = sample.resized(100)
    f, m, ref_e = warm(lambda: rtjax.render(small, edges=1), args.repeat)
    row("ex2s3 100x74 --edges 1, rtjax.render", f, m, True)
    if n > 1:
        f, m, out = warm(lambda: batch.render_sharded(small, devices=n, edges=1), args.repeat)
        differ = int(np.any(np.asarray(out) != np.asarray(ref_e), axis=-1).sum())
        row(f"ex2s3 100x74 --edges 1, render_sharded, {n} devices", f, m, differ == 0, differing_pixels=differ,
            max_difference=float(np.abs(np.asarray(out) - np.asarray(ref_e)).max()))

    deck = rtjax.load_deck(os.path.join(ROOT, "scenes", "multi_frame.dat"))
    for label, scenes in (("multi_frame.dat, 3 frames 200x147", [fr.scene for fr in deck.frames]),
                          (f"orbit, {args.frames} frames 200x147", orbit(deck.frames[0].scene, args.frames))):
        refs = [np.asarray(rtjax.render(s)) for s in scenes]
        f, m, _ = warm(lambda scenes=scenes: [rtjax.render(s) for s in scenes], args.repeat)
        row(f"{label}: frame by frame", f, m, True)
        params = rtjax.stack_params([s.params for s in scenes])
        for mode in ("vmap", "map"):
            f, m, out = warm(lambda params=params, scenes=scenes, mode=mode: rtjax.render_batch(
                scenes[0].structure, params, mode=mode), args.repeat)
            row(f"{label}: one call, {mode}", f, m, all(np.array_equal(a, b) for a, b in zip(refs, out)))
        if n > 1:
            for split in ("frames", "pixels"):
                for mode in ("vmap", "map"):
                    f, m, out = warm(lambda params=params, scenes=scenes, split=split, mode=mode: rtjax.render_batch(
                        scenes[0].structure, params, devices=n, split=split, mode=mode), args.repeat)
                    row(f"{label}: {split} over {n} devices, {mode}", f, m, all(np.array_equal(a, b) for a, b in zip(refs, out)))

    if args.fit:
        import fitting

        truth = rtjax.load_deck(os.path.join(ROOT, "scenes", "ex2s3.dat")).frames[0].scene
        target = np.floor(np.asarray(rtjax.render(truth)) + 0.5)
        start = rtjax.load_deck(os.path.join(ROOT, "scenes", "fit", "ex2s3_start.dat")).frames[0].scene
        for label, kw in (("fit, 1 start", None), ("fit_multistart, 4 starts, 1 device", {"starts": 4}),
                          (f"fit_multistart, 4 starts, {n} devices", {"starts": 4, "devices": n})):
            if kw is not None and kw.get("devices", 1) > n:
                continue
            t = time.perf_counter()
            if kw is None:
                res = fitting.fit(start, target, "centers", max_steps=8)
                hist, extra = res.history, {}
            else:
                multi = fitting.fit_multistart(start, target, "centers", max_steps=8, **kw)
                res, hist = multi.best, multi.best.history
                extra = {"converged": multi.converged, "losses": multi.losses}
            total = time.perf_counter() - t
            steps = [h["seconds"] for h in hist[1:]]
            rows.append({"what": label, "total_s": round(total, 2), "first_step_s": round(hist[0]["seconds"], 2),
                         "median_step_s": round(statistics.median(steps), 3) if steps else None, **extra})
            print(f"{label:58s} total {total:6.1f} s   first step {hist[0]['seconds']:6.2f} s   "
                  f"median step {rows[-1]['median_step_s']} s {extra.get('converged', '')}", flush=True)

    info = {"devices": n, "platform": jax.devices()[0].platform, "cpu_count": os.cpu_count(), "jax": jax.__version__, "rows": rows}
    if args.output:
        with open(args.output, "w") as fh:
            json.dump(info, fh, indent=2)


if __name__ == "__main__":
    main()
