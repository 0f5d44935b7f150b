"""`rtjax bench`: the speed/accuracy trade of each knob and the cost of scale, measured.

On the user's deck (its first frame), every knob is varied alone from the default
render (float32, the deck's default depth, one sample per pixel, pixel centres, full
size) and compared with a reference render (float64, a generous depth, K×K samples per
pixel, full size). Per setting: compile time (first call minus the median of the later
calls), the median of several timed renders after compile, and the error of the image
as written to a file (8-bit levels): PSNR, RMS and max level difference, and the
fraction of pixels off by ≥ 1 level in some channel. Derivatives (reverse gradient of
the mean image, forward Jacobian in the centres, one Levenberg–Marquardt step of
optimistix on the image residual) are timed as ratios to the plain forward render timed
in the same run, at the same size. The independent NumPy float64 renderer of the tests
(tests/reference.py, when it is there) renders the default settings in the same run, so
the speed-up is a ratio measured on this machine, not a claim.

`--scale` adds render time against the number of spheres (random non-overlapping scenes,
culled as the renderer does, and brute force where affordable, with the two images
compared), against the pixel count (the deck at several widths), and the peak memory of
the reverse gradient against depth (XLA's compiled memory analysis).

Timings are wall-clock medians on whatever else the machine is running: on a shared
machine they move by tens of per cent between runs; ratios within one run are steadier.
float64 needs `jax.config.update("jax_enable_x64", True)` before any JAX computation
(`rtjax bench` does it; float32 renders of a deck stay float32).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

#: Knob order in the table and the plot.
KNOBS = ("reference", "default", "dtype", "depth", "spp", "edges", "scale")


@dataclasses.dataclass(frozen=True)
class Config:
    """What a bench run measures. `Config.full()` and `Config.quick()` are the CLI's."""

    ref_depth: int = 16
    ref_spp: int = 16
    dtypes: tuple[str, ...] = ("float32", "float64")
    depths: tuple[int, ...] = (0, 1, 2, 3, 4, 6, 8, 10, 12)
    spps: tuple[int, ...] = (1, 2, 4, 8)
    edges: tuple[float, ...] = (0.5, 1.0, 2.0)
    scales: tuple[float, ...] = (0.25, 0.5, 1.0)
    repeats: int = 5
    derivatives: bool = True
    derivative_scale: float = 1.0  # image scale at which derivatives are timed
    lm_step: bool = True
    numpy: bool = True
    numpy_repeats: int = 3
    width: int | None = None  # render the deck at this width instead of its own
    # --scale
    sphere_counts: tuple[int, ...] = (8, 16, 32, 64, 128, 256, 512, 1000)
    brute_counts: tuple[int, ...] = (64, 128, 256, 512, 1000)
    scale_width: int = 400
    widths: tuple[int, ...] = (50, 100, 200, 400, 800)
    memory_depths: tuple[int, ...] = (0, 1, 2, 4, 8, 12)
    scale_repeats: int = 3

    @classmethod
    def full(cls) -> "Config":
        return cls()

    @classmethod
    def quick(cls) -> "Config":
        """Under 3 minutes on two cores for the sample deck: a smaller reference
        (8×8 samples, depth 12), fewer depths, derivatives at ¼ size, fewer repeats."""
        return cls(ref_depth=12, ref_spp=8, depths=(0, 1, 2, 4, 10, 12), spps=(1, 2, 4), repeats=3,
                   derivative_scale=0.25, numpy_repeats=1, sphere_counts=(8, 32, 128, 1000), brute_counts=(128, 1000),
                   widths=(100, 200, 400), memory_depths=(0, 2, 10), scale_repeats=2)


@dataclasses.dataclass(frozen=True)
class Setting:
    """One render's knobs (a dict key: equal settings are measured once)."""

    dtype: str = "float32"
    depth: int = 10
    spp: int = 1
    edges: float = 0.0
    scale: float = 1.0


# -- measuring ---------------------------------------------------------------------------------


def timed(fn: Callable[[], object], repeats: int) -> dict:
    """First call (compiles), then `repeats` timed calls; compile ≈ first − median."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    med = float(np.median(runs))
    return {"compile_s": max(first - med, 0.0), "median_s": med, "runs_s": runs, "first_s": first, "out": out}


def quantize(image) -> np.ndarray:
    """What a file holds: clamped, rounded half up, 8-bit levels (as `rtjax.to_uint8`)."""
    return np.floor(np.clip(np.asarray(image, np.float64), 0, 255) + 0.5).astype(np.int16)


def upsample(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-pixel resampling onto a height × width grid (pixel centres to pixel centres)."""
    h, w = image.shape[:2]
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return image[rows][:, cols]


