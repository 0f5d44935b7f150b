"""What the notebooks share: the quick-mode switch, the repository's folders, and
images shown side by side. Their first cell imports it (they run from this folder).

Quick mode (RTJAX_NOTEBOOK_QUICK=1) is the reduced mode the test suite runs: small
images, few iterations; every cell still runs.
"""

from __future__ import annotations

import os
import pathlib
import tempfile

import matplotlib.pyplot as plt
import numpy as np

import rtjax

QUICK = os.environ.get("RTJAX_NOTEBOOK_QUICK") == "1"


def repository_root(start: pathlib.Path | None = None) -> pathlib.Path:
    """The first folder up from `start` (default: the working directory) that holds
    scenes/ex2s3.dat."""
    root = (start or pathlib.Path.cwd()).resolve()
    while not (root / "scenes" / "ex2s3.dat").exists():
        if root == root.parent:
            raise FileNotFoundError("run this notebook from inside the rtjax repository")
        root = root.parent
    return root


ROOT = repository_root()
SCENES = ROOT / "scenes"


def show(images, titles=None, height=2.8, max_width=15.0, cmap=None):
    """Images side by side; (H, W, 3) arrays in 0..255 are shown as 8-bit files hold
    them, (H, W) ones as grey levels 0..255 (difference images: white = none)."""
    images = [np.asarray(im) for im in images]
    widths = [height * im.shape[1] / im.shape[0] for im in images]
    k = min(1.0, max_width / (sum(widths) + 0.3 * len(images)))
    fig, axes = plt.subplots(1, len(images), figsize=(k * (sum(widths) + 0.3 * len(images)), k * height + 0.45),
                             squeeze=False, gridspec_kw={"width_ratios": widths})
    for ax, im, title in zip(axes[0], images, titles or [""] * len(images)):
        if im.ndim == 3:
            ax.imshow(rtjax.to_uint8(im), interpolation="nearest")
        else:
            ax.imshow(im, cmap=cmap or "gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout(pad=0.3)
    plt.show()


def show_png(draw, *args):
    """Run a plotting function that writes a PNG (rtjax.bench's plots do) and show the
    PNG; the plots select matplotlib's Agg backend, so inline figures are restored."""
    from IPython import get_ipython
    from IPython.display import Image, display

    with tempfile.TemporaryDirectory(prefix="rtjax_nb_") as folder:
        path = os.path.join(folder, "plot.png")
        draw(*args, path)
        image = Image(filename=path)  # reads the file's bytes now
    get_ipython().run_line_magic("matplotlib", "inline")
    display(image)
