"""Fit every photo of the photo set (scenes/photos/) and measure the fitted centres.

For each photo of the chosen split, runs the command a user would:

    rtjax fit START PHOTO --free centers --spheres LIST --photo -o OUT/NAME/fitted.dat

in a fresh process (its time includes start-up and compiling: the XLA cache is off unless
`--cache`), then compares the fitted deck's centres with the truth deck's, in pixel
footprints at each sphere's true distance from the eye (distance × 2·tan(ha/2)/width).
Errors are summarised per material: opaque and mirror spheres, glass spheres. Writes
OUT/eval_SPLIT.json and OUT/eval_SPLIT.md (a markdown table).

    python scripts/eval_photos.py --split tune
    python scripts/eval_photos.py --split holdout
    python scripts/eval_photos.py --only ex2s3-cycles-1 --flags "--nuisance camera"

Run it with `nice`, and not beside other heavy work: the times are part of the result.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shlex
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PHOTOS = os.path.join(ROOT, "scenes", "photos")
#: What each material counts as in the table.
GROUPS = {"opaq": "opaque & mirror", "mirr": "opaque & mirror", "tmap": "opaque & mirror", "trpa": "glass"}
def goals() -> dict[str, float]:
    """The goals, in pixel footprints, per group: the verdict's limits (`fitting.verdict.LIMITS`)."""
    from fitting.verdict import LIMITS

    return {"opaque & mirror": LIMITS["opaq"], "glass": LIMITS["trpa"]}


def footprints(deck_path: str, width: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The deck's centres (N, 3), each centre's pixel footprint (`fitting.verdict.footprints`)
    for an image `width` pixels wide, and each sphere's kind."""
    import rtjax
    from fitting.verdict import footprints as footprints_of

    scene = rtjax.load_deck(deck_path).frames[0].scene
    return np.asarray(scene.params.centers, np.float64), footprints_of(scene.params, width), list(scene.structure.kinds)


def errors(deck_path: str, truth: np.ndarray, foot: np.ndarray, free: list[int]) -> np.ndarray:
    """|centre − true centre| / footprint of the free spheres."""
    import rtjax

    got = np.asarray(rtjax.load_deck(deck_path).frames[0].scene.params.centers, np.float64)
    return np.linalg.norm(got[free] - truth[free], axis=1) / foot[free]


def depth_errors(deck_path: str, truth: np.ndarray, eye: np.ndarray, foot: np.ndarray, free: list[int]) -> np.ndarray:
    """The free spheres' errors along the view (fitted − true centre, on the unit vector
    from the eye to the true centre; negative: nearer the eye), in pixel footprints."""
    import rtjax

    got = np.asarray(rtjax.load_deck(deck_path).frames[0].scene.params.centers, np.float64)
    view = truth[free] - eye
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    return np.sum((got[free] - truth[free]) * view, axis=1) / foot[free]


def by_group(values: np.ndarray, kinds: list[str], free: list[int]) -> dict[str, float | None]:
    """The largest value per group (None where the photo has no sphere of it)."""
    out = {}
    for group in goals():
        v = [float(x) for x, i in zip(values, free) if GROUPS[kinds[i]] == group]
        out[group] = max(v) if v else None
    return out


def run_one(photo: dict, outdir: str, flags: list[str], cache: bool) -> dict:
    """Fit one photo in a fresh process; its errors, time, exit code and verdict."""
    name = photo["name"]
    folder = os.path.join(outdir, name)
    os.makedirs(folder, exist_ok=True)
    fitted = os.path.join(folder, "fitted.dat")
    free = [int(i) for i in photo["free"]]
    command = [sys.executable, "-m", "rtjax", "fit", os.path.join(PHOTOS, photo["start"]), os.path.join(PHOTOS, photo["file"]),
               "--free", "centers", "--spheres", ",".join(map(str, free)), "-o", fitted, *flags]
    env = dict(os.environ)
    if not cache:
        env["RTJAX_CACHE"] = "off"
    started, used = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=ROOT)
    seconds = time.perf_counter() - started
    now = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (now.ru_utime - used.ru_utime) + (now.ru_stime - used.ru_stime)  # the fit's CPU time, whatever the load
    with open(os.path.join(folder, "log.txt"), "w") as f:
        f.write(" ".join(shlex.quote(c) for c in command) + "\n\n" + done.stdout + "\n" + done.stderr)
    truth, foot, kinds = footprints(os.path.join(PHOTOS, photo["truth"]), int(photo["width"]))
    start = errors(os.path.join(PHOTOS, photo["start"]), truth, foot, free)
    row = {"name": name, "renderer": photo["renderer"], "split": photo["split"], "exit": done.returncode,
           "seconds": seconds, "cpu_seconds": cpu, "start": by_group(start, kinds, free), "start_all": start.tolist(),
           "kinds": [kinds[i] for i in free], "free": free}
    report = os.path.join(folder, "fitted.json")
    if os.path.exists(fitted) and done.returncode in (0, 1):
        end = errors(fitted, truth, foot, free)
        eye = np.asarray(rtjax_eye(os.path.join(PHOTOS, photo["truth"])), np.float64)
        row.update(end=by_group(end, kinds, free), end_all=end.tolist(),
                   end_depth=depth_errors(fitted, truth, eye, foot, free).tolist())
        with open(report) as f:
            data = json.load(f)
        row["verdict"] = data.get("verdict", {}).get("message") or f"{data['result']} ({data['message']})"
        row["iterations"] = data["iterations"]
    else:
        row.update(end=None, end_all=None, verdict=(done.stderr.strip().splitlines() or ["no output"])[-1], iterations=None)
    return row