def image_errors(image, reference) -> dict:
    """Errors of an image against the reference, both as 8-bit files would hold them.

    psnr_db: None when identical (infinite); rms_levels, max_levels: level differences;
    frac_off: fraction of pixels off by ≥ 1 level in some channel."""
    a, b = quantize(image), quantize(reference)
    if a.shape != b.shape:
        a = upsample(a, *b.shape[:2])
    diff = np.abs(a.astype(np.int32) - b.astype(np.int32))
    mse = float(np.mean(diff.astype(np.float64) ** 2))
    return {
        "psnr_db": None if mse == 0 else 10 * math.log10(255.0**2 / mse),
        "rms_levels": math.sqrt(mse),
        "max_levels": int(diff.max()),
        "frac_off": float(np.mean(diff.max(axis=-1) >= 1)),
    }


def _label(knob: str, s: Setting, default: Setting) -> str:
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
    fractions = {0.25: "¼", 0.5: "½", 1.0: "1"}
    return f"scale {fractions.get(s.scale, f'{s.scale:g}')}"


def plan(default: Setting, reference: Setting, cfg: Config, secondary: bool) -> list[tuple[str, Setting]]:
    """(knob, setting) rows: the reference, the default, then each knob alone."""
    rows = [("reference", reference), ("default", default)]
    rows += [("dtype", dataclasses.replace(default, dtype=d)) for d in cfg.dtypes]
    if secondary:  # without mirrors or glass every depth renders the same image
        rows += [("depth", dataclasses.replace(default, depth=d)) for d in cfg.depths]
    rows += [("spp", dataclasses.replace(default, spp=k)) for k in cfg.spps]
    rows += [("edges", dataclasses.replace(default, edges=w)) for w in cfg.edges]
    rows += [("scale", dataclasses.replace(default, scale=f)) for f in cfg.scales]
    return rows


def _scaled(scene, factor: float):
    if factor == 1.0:
        return scene
    return scene.resized(max(1, int(round(scene.structure.width * factor))))


def render_setting(scene, s: Setting):
    """A zero-argument render of `scene` at setting `s` (for `timed`)."""
    import rtjax

    sc = _scaled(scene, s.scale)
    return lambda: rtjax.render(sc, depth=s.depth, spp=s.spp, dtype=s.dtype, edges=s.edges)


def bench_settings(scene, cfg: Config, log: Callable[[str], None]) -> tuple[list[dict], dict]:
    """Measure every row of `plan`; returns (rows, the reference's measurement)."""
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
            log(f"  {knob:9s} {_label(knob, s, default):28s} {1e3 * m['median_s']:9.1f} ms  "
                f"compile {m['compile_s']:5.1f} s  {_fmt_psnr(measured[s]['psnr_db'])}")
        sc = _scaled(scene, s.scale).structure
        label = _label(knob, s, default) + (" (default)" if knob not in ("default", "reference") and s == default else "")
        out.append({"knob": knob, "label": label, **dataclasses.asdict(s),
                    "width": sc.width, "height": sc.height, **measured[s]})
    return out, {"image": ref_img, **measured[reference]}


def _fmt_psnr(p) -> str:
    return "   ∞ dB" if p is None else f"{p:5.1f} dB"


# -- derivatives -------------------------------------------------------------------------------


