"""Write and run the worked-example notebooks in notebooks/:

* 01_render.ipynb: a forward tour (decks, every level, re-rendering without a
  recompile, the Sun raster round trip, a texture),
* 02_fit.ipynb: fitting (centres, then colours and ke, from a known truth; a photo-like
  target with a robust loss and nuisance parameters),
* 03_tradeoff.ipynb: the speed/accuracy study of the sample deck (rtjax.bench) and a tour
  of the numerical extremes with gradient maps.

The notebooks are generated from the cells below (so they are reviewable as code),
executed from a fresh kernel with nbclient (kernel `python3`) and saved with their
outputs:

    python scripts/make_notebooks.py                # write, run in full mode, save with outputs
    python scripts/make_notebooks.py --quick 01     # run one in reduced mode (outputs not saved)
    python scripts/make_notebooks.py --no-execute   # write the cells only (no outputs)

Reduced mode (the test suite, tests/test_notebooks.py): the environment variable
RTJAX_NOTEBOOK_QUICK=1 makes every notebook use small images and few iterations; every
cell still runs. `execute(..., quick=True)` also gives the kernel cheaper compiles
(QUICK_COMPILES).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import textwrap
import time

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOKS = os.path.join(ROOT, "notebooks")
QUICK_ENV = "RTJAX_NOTEBOOK_QUICK"


def md(text: str):
    return new_markdown_cell(textwrap.dedent(text).strip("\n"))


def code(text: str):
    return new_code_cell(textwrap.dedent(text).strip("\n"))


# The first code cell of every notebook: quick mode, the repository root, imports.
SETUP = '''
import os, pathlib, time

# RTJAX_NOTEBOOK_QUICK=1: the reduced mode the test suite runs (small images, few
# iterations); every cell still runs.
QUICK = os.environ.get("RTJAX_NOTEBOOK_QUICK") == "1"

# the repository root: the first folder up from here that holds scenes/ex2s3.dat
ROOT = pathlib.Path.cwd().resolve()
while not (ROOT / "scenes" / "ex2s3.dat").exists():
    if ROOT == ROOT.parent:
        raise FileNotFoundError("run this notebook from inside the rtjax repository")
    ROOT = ROOT.parent
SCENES = ROOT / "scenes"
'''

SHOW = '''
def show(images, titles=None, height=2.8, max_width=15.0, cmap=None):
    """Images side by side; (H, W, 3) arrays in 0..255 are shown as 8-bit files hold them."""
    images = [np.asarray(im) for im in images]
    widths = [height * im.shape[1] / im.shape[0] for im in images]
    k = min(1.0, max_width / (sum(widths) + 0.3 * len(images)))
    fig, axes = plt.subplots(1, len(images), figsize=(k * (sum(widths) + 0.3 * len(images)), k * height + 0.45),
                             squeeze=False, gridspec_kw={"width_ratios": widths})
    for ax, im, title in zip(axes[0], images, titles or [""] * len(images)):
        if im.ndim == 3:
            ax.imshow(rtjax.to_uint8(im), interpolation="nearest")
        else:  # one channel, 0..255 (difference images: white = none)
            ax.imshow(im, cmap=cmap or "gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout(pad=0.3)
    plt.show()
'''

# --------------------------------------------------------------------------------------
# 01: the forward tour
# --------------------------------------------------------------------------------------


def nb_render() -> list:
    return [
        md("""
        # rtjax, forward: decks, levels, re-rendering, Sun rasters, textures

        This notebook loads a scene deck, renders one deck per level of the assignment
        (opaque spheres, mirrors, glass, textures), changes parameters and re-renders
        without compiling again, writes and reads a Sun raster file, and plays with a
        texture. Everything below was produced by running the notebook top to bottom; the
        numbers quoted in the text are printed by the cells above them.
        """),
        code(SETUP + '''
import struct, tempfile

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import rtjax

WIDTH = 96 if QUICK else None  # None: every deck at its own size
print(f"rtjax {rtjax.__version__}, jax {jax.__version__} on {jax.default_backend()}; quick mode: {QUICK}")
'''),
        code(SHOW + '''

# count XLA compilations: JAX reports each one as a monitoring event
COMPILES = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kw: COMPILES.append(kw.get("fun_name", "?"))
    if event == "/jax/core/compile/backend_compile_duration" else None)


def sized(scene):
    return scene if WIDTH is None else scene.resized(WIDTH)


def timed_render(scene, **options):
    t0 = time.perf_counter()
    image = jax.block_until_ready(rtjax.render(scene, **options))
    return image, time.perf_counter() - t0
'''),
        md("""
        ## A deck

        A deck is a small text file of commands (`sphe`, `opaq`, `mirr`, `trpa`, `tmap`,
        `plig`, `back`, `elig`, `eyep`, `refp`, `vang`, `size`, `rend`; see
        `docs/DECK.md`). `rtjax.load_deck` parses it into one frame per `rend` line; a
        frame's scene is a pytree of a static `Structure` (what the compiled renderer
        depends on: material kinds, counts, image size) and array `Params` (everything
        differentiable, in the deck's units). Here is the assignment's sample deck.
        """),
        code('''
print((SCENES / "ex2s3.dat").read_text())
deck = rtjax.load_deck(SCENES / "ex2s3.dat")
scene = sized(deck.frames[0].scene)
st = scene.structure
print(f"{len(deck.frames)} frame(s); structure: {st.n_spheres} spheres {st.kinds}, {st.n_lights} light(s), "
      f"{st.width}×{st.height} pixels, default depth {st.default_depth}")
print("sphere centres (deck units):\\n", np.asarray(scene.params.centers))
'''),
        md("""
        `rtjax.render` returns a float image (height × width × 3, levels 0..255, clamped
        but not rounded). The first call compiles the renderer for this structure; later
        calls reuse it. The timing line below shows the difference.
        """),
        code('''
image, first_ex2s3 = timed_render(scene)
_, second = timed_render(scene)
print(f"{image.shape} {image.dtype}; first render (compile + run) {first_ex2s3:.2f} s, second {1e3 * second:.0f} ms")
show([image], [f"ex2s3.dat, {st.width}×{st.height}"], height=4.0)
'''),
        md("""
        ## One deck per level

        `scenes/` holds one deck per level of the assignment: level 1 opaque Phong spheres
        with shadows, level 2 mirrors, level 3 refracting glass, level 4 texture-mapped
        spheres. Each has its own structure, so each compiles once. Opaque-only scenes
        need no secondary rays (depth 0); with mirrors or glass the default depth is 10.
        """),
        code('''
LEVELS = ["level1_opaque", "level2_mirrors", "level3_glass", "level4_textures"]
level_scenes, level_images, titles = {}, [], []
for name in LEVELS:
    s = sized(rtjax.load_deck(SCENES / f"{name}.dat").frames[0].scene)
    img, first = timed_render(s)
    _, again = timed_render(s)
    level_scenes[name] = s
    level_images.append(img)
    titles.append(f"{name} ({s.structure.width}×{s.structure.height})")
    print(f"{name:16s} {s.structure.n_spheres} spheres {sorted(set(s.structure.kinds))}, depth {s.structure.default_depth:2d}: "
          f"first {first:5.2f} s, again {1e3 * again:6.1f} ms")
show(level_images[:2], titles[:2], height=3.6)
show(level_images[2:], titles[2:], height=3.6)
'''),
        md("""
        Each deck's comments say what to look for. Level 1: the four balls' highlights
        grow smaller and sharper from left to right as the Phong exponent β grows (2, 10,
        50, 400), and every ball casts a shadow. Level 2: the two large mirrors reflect
        the red and yellow balls between them back and forth, a smaller copy in each
        bounce. Level 3: the middle row's glass spheres go from n = 1 (no bending) to
        2.42 (diamond), and the backdrop balls seen through them turn upside down and
        shrink as n grows; the marble at the front right has a mirror core and shows
        total internal reflection. Level 4: the planet, the checker ball, the bands and a
        tiny 5 × 3 texture are texture-mapped; the glass lens shows the checker ball, and
        the mirror ball at the back reflects the textured spheres.

        ## Change a parameter, render again: no recompilation

        Only the `Structure` is compiled in. Parameters are arrays: a new ambient
        coefficient, moved spheres, other colours or another light direction reuse the
        compiled renderer. The cell counts XLA compilations while it renders four
        variants of the sample deck.
        """),
        code('''
c = np.asarray(scene.params.centers)
variants = {
    "ke 0.2 → 0.6": scene.replace(ke=0.6),
    "yellow sphere up 15": scene.replace(centers=c + np.array([[0, 0, 15]] + [[0, 0, 0]] * 7)),
    "colours rotated (RGB → GBR)": scene.replace(diffuse=np.roll(np.asarray(scene.params.diffuse), 1, axis=1)),
    "light from the other side": scene.replace(light_dirs=np.array([[-0.5, -0.5, 2.0]])),
}
before = len(COMPILES)
images, seconds = [], []
for s in variants.values():
    img, dt = timed_render(s)
    images.append(img)
    seconds.append(dt)
n_new = len(COMPILES) - before
print(f"{len(variants)} renders with new parameters: {n_new} compilations, "
      f"{', '.join(f'{1e3 * t:.0f}' for t in seconds)} ms each (the first render of this scene took {first_ex2s3:.2f} s)")
show(images, list(variants), height=2.4)
'''),
        md("""
        What is compiled in is the structure: another image size, depth or number of
        samples is another renderer. The next cell renders the same scene at another
        width and counts the compilations that causes; rendering that size again costs
        none.
        """),
        code('''
before = len(COMPILES)
small = scene.resized(st.width // 2)
img_small, t_small = timed_render(small)
after_first = len(COMPILES) - before
_, t_again = timed_render(small.replace(ke=0.6))
print(f"width {st.width} → {small.structure.width}: {after_first} compilation(s), {t_small:.2f} s; "
      f"the same size with other parameters: {len(COMPILES) - before - after_first} more, {1e3 * t_again:.0f} ms")
'''),
        md("""
        ## The Sun raster round trip

        The assignment writes Sun raster files. `rtjax.save_image` picks the format by
        extension (`.sunimg`, `.ras`, … through rtjax's own codec; PNG, JPEG, EXR, …
        through OpenImageIO), rounding to the nearest level; `rtjax.load_image` reads any
        of them back. The cell writes the render, decodes the 32-byte header, reads the
        file back with rtjax and, independently, with Pillow, and compares both with the
        8-bit image.
        """),
        code('''
from PIL import Image

tmp = pathlib.Path(tempfile.mkdtemp(prefix="rtjax_nb_"))
path = tmp / "ex2s3.sunimg"
rtjax.save_image(path, image)
raw = path.read_bytes()
magic, w, h, depth, length, kind, maptype, maplength = struct.unpack(">8I", raw[:32])
print(f"{path.name}: {len(raw)} bytes; header: magic {magic:#x}, {w}×{h}, depth {depth}, "
      f"{length} bytes of pixels (rows padded to even), type {kind} (B,G,R), no colour map ({maptype}, {maplength})")
back = rtjax.load_image(path)
with Image.open(path, formats=["SUN"]) as im:
    pillow = np.asarray(im.convert("RGB"))
want = rtjax.to_uint8(image)
print("read back by rtjax is the 8-bit image:", np.array_equal(back, want))
print("read back by Pillow is the 8-bit image:", np.array_equal(pillow, want))
print(f"largest change from the float render: {np.abs(back - np.asarray(image)).max():.3f} levels (rounding only)")

# the assignment's own code wrote R,G,B under type 1: `assignment_order=True` writes that
# literal order; a standard reader then swaps red and blue (the dark-blue sky turns dark red)
rtjax.save_image(tmp / "literal.sunimg", image, assignment_order=True)
swapped = rtjax.load_image(tmp / "literal.sunimg")
literal = rtjax.load_image(tmp / "literal.sunimg", assignment_order=True)
print("assignment order read in assignment order is the image:", np.array_equal(literal, want))
show([image, back, swapped], ["render", "written and read back (.sunimg)", "assignment order read as standard"], height=2.6)
'''),
        md("""
        ## A texture

        A `tmap` sphere takes its diffuse colour from an equirectangular texture (columns
        are longitude, rows colatitude from the north pole). Textures are Sun raster
        files too, and once loaded their texels are parameters like any other: below the
        planet of level 4 is turned by a quarter of a revolution (texel columns rolled),
        its oceans recoloured, and the scene rendered again without compiling anything.
        """),
        code('''
tex_scene = level_scenes["level4_textures"]
planet = rtjax.load_image(SCENES / "textures" / "planet.sunimg")
print(f"planet.sunimg: {planet.shape[1]}×{planet.shape[0]} texels, {planet.dtype}; "
      f"textures in the scene: {[t.shape[:2] for t in tex_scene.params.textures]}")
textures = list(tex_scene.params.textures)
k = next(i for i, t in enumerate(textures) if t.shape == planet.shape)
turned = np.roll(np.asarray(textures[k]), planet.shape[1] // 4, axis=1)
blue = (turned[..., 2] > turned[..., 0] + 40)[..., None]  # ocean texels
recoloured = np.where(blue, turned[..., [2, 0, 1]], turned)  # (B, R, G): oceans crimson
before = len(COMPILES)
img_turned, _ = timed_render(tex_scene.replace(textures=tuple(textures[:k] + [turned] + textures[k + 1:])))
img_recol, _ = timed_render(tex_scene.replace(textures=tuple(textures[:k] + [recoloured] + textures[k + 1:])))
print(f"two renders with new texels: {len(COMPILES) - before} compilations")
show([planet, turned, recoloured], ["planet.sunimg", "rolled a quarter turn", "oceans recoloured"], height=1.6)
show([level_images[3], img_turned, img_recol], ["level 4 as in the deck", "planet turned", "oceans recoloured"], height=2.6)
'''),
        md("""
        ## Derivatives come with it

        The renderer is a JAX function of the parameters, so `jax.grad` differentiates any
        scalar of the image: below, the mean level of the sample deck's image against the
        ambient coefficient and against each sphere's radius, all in one reverse pass.

        This is the plain render, sampled at pixel centres: piecewise constant across
        silhouettes, so its derivative sees how a sphere's shading changes as the radius
        grows but not its outline moving over what lies behind. The silhouette-aware
        mode (`render(scene, edges=1)`, README) includes that motion; `03_tradeoff.ipynb`
        shows derivative images made with it, and `02_fit.ipynb` fits scenes to images
        with it.
        """),
        code('''
def mean_level(params):
    return rtjax.render(rtjax.Scene(st, params)).mean()

g = jax.grad(mean_level)(scene.params)
print(f"d(mean level)/d ke = {float(g.ke):.1f} levels per unit")
for i, (kind, dr) in enumerate(zip(st.kinds, np.asarray(g.radii))):
    print(f"  sphere {i} ({kind}): d(mean level)/d radius = {dr:+.3f} levels per unit")
'''),
    ]


# --------------------------------------------------------------------------------------
# 02: fitting
# --------------------------------------------------------------------------------------

FIT_DECK = """\
# three balls on a floor (the floor is a huge sphere), two lights
sphe 0 0 -1000 1000
opaq 0.75 0.72 0.65 0.05 2
sphe -14 6 8 8
opaq 0.9 0.25 0.15 0.5 20
sphe 4 -4 6 6
opaq 0.2 0.55 0.95 0.4 12
sphe 17 14 10 10
opaq 0.95 0.8 0.2 0.3 8
plig 0.6 -0.8 1.2 230 220 200
plig -1 -0.3 0.6 60 70 110
back 30 40 70
elig 0.2
eyep 0 -70 35
refp 2 4 6
vang 50 36
size 240
rend truth.sunimg
"""


def nb_fit() -> list:
    return [
        md("""
        # rtjax, inverse: fitting a scene to an image

        `fitting.fit(scene, target, free=...)` adjusts the chosen parameters of a scene
        until its render matches a target image, with optimistix's Levenberg–Marquardt
        solver on the residuals of the silhouette-aware render, coarse to fine (see the
        README's "Fitting a scene to an image"). This notebook

        1. makes a target from a known truth, moves the spheres, and fits the centres back;
        2. then fits the colours and the ambient coefficient `ke`;
        3. makes a photo-like target (blur, camera response, noise, JPEG, and a date
           stamp burnt into the picture) and shows what nuisance parameters for the
           camera and the robust Cauchy loss do.

        Every number quoted in the text is printed by the cell above it.
        """),
        code(SETUP + '''
import io

import jax
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image, ImageDraw, ImageFont

import fitting
import rtjax

WIDTH = 64 if QUICK else 240          # image width of truth, target and fits
STEPS = (10, 8, 6) if QUICK else (30, 20, 25)  # iterations: centres, colours and ke, photo-like target
print(f"quick mode: {QUICK}; images {WIDTH} pixels wide; at most {STEPS} iterations")
'''),
        code(SHOW + '''

def plot_histories(results, labels, title):
    """Loss per iteration (log scale), one line per fit; pyramid levels marked by their width."""
    fig, ax = plt.subplots(figsize=(7.5, 3.3))
    for res, label in zip(results, labels):
        h = res.history
        line, = ax.semilogy([r["step"] for r in h], [r["loss"] for r in h], "o-", ms=3, label=label)
        for a, b in zip(h, h[1:]):
            if b["width"] != a["width"]:
                ax.axvline(a["step"] + 0.5, color=line.get_color(), lw=0.6, ls=":")
    h = results[0].history
    for r in h:
        if r is h[0] or r["width"] != h[h.index(r) - 1]["width"]:
            ax.annotate(f"{r['width']} px", (r["step"], 1.0), xycoords=("data", "axes fraction"), fontsize=7,
                        va="bottom", ha="left")
    ax.set_xlabel("iteration (levels: 1/4, 1/2, full size; widths on top)")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=10, pad=12)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    plt.show()


def difference(a, b, gain=4.0):
    """|a − b| per pixel (largest channel), ×gain, as a grey image (white = 255/gain levels or more)."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max(axis=-1)
    return np.clip(255 - gain * d, 0, 255)
'''),
        md("""
        ## A known truth

        The truth is a small deck: three balls on a floor, a warm key light and a cool
        fill light. The target is its render rounded to 8-bit levels, as a file would
        hold it.
        """),
        code(f'''
DECK = """\\
{FIT_DECK}"""
truth = rtjax.parse_deck(DECK).frames[0].scene.resized(WIDTH)
target = np.floor(np.asarray(rtjax.render(truth)) + 0.5)
print(f"truth: {{truth.structure.n_spheres}} spheres, {{truth.structure.width}}×{{truth.structure.height}}")
show([target], ["target (the truth, rendered)"], height=3.2)
'''),
        md("""
        ## 1. Centres

        Each ball's centre is moved by up to ±2.5 units in each direction (a quarter to
        two fifths of a radius); the floor stays. `fitting.fit` with `free="centers"`
        and `spheres=[1, 2, 3]` fits the nine coordinates. Depth along the line of sight
        is seen only through perspective and shadows, so it is the least determined.
        """),
        code('''
rng = np.random.default_rng(7)
true_c = np.asarray(truth.params.centers)
moved = true_c.copy()
moved[1:] += rng.uniform(-2.5, 2.5, (3, 3))
start = truth.replace(centers=moved)
print("start error per ball (units):", np.round(np.linalg.norm(moved - true_c, axis=1)[1:], 2))

t0 = time.perf_counter()
res_c = fitting.fit(start, target, "centers", spheres=[1, 2, 3], max_steps=STEPS[0])
print(f"{res_c.steps} iterations in {time.perf_counter() - t0:.1f} s "
      f"(of which the first, with the compilation, {res_c.times['first_step']:.1f} s): {res_c.result} ({res_c.message})")
fitted_c = np.asarray(res_c.scene.params.centers)
print(f"{'ball':>4s}  {'start':>22s}  {'fitted':>22s}  {'truth':>22s}  error")
for i in (1, 2, 3):
    print(f"{i:4d}  {np.array2string(moved[i], precision=2):>22s}  {np.array2string(fitted_c[i], precision=2):>22s}  "
          f"{np.array2string(true_c[i], precision=2):>22s}  {np.linalg.norm(fitted_c[i] - true_c[i]):.3f}")
err_c = np.abs(fitted_c - true_c)[1:].max()
print(f"FIT centres: max centre error {err_c:.3f} units (start {np.abs(moved - true_c)[1:].max():.2f}); "
      f"RMS residual {np.sqrt(2 * res_c.loss) * 255:.2f} levels")
'''),
        code('''
plot_histories([res_c], ["centres (LM, Cauchy loss)"], "fitting the centres: loss per iteration")
img_start = rtjax.render(start)
img_fit = rtjax.render(res_c.scene)
show([img_start, img_fit, target, difference(img_start, target), difference(img_fit, target)],
     ["start", "fitted", "target", "|start − target| ×4", "|fitted − target| ×4"], height=2.3)
'''),
        md("""
        Each pyramid level measures its own image (dotted lines where the width
        changes: quarter size, half size, full size), so the loss jumps where a level
        starts. The full-size level is matched at pixel centres, as the target was
        rendered: an edge pixel counts exactly when its centre lies on the target's side
        of the edge, so the fit is unbiased there; the steep drop at its start is where
        its sharp edges meet the target's. The difference images (white = no difference) show the start's
        misplaced silhouettes and shadows, and what is left after the fit; the table
        gives each ball's remaining error in deck units.

        ## 2. Colours and `ke`

        Next, starting from the fitted centres, every sphere's colour (the floor's too)
        is set to a neutral grey 0.5 and the ambient coefficient to 0.5; the fit
        recovers 13 numbers: `free="colors,ke"`. Colours and `ke` are bounded to [0, 1]
        by a logistic reparameterisation, so the solver can never leave the valid range.
        """),
        code('''
true_d = np.asarray(truth.params.diffuse)
start2 = res_c.scene.replace(diffuse=np.full_like(true_d, 0.5), ke=0.5)
t0 = time.perf_counter()
res_d = fitting.fit(start2, target, "colors,ke", max_steps=STEPS[1])
print(f"{res_d.steps} iterations in {time.perf_counter() - t0:.1f} s: {res_d.result} ({res_d.message})")
fit_d = np.asarray(res_d.scene.params.diffuse)
for i in range(truth.structure.n_spheres):
    print(f"sphere {i}: colour {np.round(fit_d[i], 3)}  truth {np.round(true_d[i], 3)}")
print(f"ke {float(res_d.scene.params.ke):.4f}  truth {float(truth.params.ke):.4f}")
err_d = max(np.abs(fit_d - true_d).max(), abs(float(res_d.scene.params.ke) - float(truth.params.ke)))
print(f"FIT colours: max colour or ke error {err_d:.4f}; RMS residual {np.sqrt(2 * res_d.loss) * 255:.2f} levels")
plot_histories([res_d], ["colours and ke (LM, Cauchy loss)"], "fitting colours and ke: loss per iteration")
img_start2 = rtjax.render(start2)
img_fit2 = rtjax.render(res_d.scene)
show([img_start2, img_fit2, target, difference(img_fit2, target)],
     ["start: grey, ke 0.5", "fitted", "target", "|fitted − target| ×4"], height=2.5)
'''),
        md("""
        Colours enter the image almost linearly: the loss falls steadily on the coarse
        level, and the full-size level brings it to the level of the centres' remaining error
        (the table compares each fitted number with the truth).

        ## 3. A photo-like target

        A photograph is not a render. The target below is the truth rendered with 4×4
        samples per pixel (antialiased), seen through a camera:

        * a **Gaussian blur** of σ = 0.7 pixels (the lens),
        * a **camera response** 255·(1.15·I/255)^0.8 (exposure and gamma),
        * **noise** of σ = 3 levels,
        * **JPEG** compression at quality 75 (Pillow),
        * and a **date stamp** burnt into the lower right corner over the floor, as old
          cameras did: a few hundred pixels that no scene explains.

        The geometry is that of step 1 (the fitted centres); colours and `ke` are fitted
        from grey again, three ways:

        1. `loss="cauchy"` (the default, as in step 2), the scene's parameters only;
        2. `loss="l2"`, plain least squares, with the nuisance parameters of a camera
           model fitted jointly (`nuisance=("camera",)`: `gain` and `gamma`, `blur`, a
           further `chroma` blur for JPEG's subsampled colour, and the `order` of blur
           and response; `fitting.camera` is the model);
        3. `loss="cauchy"` with the same nuisance parameters.

        The first and the last differ by the nuisance parameters, the last two by the loss.
        """),
        code('''
CAMERA = {"gain": 1.15, "gamma": 0.8, "blur": 0.7}  # lens blur, then the response 255·(gain·I/255)^gamma


def photograph(scene, seed=0):
    image = np.asarray(fitting.camera(rtjax.render(scene, spp=4), CAMERA))
    image = image + np.random.default_rng(seed).normal(0, 3, image.shape)
    pil = Image.fromarray(rtjax.to_uint8(np.clip(image, 0, 255)))
    h, w = image.shape[:2]
    try:
        font = ImageFont.load_default(size=max(8, round(0.1 * h)))
    except TypeError:  # Pillow before 10.1: one small bitmap font
        font = ImageFont.load_default()
    ImageDraw.Draw(pil).text((0.97 * w, 0.97 * h), "'10 6 14", fill=(255, 140, 40), font=font, anchor="rb")
    buf = io.BytesIO()
    pil.save(buf, "JPEG", quality=75)
    return np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"), np.float64), len(buf.getvalue())


photo, nbytes = photograph(truth)
clean = np.asarray(rtjax.render(truth))
stamp = np.abs(photo - np.asarray(fitting.camera(rtjax.render(truth, spp=4), CAMERA))).max(-1) > 40
print(f"photo: {photo.shape[1]}×{photo.shape[0]}, JPEG {nbytes} bytes; RMS difference from the render: "
      f"{np.sqrt(np.mean((photo - clean) ** 2)):.1f} levels; {stamp.sum()} pixels off by more than 40 levels "
      f"from the camera's noiseless view (the stamp)")
show([target, photo, difference(photo, target, gain=2)], ["render (truth)", "photo-like target", "|photo − render| ×2"],
     height=3.0)
'''),
        code('''
WAYS = {"cauchy": dict(loss="cauchy"),
        "l2 + camera": dict(loss="l2", nuisance=("camera",)),
        "cauchy + camera": dict(loss="cauchy", nuisance=("camera",))}
runs = {}
for label, options in WAYS.items():
    t0 = time.perf_counter()
    runs[label] = fitting.fit(start2, photo, "colors,ke", max_steps=STEPS[2], **options)
    print(f"{label:16s} {runs[label].steps:3d} iterations, {time.perf_counter() - t0:5.1f} s, {runs[label].result}")

print()
print(f"{'fit':16s} {'balls: colour err':>17s} {'floor: colour err':>17s} {'ke':>6s}   camera (made with gain 1.15, gamma 0.8, blur 0.7)")
errors = {}
for label, res in runs.items():
    d = np.asarray(res.scene.params.diffuse)
    balls, floor = np.abs(d[1:] - true_d[1:]).max(), np.abs(d[0] - true_d[0]).max()
    ke = float(res.scene.params.ke)
    errors[label] = max(balls, floor, abs(ke - float(truth.params.ke)))
    cam = ", ".join(f"{k} {v:.3f}" for k, v in res.nuisance.items()) or "-"
    print(f"{label:16s} {balls:17.3f} {floor:17.3f} {ke:6.3f}   {cam}")
best = min(errors, key=errors.get)
print(f"\\nFIT photo: smallest largest error {errors[best]:.3f} with {best} (truth: ke {float(truth.params.ke):.2f})")
'''),
        code('''
plot_histories(list(runs.values()), list(runs), "photo-like target: colours and ke, three ways")
labels = list(runs)
show([photo] + [rtjax.render(runs[k].scene) for k in labels], ["photo-like target"] + [f"fitted scene: {k}" for k in labels],
     height=2.4)
model = {k: np.asarray(fitting.camera(rtjax.render(runs[k].scene, spp=4), runs[k].nuisance)) for k in labels}
show([difference(model[k], photo, gain=3) for k in labels], [f"|model − photo| ×3: {k}" for k in labels], height=2.4)
'''),
        md("""
        How to read this (the table above has this run's numbers):

        * **Without nuisance parameters** (`cauchy`) nothing in the scene can explain the
          camera's response: the colours and `ke` take the blame (errors of about a tenth
          of the colour range), and the fitted scene (first fitted image) is rendered
          with the photo's exposure and contrast instead of its own; the sky, whose
          colour is not free, is left over in its `|model − photo|` map.
        * **With the camera model** fitted jointly, the response is absorbed by the
          numbers it was made with (printed beside each fit), and the scene's
          own colours and `ke` come out within about 0.02 of the truth. The fitted images
          are renders of the scene alone, without the camera, and look like the truth.
        * **The loss**: the date stamp is a few hundred pixels of a colour no scene
          parameter produces. Least squares (`l2 + camera`) lets them pull on whatever
          can reduce their squared error: the floor's colour, which lies under the
          stamp, and the camera's gain and gamma come out further from the truth than
          with the Cauchy loss, which grows only logarithmically for residuals much
          larger than its scale (10 levels), so the stamp barely pulls. The balls'
          colours, away from the stamp, are about equally good either way.
        * The losses of the three fits are different functions (and each level of the
          pyramid measures a different image), so the convergence plot shows how each fit
          progresses, not which is better. The `|model − photo|` maps show each fitted
          scene through its fitted camera against the photo: what remains is the stamp,
          edges softened by JPEG, and noise, which no fit removes.

        This is why the Cauchy loss is the default of `fitting.fit` and `rtjax fit`.
        """),
    ]


# --------------------------------------------------------------------------------------
# 03: the trade-off study and the numerical extremes
# --------------------------------------------------------------------------------------


def nb_tradeoff() -> list:
    return [
        md("""
        # rtjax: speed against accuracy, and the numerical extremes

        Part 1 measures, on the assignment's sample deck, what each knob of the renderer
        costs and buys: the reflection/refraction **depth**, the samples per pixel
        (**spp**), the floating-point **dtype**, the **silhouette-aware** mode (edges)
        and the **resolution**. Each knob is varied alone from the default render
        (float32, depth 10, 1 sample per pixel, pixel centres) and compared with a
        reference (float64, deeper, many samples per pixel); the measurements are
        `rtjax.bench`'s (the same as `rtjax bench scenes/ex2s3.dat`).

        Part 2 renders the numerical extremes that `tests/test_extremes.py` checks (a ray
        exactly tangent to a sphere, the onset of total internal reflection, a Phong
        exponent of 10 000, spheres of radius 10⁻³ and 10⁵, the eye inside glass, …)
        and shows each image with a derivative image, all finite.
        """),
        code(SETUP + '''
import dataclasses, functools, tempfile

import jax

jax.config.update("jax_enable_x64", True)  # the reference renders in float64 (decks stay float32)
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image as PNG, display

import rtjax
from rtjax import bench

if QUICK:  # small images, one timed run each, no derivative timings
    CFG = bench.Config(ref_depth=6, ref_spp=2, depths=(0,), spps=(1, 2), edges=(1.0,), scales=(0.5, 1.0), repeats=1,
                       derivatives=False, numpy=False, width=64)
else:  # `rtjax bench --quick` (reference 8×8 samples at depth 12, derivatives timed at ¼ size), 5 timed runs each
    CFG = dataclasses.replace(bench.Config.quick(), repeats=5)
EXTREME_WIDTH = 32 if QUICK else 96
print(f"quick mode: {QUICK}; {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()}")
'''),
        code(SHOW + '''

def show_png(draw, *args):
    """Run a plotting function that writes a PNG (rtjax.bench's plots do), show the PNG."""
    path = os.path.join(tempfile.mkdtemp(prefix="rtjax_nb_"), "plot.png")
    draw(*args, path)
    get_ipython().run_line_magic("matplotlib", "inline")  # they select Agg: back to inline figures
    display(PNG(filename=path))
'''),
        md("""
        ## 1. The knobs, measured

        The next cell runs the study (it prints one line per setting as it goes, then the
        table). Times are medians of repeated renders after compilation, on this
        machine, whatever else it was running; the error is that of the image as an
        8-bit file would hold it, against the reference.
        """),
        code('''
deck_path = os.path.relpath(SCENES / "ex2s3.dat")
result = bench.run(deck_path, CFG, log=print)
result["deck"] = "scenes/ex2s3.dat"
print()
print(bench.table_text(result))
'''),
        code('''
show_png(bench.pareto_plot, result)
front, best = [], float("inf")
for r in sorted((r for r in result["settings"] if r["knob"] != "reference"), key=lambda r: r["median_s"]):
    if r["rms_levels"] < best:
        front.append(r["label"])
        best = r["rms_levels"]
default = next(r for r in result["settings"] if r["knob"] == "default")
print(f"default: {1e3 * default['median_s']:.1f} ms, RMS error {default['rms_levels']:.2f} levels, "
      f"{100 * default['frac_off']:.1f}% of pixels off by ≥ 1 level")
print("on the Pareto front (nothing both faster and more accurate), fastest first:", "; ".join(dict.fromkeys(front)))
'''),
        md("""
        Reading the plot and the table (each point is one knob moved alone from the
        default; lower is more accurate, further left is faster):

        * **depth**: depth 0 (no reflection or refraction at all) is fast and far off —
          everything seen in the two mirrors and the three glass spheres is missing. The
          error falls quickly over the first few segments and then stops changing: depth
          10 (the default) and 12 have the same error on this deck.
        * **spp**: K×K samples per pixel cost about K² times one sample and take most of
          the remaining error away: what the default still gets wrong is mostly aliasing
          at edges.
        * **dtype**: float64 is slower and changes next to nothing in 8-bit levels.
        * **edges** (the silhouette-aware mode) box-filters each pixel's nearest
          silhouette in closed form: at 1 pixel it is antialiasing on the Pareto front,
          between 2×2 and 4×4 supersampling in error, and faster than 4×4;
          narrower (0.5) leaves more aliasing, wider (2) blurs. Its purpose is
          derivatives through edges (`fitting` renders with it); the antialiasing comes
          with it.
        * **scale**: fewer pixels are the fastest renders, but upsampled back to full
          size their error is large: previews.

        Under the table, derivatives are timed against a forward render of the same
        (quarter) size: a reverse-mode gradient of a scalar costs several forward
        renders, a forward-mode Jacobian in the 24 centre coordinates of the order of one
        render per coordinate, one Levenberg–Marquardt step (a Jacobian, a linear solve and the
        solver's bookkeeping) more than that; and the NumPy float64 renderer of the
        tests, run on the same deck, gives the speed-up of the compiled renderer on this
        machine.

        The rows of the table give the figures for this run. Below, the images behind a
        few of the points: the reference, the default, and the default's difference from
        the reference next to those of three cheaper or dearer settings.
        """),
        code('''
scene = rtjax.load_deck(deck_path).frames[0].scene
if CFG.width:
    scene = scene.resized(CFG.width)
ref = next(r for r in result["settings"] if r["knob"] == "reference")
reference = np.asarray(rtjax.render(scene, depth=ref["depth"], spp=ref["spp"], dtype="float64"))


def diff(img, gain=8.0):
    d = np.abs(bench.quantize(img) - bench.quantize(reference)).max(-1)
    return np.clip(255 - gain * d, 0, 255)


settings = {
    "default": rtjax.render(scene),
    "depth 0": rtjax.render(scene, depth=0),
    "2×2 spp": rtjax.render(scene, spp=2),
    "edges 1 px": rtjax.render(scene, edges=1.0),
}
show([reference, settings["default"]], [f"reference (float64, depth {ref['depth']}, {ref['spp']}×{ref['spp']})", "default"],
     height=3.4)
show([diff(v) for v in settings.values()], [f"|{k} − reference| ×8" for k in settings], height=2.4)
'''),
        md("""
        White is agreement, dark is error (×8). The default's errors sit on silhouettes
        and shadow edges (aliasing) and inside mirrors and glass (detail a pixel centre
        samples differently); depth 0 loses everything seen in mirrors and through glass;
        2×2 samples and the silhouette-aware mode both thin out the edge errors.

        ## 2. The numerical extremes

        Each scene below is one of `tests/test_extremes.py`'s, rendered at a small size
        in float32, the opaque ones in the silhouette-aware mode (edges 1 pixel). Under
        each image is a derivative image: dI/dθ for one parameter θ (forward mode,
        `jax.jvp`, summed over the colour channels; red is brighter as θ grows, blue
        darker, each panel on its own scale). The table says whether the image and its
        derivative are finite at every pixel.
        """),
        code('''
LIT = "plig 0.3 -1 0.5 200 180 160\\nelig 0.2\\nback 10 20 30\\n"
CAM = "eyep 0 -50 0\\nrefp 0 0 0\\nvang 40 30\\n"


def deck(body, camera=CAM):
    return rtjax.parse_deck(body + camera + f"size {EXTREME_WIDTH}\\nrend x.ras\\n").frames[0].scene


def tangent_radius(scene):
    """The radius that makes the sphere's silhouette pass exactly through a pixel's ray."""
    st, p = scene.structure, scene.params
    _, d = rtjax.camera.primary_rays(p.eye, p.refp, p.vang, st.width, st.height, jnp.array([0.5, 0.5]))
    d = np.asarray(d)[:, (st.height // 2) * st.width + st.width // 2 + st.width // 4]
    return np.linalg.norm(np.cross(-np.asarray(p.eye), d)) / np.linalg.norm(d)


one = deck("sphe 0 0 0 5\\nopaq 1 0.5 0.2 0.3 10\\n" + LIT)
# behind the glass: a big blue ball and a red one
BEHIND = "sphe 0 60 0 50\\nopaq 0.3 0.6 1 0.6 4\\nsphe -40 0 0 10\\nopaq 1 0 0 0.3 5\\n"
EXTREMES = [  # (name, scene, depth, parameter θ: (family, index)); all silhouette-aware, edges 1 pixel
    ("tangent ray\\n(silhouette on a pixel centre)", one.replace(radii=[tangent_radius(one)]), 0, ("radii", (0,))),
    ("Phong exponent\\nβ = 10 000", deck("sphe 0 0 0 10\\nopaq 1 1 1 1 10000\\n" + LIT), 0, ("beta", (0,))),
    ("light grazing the surface\\n(N·L = 0 on the terminator)", deck("sphe 0 0 0 10\\nopaq 1 1 1 0.5 3\\nplig 1 0 0 255 255 255\\n"),
     0, ("light_dirs", (0, 1))),
    ("radius 10⁻³,\\nseen from 5·10⁻³", deck("sphe 0 0 0 1e-3\\nopaq 1 0.5 0 0.4 10\\n" + LIT, "eyep 0 -5e-3 0\\nrefp 0 0 0\\nvang 40 30\\n"),
     0, ("centers", (0, 0))),
    ("radius 10⁵,\\nseen from 3·10⁵", deck("sphe 0 0 0 1e5\\nopaq 1 0.5 0 0.4 10\\n" + LIT, "eyep 0 -3e5 0\\nrefp 0 0 0\\nvang 40 30\\n"),
     0, ("centers", (0, 0))),
    ("eye inside\\nan opaque sphere", deck("sphe 0 -50 0 5\\nopaq 1 0.5 0.2 0.5 5\\n" + LIT), 0, ("ke", ())),
    # the eye 13.6 units off the centre of a glass sphere of radius 20 and n 1.5: rays leave it at
    # up to asin(13.6/20) = 42.8°, past the critical angle asin(1/1.5) = 41.8° within the image
    ("eye in glass, off centre:\\ntotal internal reflection", deck("sphe 13.6 -50 0 20\\ntrpa 0.9 1.5 0.2 10\\n" + BEHIND + LIT),
     3, ("ior", (0,))),
    ("eye inside a small\\nglass sphere (n 1.4)", deck("sphe 0 -50 0 5\\ntrpa 0.8 1.4 0.3 5\\nsphe 0 0 0 10\\nopaq 1 1 0 0 1\\n"
                                                 "sphe 0 60 0 50\\nopaq 0.3 0.6 1 0.6 4\\n" + LIT), 3, ("centers", (1, 0))),
]
'''),
        code('''
@functools.partial(jax.jit, static_argnames=("structure", "depth", "edges"))
def image_and_derivative(params, tangent, structure, depth, edges):
    """The image and dI/dθ along `tangent` (forward mode): one compilation per structure
    (the six opaque scenes share one, the two glass scenes another)."""
    def f(p):
        return rtjax.render(rtjax.Scene(structure, p), depth=depth, edges=edges)

    return jax.jvp(f, (params,), (tangent,))


def unit_tangent(scene, family, index):
    zero = jax.tree_util.tree_map(jnp.zeros_like, scene.params)
    leaf = np.zeros(np.shape(getattr(zero, family)), np.float32)
    leaf[index] = 1.0
    return rtjax.Scene(scene.structure, zero).replace(**{family: leaf}).params


rows, panels = [], []
for name, s, depth, (family, index) in EXTREMES:
    image, d_image = image_and_derivative(s.params, unit_tangent(s, family, index), s.structure, depth, 1.0)
    ok = (bool(jnp.all(jnp.isfinite(image))), bool(jnp.all(jnp.isfinite(d_image))))
    rows.append((name.replace("\\n", " "), f"{family}{list(index) if index else ''}", *ok, float(jnp.abs(d_image).max())))
    panels.append((name, np.asarray(image), np.asarray(d_image).sum(-1), f"dI/d {family}{list(index) if index else ''}"))

print(f"{'extreme':57s} {'θ':16s} image   dI/dθ   max |dI/dθ|")
for name, theta, a, b, m in rows:
    print(f"{name:57s} {theta:16s} {'finite' if a else 'NOT':7s} {'finite' if b else 'NOT':7s} {m:.3g}")
print(f"\\nall images and derivative images finite: {all(r[2] and r[3] for r in rows)}")
'''),
        code('''
COLS = 4
fig, axes = plt.subplots(2 * ((len(panels) + COLS - 1) // COLS), COLS, figsize=(11, 8.6), squeeze=False)
for k, (name, image, grad_map, label) in enumerate(panels):
    top, col = 2 * (k // COLS), k % COLS
    axes[top, col].imshow(rtjax.to_uint8(image), interpolation="nearest")
    axes[top, col].set_title(name, fontsize=8)
    v = float(np.abs(grad_map).max()) or 1.0
    axes[top + 1, col].imshow(grad_map, cmap="RdBu_r", vmin=-v, vmax=v, interpolation="nearest")
    axes[top + 1, col].set_title(f"{label} (±{v:.3g})", fontsize=8)
for ax in axes.ravel():
    ax.set_xticks([]), ax.set_yticks([])
fig.tight_layout(pad=0.4)
plt.show()
'''),
        md("""
        What the derivative images show (row by row, left to right):

        * **tangent ray**: growing the radius moves the outline outward over the dark
          background: a ring at the silhouette, strongest where the lit side meets the
          background, finite although one pixel's ray grazes the sphere exactly;
        * **β = 10 000**: the highlight is far narrower than a pixel, and dI/dβ is zero
          but for the one pixel that catches a trace of it, where it is tiny (the
          table's maximum): finite where cos γ ≤ 0 and where cos γ^β underflows;
        * **light grazing the surface**: tilting the light away from the eye (its y
          direction) darkens the lit side; finite on the terminator, where N·L = 0 (and
          zero where the image is clamped at 255);
        * **radius 10⁻³ and 10⁵**: the same picture at scales eight orders of magnitude
          apart (the tolerances are relative to the scene's size): moving the sphere to
          the right brightens its right edge, darkens its left, and moves its highlight;
          the derivatives are per unit length, hence their very different scales;
        * **eye inside an opaque sphere**: only the ambient term reaches the eye, so the
          image and dI/d ke are one flat colour;
        * **eye in glass, off centre**: rays leave the glass at up to 42.8° from the
          normal, past the critical angle of 41.8°. In the middle band they are totally
          reflected, at the same angle at every bounce, never get out, and end black after
          the depth's segments; at the sides they leave, strongly bent, and show the blue
          ball. Raising n moves the critical angle, and near it the refracted rays turn
          very fast: the blue ball's outline next to the band moves quickly — a large
          derivative, but finite, right at the onset of total internal reflection;
        * **eye inside a small glass sphere**: moving the yellow ball sideways moves its
          outline, seen through the glass, over the blue ball behind it (which adds up to
          more levels than the yellow ball here, hence the signs).

        `tests/test_extremes.py` checks these extremes and more, on 8-pixel-wide images, in
        float32 and float64, forward and reverse mode, with random directions that reach
        every entry of the Jacobian.
        """),
    ]


# --------------------------------------------------------------------------------------

BUILDERS = {"01_render.ipynb": nb_render, "02_fit.ipynb": nb_fit, "03_tradeoff.ipynb": nb_tradeoff}


def build(name: str) -> nbformat.NotebookNode:
    """The notebook `name` without outputs (deterministic cell ids, so diffs stay small)."""
    nb = new_notebook(cells=BUILDERS[name](), metadata={
        "kernelspec": {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"},
        "language_info": {"name": "python"},
    })
    stem = name.split("_")[0]
    for i, cell in enumerate(nb.cells):
        cell["id"] = f"nb{stem}-{i:02d}"
    nbformat.validate(nb)
    return nb


#: Quick mode's compile-time savers, for the kernel's environment (the notebooks' results
#: do not depend on them): XLA's cheaper backend optimisation (about half the compile
#: time, slower runs: right for small images), and JAX's persistent compilation cache
#: (fits with the same free parameters, loss and constants compile once; a folder shared
#: by the notebooks of one run when JAX_COMPILATION_CACHE_DIR is set, else a new one).
QUICK_COMPILES = {"XLA_FLAGS": "--xla_backend_optimization_level=0"}


def execute(nb: nbformat.NotebookNode, *, quick: bool, timeout: int = 900, cwd: str = NOTEBOOKS, record_timing: bool = False) -> float:
    """Run `nb` in place from a fresh `python3` kernel (cwd: the notebooks folder);
    returns seconds. Quick mode sets RTJAX_NOTEBOOK_QUICK=1 for the kernel."""
    from nbclient import NotebookClient

    env = {QUICK_ENV: "1" if quick else None}
    if quick:
        env.update(QUICK_COMPILES)
        env["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + env["XLA_FLAGS"]).strip()
        if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
            env["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="rtjax_nb_jax_cache_")
    saved = {k: os.environ.get(k) for k in env}
    for k, v in env.items():  # the kernel inherits this process's environment
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    try:
        t0 = time.perf_counter()
        NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": cwd}},
                       record_timing=record_timing).execute()
        return time.perf_counter() - t0
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def update_markdown(name: str) -> None:
    """Text-only edits: the committed notebook's code cells and outputs stay as they are
    (its code must equal the generator's), its markdown cells become the generator's."""
    path = os.path.join(NOTEBOOKS, name)
    committed, built = nbformat.read(path, as_version=4), build(name)
    kinds = [c.cell_type for c in committed.cells]
    if kinds != [c.cell_type for c in built.cells] or any(
            a.source != b.source for a, b in zip(committed.cells, built.cells) if a.cell_type == "code"):
        raise SystemExit(f"{name}: code cells changed; run it again instead of --markdown-only")
    for a, b in zip(committed.cells, built.cells):
        if a.cell_type == "markdown":
            a.source = b.source
    nbformat.write(committed, path)
    print(f"rewrote the text cells of notebooks/{name}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="notebooks to make (prefixes such as 01; default: all)")
    ap.add_argument("--quick", action="store_true", help="execute in reduced mode and save nothing")
    ap.add_argument("--no-execute", action="store_true", help="write the cells without running them")
    ap.add_argument("--out", help="save the executed notebooks in this folder instead (quick mode too)")
    ap.add_argument("--committed", action="store_true",
                    help="execute notebooks/NAME as committed (outputs cleared) instead of the cells below")
    ap.add_argument("--timeout", type=int, default=900, help="seconds per cell (default 900)")
    ap.add_argument("--markdown-only", action="store_true",
                    help="rewrite only the text cells of notebooks/NAME, keeping its outputs (its code cells must be unchanged)")
    args = ap.parse_args(argv)
    names = [n for n in BUILDERS if not args.names or any(n.startswith(p) for p in args.names)]
    os.makedirs(NOTEBOOKS, exist_ok=True)
    for name in names:
        if args.markdown_only:
            update_markdown(name)
            continue
        nb = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4) if args.committed else build(name)
        if args.committed:
            for cell in nb.cells:
                if cell.cell_type == "code":
                    cell.outputs, cell.execution_count = [], None
        if not args.no_execute:
            seconds = execute(nb, quick=args.quick, timeout=args.timeout, record_timing=bool(args.out))
            print(f"{name}: ran in {seconds:.1f} s ({'quick' if args.quick else 'full'} mode)", flush=True)
        if args.out:
            os.makedirs(args.out, exist_ok=True)
            nbformat.write(nb, os.path.join(args.out, name))
            print(f"wrote {os.path.join(args.out, name)}", flush=True)
        elif not args.quick:
            nbformat.write(nb, os.path.join(NOTEBOOKS, name))
            print(f"wrote notebooks/{name}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
