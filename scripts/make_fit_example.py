"""Make the ready-made fitting example in scenes/fit/ (deterministic):

* ex2s3_target.sunimg: the sample deck rendered at pixel centres (the known truth),
* ex2s3_start.dat: the same deck with all 8 centres moved by up to ±3 units, the
  starting point `rtjax fit` recovers the truth from.

Run: python scripts/make_fit_example.py
"""

from __future__ import annotations

import os

import numpy as np

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "scenes", "fit")


def main() -> None:
    os.makedirs(OUT, exist_ok=True)
    truth = rtjax.load_deck(os.path.join(ROOT, "scenes", "ex2s3.dat")).frames[0].scene
    rtjax.save_image(os.path.join(OUT, "ex2s3_target.sunimg"), rtjax.render(truth))
    rng = np.random.default_rng(2010)
    moved = np.round(np.asarray(truth.params.centers) + rng.uniform(-3, 3, (8, 3)), 2)
    rtjax.save_deck(
        os.path.join(OUT, "ex2s3_start.dat"),
        truth.replace(centers=moved),
        "ex2s3_start.sunimg",
        header="The sample deck with every sphere centre moved by up to ±3 units (scripts/make_fit_example.py).\n"
        "rtjax fit scenes/fit/ex2s3_start.dat scenes/fit/ex2s3_target.sunimg --free centers -o out/fitted.dat",
    )


if __name__ == "__main__":
    main()