def bench_derivatives(scene, cfg: Config, log: Callable[[str], None]) -> dict:
    """Reverse gradient, forward Jacobian in the centres and one LM step, each timed
    like a render and divided by the plain forward render's median at the same size."""
    import jax

    import rtjax

    sc = _scaled(scene, cfg.derivative_scale)
    st, p0 = sc.structure, sc.params
    log(f"derivatives at {st.width}×{st.height} (float32, depth {st.default_depth}) …")

    def image(p):
        return rtjax.render(rtjax.Scene(st, p))

    fwd = jax.jit(image)
    grad = jax.jit(jax.grad(lambda p: image(p).mean()))
    jac = jax.jit(jax.jacfwd(lambda c: image(_replace_params(p0, centers=c))))
    result = {"width": st.width, "height": st.height, "n_params_centers": int(p0.centers.size)}
    for name, fn, arg in (("forward", fwd, p0), ("grad", grad, p0), ("jacfwd_centers", jac, p0.centers)):
        m = timed(lambda fn=fn, arg=arg: fn(arg), cfg.repeats)
        m.pop("out")
        result[name] = m
        log(f"  {name:15s} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    if cfg.lm_step:
        step = _lm_step(st, p0, image)
        m = timed(step, cfg.repeats)
        m.pop("out")
        result["lm_step"] = m
        log(f"  {'lm_step':15s} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    base = result["forward"]["median_s"]
    for name in ("grad", "jacfwd_centers", "lm_step"):
        if name in result:
            result[name]["ratio"] = result[name]["median_s"] / base
    return result


def _replace_params(p, **changes):
    fields = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    fields.update(changes)
    return type(p)(**fields)


def _lm_step(st, p0, image):
    """One Levenberg–Marquardt step (optimistix) on the centres, fitting the image of
    the scene with every centre moved by 0.5: a zero-argument call for `timed`."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    target = jax.lax.stop_gradient(image(_replace_params(p0, centers=p0.centers + 0.5)))
    # the solver's coordinates in the default float type (float64 with x64: optimistix
    # builds its damped system in it), the render in the scene's own (as `fitting` does)
    y0 = jnp.asarray(p0.centers, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)

    def residuals(c, args):
        r = image(_replace_params(p0, centers=c.astype(p0.centers.dtype))) - args
        return r.ravel().astype(y0.dtype), None

    solver = optx.LevenbergMarquardt(rtol=1e-5, atol=1e-7)

    @eqx.filter_jit
    def init(y, args):
        f_struct, aux_struct = jax.eval_shape(lambda: residuals(y, args))
        return solver.init(residuals, y, args, {}, f_struct, aux_struct, frozenset())

    @eqx.filter_jit
    def step(y, state, args):
        y, state, _ = solver.step(residuals, y, args, {}, state, frozenset())
        return y, state

    state = init(y0, target)
    jax.block_until_ready(state)
    return lambda: step(y0, state, target)[0]


# -- the NumPy reference -----------------------------------------------------------------------


def numpy_reference_module():
    """tests/reference.py (the independent float64 NumPy renderer), or None when rtjax
    runs from an installation without the repository's tests folder."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "reference.py")
    if not os.path.exists(path):
        return None
    name = "rtjax_bench_numpy_reference"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while it loads
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def bench_numpy(deck_path: str, scene, width: int, depth: int, cfg: Config, default_image, log) -> dict | None:
    """The NumPy renderer on the same frame at the default settings (spp 1), timed."""
    ref = numpy_reference_module()
    if ref is None:
        return None
    with open(deck_path, encoding="utf-8") as f:
        frame = ref.parse_deck_text(f.read(), os.path.dirname(os.path.abspath(deck_path)))[0]
    frame.size = width
    log(f"NumPy reference renderer (tests/reference.py), depth {depth}, 1×1 …")
    runs = []
    for _ in range(max(1, cfg.numpy_repeats)):
        t0 = time.perf_counter()
        img = ref.render_reference(frame, depth=depth, spp=1)
        runs.append(time.perf_counter() - t0)
    agree = image_errors(default_image, img)
    return {"median_s": float(np.median(runs)), "runs_s": runs, "depth": depth, "spp": 1,
            "rtjax_default_vs_numpy": agree}


# -- scale ------------------------------------------------------------------------------------


def random_deck_text(n: int, seed: int = 0, size: int = 400, mirrors: float = 0.1, glass: float = 0.1) -> str:
    """A deck of `n` random non-overlapping spheres (radii 0.5–1.5) filling a cube at
    about 8 % of its volume, a tenth mirrors and a tenth glass, two lights, viewed
    from outside the cube's corner; image `size` pixels wide (400 × 294)."""
    rng = np.random.default_rng(seed)
    side = (n * 4 / 3 * math.pi / 0.08) ** (1 / 3)
    centers: list[np.ndarray] = []
    radii: list[float] = []
    cells: dict[tuple[int, int, int], list[int]] = {}
    cell = 3.0  # ≥ the largest diameter: overlaps are only with neighbouring cells
    while len(centers) < n:
        r = float(rng.uniform(0.5, 1.5))
        c = rng.uniform(-side / 2 + r, side / 2 - r, 3)
        key = tuple(int(k) for k in np.floor(c / cell))
        near = (j for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                for j in cells.get((key[0] + dx, key[1] + dy, key[2] + dz), ()))
        if all(np.linalg.norm(c - centers[j]) > r + radii[j] + 0.05 for j in near):
            cells.setdefault(key, []).append(len(centers))
            centers.append(c)
            radii.append(r)
    lines = [f"# {n} random spheres (rtjax.bench.random_deck_text, seed {seed})"]
    for c, r in zip(centers, radii):
        lines.append("sphe %.4f %.4f %.4f %.4f" % (*c, r))
        u = rng.uniform()
        if u < mirrors:
            lines.append("mirr")
        elif u < mirrors + glass:
            lines.append("trpa %.2f %.2f 0.2 10" % (rng.uniform(0.6, 0.9), rng.uniform(1.3, 1.8)))
        else:
            lines.append("opaq %.3f %.3f %.3f 0.3 20" % tuple(rng.uniform(0.1, 1, 3)))
    lines += ["back 0 0 128", "plig 0.5 0.5 2 255 255 255", "plig -1 0.3 0.5 100 100 80", "elig 0.2",
              "eyep %.3f %.3f %.3f" % (1.6 * side, 1.3 * side, 0.9 * side), "refp 0 0 0", "vang 40 30",
              f"size {size}", "rend random.sunimg", "quit"]
    return "\n".join(lines) + "\n"


def random_scene(n: int, seed: int = 0, size: int = 400):
    import rtjax

    return rtjax.parse_deck(random_deck_text(n, seed, size), f"<random {n}>").frames[0].scene


def bench_scale(scene, cfg: Config, log: Callable[[str], None]) -> dict:
    """Render time against spheres and pixels; gradient memory against depth."""
    import jax

    import rtjax

    out: dict = {"spheres": [], "pixels": [], "memory": []}
    log(f"scale: random scenes at width {cfg.scale_width}, default settings (float32, depth 10, 1×1) …")
    scenes = {n: random_scene(n, size=cfg.scale_width) for n in cfg.sphere_counts}
    images = {}
    for n, sc in scenes.items():
        m = timed(lambda sc=sc: rtjax.render(sc), cfg.scale_repeats)
        images[n] = np.asarray(m.pop("out"))
        out["spheres"].append({"n": n, "width": sc.structure.width, "height": sc.structure.height,
                               "culled": sc.structure.culls, **m})
        log(f"  {n:5d} spheres  {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s"
            f"{'  (culled)' if sc.structure.culls else ''}")
    brute = [n for n in cfg.brute_counts if n in scenes and scenes[n].structure.culls]
    if brute:
        log("  brute force (every ray against every sphere), one timed run each …")
        for n in brute:
            sc = rtjax.Scene(scenes[n].structure.replace(culling=False), scenes[n].params)
            m = timed(lambda sc=sc: rtjax.render(sc), 1)
            img = np.asarray(m.pop("out"))
            row = next(r for r in out["spheres"] if r["n"] == n)
            row["brute"] = m
            row["identical_to_brute"] = bool(np.array_equal(img, images[n]))
            row["max_abs_diff_to_brute"] = float(np.max(np.abs(img - images[n])))
            log(f"  {n:5d} spheres  brute {1e3 * m['median_s']:9.1f} ms  identical: {row['identical_to_brute']}")
    log(f"scale: the deck at widths {', '.join(map(str, cfg.widths))} …")
    for w in cfg.widths:
        sc = scene.resized(w)
        m = timed(lambda sc=sc: rtjax.render(sc), cfg.scale_repeats)
        m.pop("out")
        out["pixels"].append({"width": w, "height": sc.structure.height, "pixels": w * sc.structure.height, **m})
        log(f"  {w:5d}×{sc.structure.height:<5d} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    st = scene.structure
    log(f"scale: memory of the reverse gradient (mean image) against depth, {st.width}×{st.height} …")
    for depth in cfg.memory_depths if st.needs_secondary_rays else (0,):
        def loss(p, depth=depth):
            return rtjax.render(rtjax.Scene(st, p), depth=depth).mean()

        t0 = time.perf_counter()
        compiled = jax.jit(jax.grad(loss)).lower(scene.params).compile()
        seconds = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        fwd = jax.jit(loss).lower(scene.params).compile().memory_analysis()
        row = {"depth": depth, "compile_s": seconds, **_memory(mem, "grad"), **_memory(fwd, "forward")}
        out["memory"].append(row)
        log(f"  depth {depth:2d}  gradient peak {row['grad_peak_bytes'] / 2**20:8.1f} MiB   forward {row['forward_peak_bytes'] / 2**20:7.1f} MiB")
    return out


def _memory(stats, prefix: str) -> dict:
    if stats is None:
        return {f"{prefix}_peak_bytes": None}
    temp, arg, outb, alias = (int(getattr(stats, k, 0) or 0) for k in
                              ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes", "alias_size_in_bytes"))
    return {f"{prefix}_temp_bytes": temp, f"{prefix}_peak_bytes": temp + arg + outb - alias}


# -- the run ----------------------------------------------------------------------------------


def machine() -> dict:
    import jax

    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


def run(deck_path: str, cfg: Config | None = None, *, scale: bool = False, log: Callable[[str], None] = print) -> dict:
    """Measure a deck's first frame; returns the JSON-ready result (see the module doc)."""
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
    rows, ref = bench_settings(scene, cfg, log)
    result["settings"] = rows
    result["reference"] = {k: v for k, v in ref.items() if k != "image"}
    default = next(r for r in rows if r["knob"] == "default")
    if cfg.derivatives:
        result["derivatives"] = bench_derivatives(scene, cfg, log)
    note = None
    if cfg.numpy:
        default_img = np.asarray(rtjax.render(scene))
        np_result = bench_numpy(deck_path, scene, st.width, st.default_depth, cfg, default_img, log)
        if np_result is None:
            note = "tests/reference.py not found (an installed rtjax without the repository's tests): NumPy timing skipped"
        else:
            np_result["speedup"] = np_result["median_s"] / default["median_s"]
        result["numpy"] = np_result
    else:
        note = "NumPy timing not asked for"
    if note:
        result["numpy_note"] = note
    if scale:
        result["scale"] = bench_scale(scene, cfg, log)
    result["total_s"] = time.perf_counter() - started
    return _jsonable(result)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


# -- output -----------------------------------------------------------------------------------


def table_text(result: dict) -> str:
    """The knob table, the derivative costs and the NumPy ratio as plain text."""
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
        lines.append(f"NumPy float64 reference renderer (tests/reference.py), depth {n['depth']}, 1×1: {1e3 * n['median_s']:.0f} ms; "
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
    return next(r for r in result["settings"] if r["knob"] == "default")


def pareto_plot(result: dict, path: str) -> None:
    """Error (RMS level difference, log) against render time (ms, log), one labelled
    point per distinct setting, the Pareto front (nothing both faster and more
    accurate) joined by a line. Drawn on a `matplotlib.figure.Figure` of its own (not
    pyplot): the caller's backend, a notebook's say, is left as it is."""
    from matplotlib.figure import Figure

    seen, pts = set(), []
    for r in result["settings"]:
        key = (r["dtype"], r["depth"], r["spp"], r["edges"], r["scale"])
        if r["knob"] == "reference" or key in seen:
            continue
        seen.add(key)
        pts.append((1e3 * r["median_s"], max(r["rms_levels"], 1e-3), r["label"], r["knob"]))
    colours = {"default": "black", "dtype": "tab:purple", "depth": "tab:blue", "spp": "tab:green", "edges": "tab:orange", "scale": "tab:red"}
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
    """Three log-log panels: time against spheres (culled and brute force), time against
    pixels, gradient memory against depth (a `Figure` of its own, as `pareto_plot`)."""
    from matplotlib.figure import Figure

    s = result["scale"]
    fig = Figure(figsize=(14, 4.3), dpi=110)
    axes = fig.subplots(1, 3)
    ax = axes[0]
    ax.plot([r["n"] for r in s["spheres"]], [1e3 * r["median_s"] for r in s["spheres"]], "o-", label="rtjax (culled beyond 32)")
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


def write_outputs(result: dict, outdir: str, stem: str) -> dict[str, str]:
    """bench_<stem>.json, bench_<stem>.png (Pareto), bench_<stem>_scale.png (with --scale)."""
    from .atomic import atomic_write

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
    """What `rtjax bench` runs: measure, print the table, write JSON and plots."""
    cfg = cfg or (Config.quick() if quick else Config.full())
    result = run(deck, cfg, scale=scale, log=log)
    stem = os.path.splitext(os.path.basename(deck))[0]
    paths = write_outputs(result, outdir, stem)
    log("")
    log(table_text(result))
    log("wrote " + ", ".join(paths.values()) + f"  ({result['total_s']:.0f} s in all)")
    return paths


__all__: Sequence[str] = ["Config", "Setting", "run", "table_text", "pareto_plot", "scale_plot", "write_outputs",
                          "random_deck_text", "random_scene", "image_errors", "main_bench"]
