"""Basin of convergence of `fitting.fit` on the sample deck: success rate (every centre
within `--tol` units of the truth) against the size of the perturbation, and the same
with the coarse-to-fine schedule against a single full-size level.

  python scripts/basin.py --amplitudes 1,3,5,8 --seeds 3 [--width 400] [-o docs/fitting_basin.json]

Every run perturbs all 8 centres by uniform noise in ±amplitude per coordinate (a fixed
seed per run), fits with the defaults (Levenberg–Marquardt, 30 iterations), and records
the maximum centre error, the iterations and the time. Minutes per configuration on a
2-core CPU: this is a study, not a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import fitting
import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)


def run(truth, target, amplitude: float, seed: int, **kw) -> dict:
    rng = np.random.default_rng(1000 + seed)
    start = truth.replace(centers=np.asarray(truth.params.centers) + rng.uniform(-amplitude, amplitude, (8, 3)))
    t = time.perf_counter()
    res = fitting.fit(start, target, "centers", **kw)
    err = np.abs(np.asarray(res.scene.params.centers) - np.asarray(truth.params.centers)).max()
    return {"amplitude": amplitude, "seed": seed, "max_error": float(err), "iterations": res.steps,
            "seconds": time.perf_counter() - t, "result": res.result, **{k: str(v) for k, v in kw.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--amplitudes", default="1,3,5,8")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--tol", type=float, default=0.1)
    ap.add_argument("--compare-levels", action="store_true", help="also run one full-size level at amplitude 3")
    ap.add_argument("-o", "--output", default="docs/fitting_basin.json")
    args = ap.parse_args()
    truth = rtjax.load_deck("scenes/ex2s3.dat").frames[0].scene.resized(args.width)
    target = np.floor(np.asarray(rtjax.render(truth)) + 0.5)
    rows = []
    configs = [({}, float(a)) for a in args.amplitudes.split(",")]
    if args.compare_levels:
        configs.append(({"levels": 1}, 3.0))
    for kw, amp in configs:
        for seed in range(args.seeds):
            row = run(truth, target, amp, seed, **kw)
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = []
    for kw, amp in configs:
        sel = [r for r in rows if r["amplitude"] == amp and all(r.get(k) == str(v) for k, v in kw.items())
               and (kw or "levels" not in r)]
        ok = [r for r in sel if r["max_error"] < args.tol]
        summary.append({"amplitude": amp, "schedule": "single full-size level" if kw else "coarse to fine",
                        "success": f"{len(ok)}/{len(sel)}", "median_error": float(np.median([r["max_error"] for r in sel])),
                        "median_seconds": float(np.median([r["seconds"] for r in sel]))})
    for s in summary:
        print(s)
    rtjax.atomic_write(args.output, (json.dumps({"tol": args.tol, "width": args.width, "runs": rows, "summary": summary}, indent=2) + "\n").encode())


if __name__ == "__main__":
    main()
