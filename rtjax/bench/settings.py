"""The bench's knob table: every knob varied alone from the default render, each setting
timed and compared with a float64 reference render; and the independent NumPy renderer
(`rtjax.reference`) timed at the default settings, so that its ratio is measured on the
machine at hand.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable

import numpy as np

from .config import Config
from .measure import image_errors, timed

#: Knob order in the table and the plot.
KNOBS = ("reference", "default", "dtype", "depth", "spp", "edges", "subdivide", "scale")


@dataclasses.dataclass(frozen=True)
class Setting:
    """One render's knobs (a dict key: equal settings are measured once)."""

    dtype: str = "float32"
    depth: int = 10
    spp: int = 1
    edges: float = 0.0
    subdivide: int = 0
    scale: float = 1.0


def label(knob: str, s: Setting) -> str:
    """The table's and the plot's name of setting `s` in row `knob`."""
    if knob == "reference":
        return f"reference (f64, depth {s.depth}, {s.spp}×{s.spp})"
    if knob == "default":
        return f"default (f32, depth {s.depth}, 1×1)"
    if knob == "dtype":
        return s.dtype
    if knob == "depth":
        return f"depth {s.depth}"
    if knob == "spp":
        return f"{s.spp}×{s.spp} spp"
    if knob == "edges":
        return f"edges {s.edges:g} px"
    if knob == "subdivide":
        return f"edges {s.edges:g} px, {2**s.subdivide}×{2**s.subdivide} sub"
    fractions = {0.25: "¼", 0.5: "½", 1.0: "1"}
    return f"scale {fractions.get(s.scale, f'{s.scale:g}')}"


def plan(default: Setting, reference: Setting, cfg: Config, secondary: bool) -> list[tuple[str, Setting]]:
    """The table's (knob, setting) rows: the reference, the default, then each knob alone
    (depths only when `secondary`: without mirrors or glass every depth renders the
    same image)."""
    rows = [("reference", reference), ("default", default)]
    rows += [("dtype", dataclasses.replace(default, dtype=d)) for d in cfg.dtypes]
    if secondary:
        rows += [("depth", dataclasses.replace(default, depth=d)) for d in cfg.depths]
    rows += [("spp", dataclasses.replace(default, spp=k)) for k in cfg.spps]
    rows += [("edges", dataclasses.replace(default, edges=w)) for w in cfg.edges]
    rows += [("subdivide", dataclasses.replace(default, edges=1.0, subdivide=n)) for n in cfg.subdivides]
    rows += [("scale", dataclasses.replace(default, scale=f)) for f in cfg.scales]
    return rows


def scaled(scene, factor: float):
    """`scene` with its width times `factor` (rounded, at least 1); the scene itself at 1."""
    if factor == 1.0:
        return scene
    return scene.resized(max(1, int(round(scene.structure.width * factor))))


def render_setting(scene, s: Setting) -> Callable[[], object]:
    """A zero-argument render of `scene` at setting `s` (for `timed`)."""
    import rtjax

    sc = scaled(scene, s.scale)
    return lambda: rtjax.render(sc, depth=s.depth, spp=s.spp, dtype=s.dtype, edges=s.edges, subdivide=s.subdivide)


def format_psnr(p: float | None) -> str:
    """A PSNR for the log, ∞ for None (identical images)."""
    return "   ∞ dB" if p is None else f"{p:5.1f} dB"


def measure_settings(scene, cfg: Config, log: Callable[[str], None]) -> tuple[list[dict], dict]:
    """Time and compare every row of `plan`.

    **Arguments:**

    - `scene`: the scene measured; its own depth is the default's.
    - `cfg`: the knob values, the reference's depth and samples, the repeats.
    - `log`: called with each progress line.

    **Returns:** (rows, reference): one dict per row (knob, label, the setting's fields,
    width, height, `timed`'s figures and `image_errors` against the reference), and the
    reference's own measurement with its float64 image under `image`.
    """
    st = scene.structure
    default = Setting(depth=st.default_depth)
    reference = Setting(dtype="float64", depth=cfg.ref_depth if st.needs_secondary_rays else 0, spp=cfg.ref_spp)
    rows = plan(default, reference, cfg, st.needs_secondary_rays)
    measured: dict[Setting, dict] = {}
    log(f"reference: float64, depth {reference.depth}, {reference.spp}×{reference.spp} samples per pixel, {st.width}×{st.height} …")
    ref_m = timed(render_setting(scene, reference), 1)
    ref_img = np.asarray(ref_m.pop("out"), np.float64)
    measured[reference] = ref_m | image_errors(ref_img, ref_img)
    out = []
    for knob, s in rows:
        if s not in measured:
            m = timed(render_setting(scene, s), cfg.repeats)
            img = m.pop("out")
            measured[s] = m | image_errors(img, ref_img)
            log(f"  {knob:9s} {label(knob, s):28s} {1e3 * m['median_s']:9.1f} ms  "
                f"compile {m['compile_s']:5.1f} s  {format_psnr(measured[s]['psnr_db'])}")
        sc = scaled(scene, s.scale).structure
        name = label(knob, s) + (" (default)" if knob not in ("default", "reference") and s == default else "")
        out.append({"knob": knob, "label": name, **dataclasses.asdict(s),
                    "width": sc.width, "height": sc.height, **measured[s]})
    return out, {"image": ref_img, **measured[reference]}


def measure_numpy(deck_path: str, width: int, depth: int, cfg: Config, default_image,
                  log: Callable[[str], None]) -> dict:
    """Time the NumPy renderer (`rtjax.reference`) on the deck's first frame.

    **Arguments:**

    - `deck_path`: the deck, read with the reference's own reader.
    - `width`, `depth`: the frame's width and the depth rendered (one sample per pixel).
    - `cfg`: its `numpy_repeats`.
    - `default_image`: rtjax's default render of the same frame, compared with the NumPy one.
    - `log`: called with the progress line.

    **Returns:** a dict with `median_s`, `runs_s`, `depth`, `spp` and
    `rtjax_default_vs_numpy` (`image_errors` of rtjax's image against NumPy's).
    """
    from .. import reference

    with open(deck_path, encoding="utf-8") as f:
        frame = reference.parse_deck_text(f.read(), os.path.dirname(os.path.abspath(deck_path)))[0]
    frame.size = width
    log(f"NumPy reference renderer (rtjax.reference), depth {depth}, 1×1 …")
    runs = []
    for _ in range(max(1, cfg.numpy_repeats)):
        t0 = time.perf_counter()
        img = reference.render_reference(frame, depth=depth, spp=1)
        runs.append(time.perf_counter() - t0)
    agree = image_errors(default_image, img)
    return {"median_s": float(np.median(runs)), "runs_s": runs, "depth": depth, "spp": 1,
            "rtjax_default_vs_numpy": agree}