def rtjax_eye(deck_path: str) -> np.ndarray:
    import rtjax

    return np.asarray(rtjax.load_deck(deck_path).frames[0].scene.params.eye, np.float64)


def cell(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def markdown(rows: list[dict]) -> str:
    """The table: per photo, start and end errors per group (largest, in pixel footprints),
    time, exit code and verdict; held-out photos after the others."""
    head = ("| photo | split | start: opaque & mirror | start: glass | end: opaque & mirror | end: glass | goals met | "
            "time | CPU time | exit | verdict |\n|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for split in ("tune", "holdout"):
        for r in (r for r in rows if r["split"] == split):
            end = r["end"] or {}
            met = "yes" if r["end"] and goals_met(r) else "no"
            lines.append(f"| {r['name']} | {split} | {cell(r['start']['opaque & mirror'])} | {cell(r['start']['glass'])} | "
                         f"{cell(end.get('opaque & mirror'))} | {cell(end.get('glass'))} | {met} | {r['seconds']:.0f} s | {r.get('cpu_seconds', math.nan):.0f} s | "
                         f"{r['exit']} | {r['verdict'].replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def goals_met(row: dict) -> bool:
    """Every opaque and mirror centre within 1 footprint, every glass one within 3."""
    return all(v is None or v <= goals()[g] for g, v in row["end"].items())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=("tune", "holdout", "all"), default="tune")
    ap.add_argument("--only", default=None, help="comma-separated photo names (or parts of them) to run")
    ap.add_argument("--out", default=os.path.join(ROOT, "build", "photos", "eval"), help="output folder")
    ap.add_argument("--flags", default="--photo", help="the fit's options after --free/--spheres (default --photo)")
    ap.add_argument("--cache", action="store_true", help="keep XLA's compilation cache on (times then exclude most compiling)")
    ap.add_argument("--tag", default="", help="a suffix for the output files' names")
    args = ap.parse_args(argv)
    with open(os.path.join(PHOTOS, "manifest.json")) as f:
        photos = json.load(f)["photos"]
    chosen = [p for p in photos if args.split == "all" or p["split"] == args.split]
    if args.only:
        parts = [s.strip() for s in args.only.split(",") if s.strip()]
        chosen = [p for p in chosen if any(s in p["name"] for s in parts)]
    os.makedirs(args.out, exist_ok=True)
    rows = []
    stem = f"eval_{args.split}{args.tag}"
    for photo in chosen:
        row = run_one(photo, args.out, shlex.split(args.flags), args.cache)
        rows.append(row)
        end = row["end"] or {}
        print(f"{row['name']:26s} start {cell(row['start']['opaque & mirror']):>6} / {cell(row['start']['glass']):>6}  "
              f"end {cell(end.get('opaque & mirror')):>6} / {cell(end.get('glass')):>6}  {row['seconds']:5.0f} s  "
              f"exit {row['exit']}  {row['verdict']}", flush=True)
        with open(os.path.join(args.out, stem + ".json"), "w") as f:
            json.dump({"flags": args.flags, "rows": rows}, f, indent=2)
        with open(os.path.join(args.out, stem + ".md"), "w") as f:
            f.write(markdown(rows))
    met = sum(bool(r["end"]) and goals_met(r) for r in rows)
    print(f"goals met on {met} of {len(rows)} photos; wrote {os.path.join(args.out, stem)}.json and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
