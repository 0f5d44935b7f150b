# %% [markdown]
# # rtjax: speed against accuracy, and the numerical extremes
#
# Part 1 measures, on the assignment's sample deck, what each knob of the renderer
# costs and buys: the reflection/refraction **depth**, the samples per pixel
# (**spp**), the floating-point **dtype**, the **silhouette-aware** mode (edges)
# and the **resolution**. Each knob is varied alone from the default render
# (float32, depth 10, 1 sample per pixel, pixel centres) and compared with a
# reference (float64, deeper, many samples per pixel); the measurements are
# `rtjax.bench`'s (the same as `rtjax bench scenes/ex2s3.dat`).
#
# Part 2 renders the numerical extremes that `tests/test_extremes.py` checks (a ray
# exactly tangent to a sphere, the onset of total internal reflection, a Phong
# exponent of 10 000, spheres of radius 10⁻³ and 10⁵, the eye inside glass, …)
# and shows each image with a derivative image, all finite.

# %%
import dataclasses, functools, os

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import rtjax
from rtjax import bench

rtjax.tune_cpu()  # before the first JAX computation: XLA's faster CPU code (docs/DEVICES.md)
jax.config.update("jax_enable_x64", True)  # the reference renders in float64 (decks stay float32)
from nbsetup import QUICK, SCENES, show, show_png

if QUICK:  # small images, one timed run each, no derivative timings
    CFG = bench.Config(ref_depth=6, ref_spp=2, depths=(0,), spps=(1, 2), edges=(1.0,), subdivides=(), scales=(0.5, 1.0),
                       repeats=1, derivatives=False, numpy=False, width=64)
else:  # `rtjax bench --quick` (reference 8×8 samples at depth 12, derivatives timed at ¼ size), 5 timed runs each
    CFG = dataclasses.replace(bench.Config.quick(), repeats=5)
EXTREME_WIDTH = 32 if QUICK else 96
print(f"quick mode: {QUICK}; {os.cpu_count()} CPU cores, jax {jax.__version__} on {jax.default_backend()}")


# %% [markdown]
# ## 1. The knobs, measured
#
# The next cell runs the study (it prints one line per setting as it goes, then the
# table). Times are medians of repeated renders after compilation, on this
# machine, whatever else it was running; the error is that of the image as an
# 8-bit file would hold it, against the reference.

# %%
deck_path = os.path.relpath(SCENES / "ex2s3.dat")
result = bench.run(deck_path, CFG, log=print)
result["deck"] = "scenes/ex2s3.dat"
print()
print(bench.table_text(result))

# %%
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

# %% [markdown]
# Reading the plot and the table (each point is one knob moved alone from the
# default; lower is more accurate, further left is faster):
#
# * **depth**: depth 0 (no reflection or refraction at all) is fast and far off —
#   everything seen in the two mirrors and the three glass spheres is missing. The
#   error falls quickly over the first few segments and then stops changing: depth
#   10 (the default) and 12 have the same error on this deck.
# * **spp**: K×K samples per pixel cost about K² times one sample and take most of
#   the remaining error away: what the default still gets wrong is mostly aliasing
#   at edges.
# * **dtype**: float64 is slower and changes next to nothing in 8-bit levels.
# * **edges** (the silhouette-aware mode) box-filters each pixel's nearest
#   silhouette in closed form: at 1 pixel it is antialiasing on the Pareto front,
#   between 2×2 and 4×4 supersampling in error, and faster than 4×4;
#   narrower (0.5) leaves more aliasing, wider (2) blurs. Its purpose is
#   derivatives through edges (`fitting` renders with it); the antialiasing comes
#   with it.
# * **subdivide**: the same mode with the pixels an edge may cross split into 2×2 or
#   4×4 sub-boxes, each with its own nearest edge (`render(..., subdivide=n)`): where a
#   pixel holds several edges, and inside mirrors and glass, one straight edge per
#   pixel is a poor model, and the sub-boxes take the error below 4×4 supersampling's,
#   for less time. They were made for derivatives there (docs/EDGES.md); the
#   antialiasing again comes with them.
# * **scale**: fewer pixels are the fastest renders, but upsampled back to full
#   size their error is large: previews.
#
# Under the table, derivatives are timed against a forward render of the same
# (quarter) size: a reverse-mode gradient of a scalar costs several forward
# renders, a forward-mode Jacobian in the 24 centre coordinates of the order of one
# render per coordinate, one Levenberg–Marquardt step (a Jacobian, a linear solve and the
# solver's bookkeeping) more than that; and the NumPy float64 renderer of the
# tests, run on the same deck, gives the speed-up of the compiled renderer on this
# machine.
#
# The rows of the table give the figures for this run. Below, the images behind a
# few of the points: the reference, the default, and the default's difference from
# the reference next to those of three cheaper or dearer settings.

# %%
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

# %% [markdown]
# White is agreement, dark is error (×8). The default's errors sit on silhouettes
# and shadow edges (aliasing) and inside mirrors and glass (detail a pixel centre
# samples differently); depth 0 loses everything seen in mirrors and through glass;
# 2×2 samples and the silhouette-aware mode both thin out the edge errors.
#
# ## 2. The numerical extremes
#
# Each scene below is one of `tests/test_extremes.py`'s, rendered at a small size
# in float32, the opaque ones in the silhouette-aware mode (edges 1 pixel). Under
# each image is a derivative image: dI/dθ for one parameter θ (forward mode,
# `jax.jvp`, summed over the colour channels; red is brighter as θ grows, blue
# darker, each panel on its own scale). The table says whether the image and its
# derivative are finite at every pixel.

# %%
LIT = "plig 0.3 -1 0.5 200 180 160\nelig 0.2\nback 10 20 30\n"
CAM = "eyep 0 -50 0\nrefp 0 0 0\nvang 40 30\n"


def deck(body, camera=CAM):
    return rtjax.parse_deck(body + camera + f"size {EXTREME_WIDTH}\nrend x.ras\n").frames[0].scene


def tangent_radius(scene):
    """The radius that makes the sphere's silhouette pass exactly through a pixel's ray."""
    st, p = scene.structure, scene.params
    _, d = rtjax.camera.primary_rays(p.eye, p.refp, p.vang, st.width, st.height, jnp.array([0.5, 0.5]))
    d = np.asarray(d)[:, (st.height // 2) * st.width + st.width // 2 + st.width // 4]
    return np.linalg.norm(np.cross(-np.asarray(p.eye), d)) / np.linalg.norm(d)


one = deck("sphe 0 0 0 5\nopaq 1 0.5 0.2 0.3 10\n" + LIT)
# behind the glass: a big blue ball and a red one
BEHIND = "sphe 0 60 0 50\nopaq 0.3 0.6 1 0.6 4\nsphe -40 0 0 10\nopaq 1 0 0 0.3 5\n"
EXTREMES = [  # (name, scene, depth, parameter θ: (family, index)); all silhouette-aware, edges 1 pixel
    ("tangent ray\n(silhouette on a pixel centre)", one.replace(radii=[tangent_radius(one)]), 0, ("radii", (0,))),
    ("Phong exponent\nβ = 10 000", deck("sphe 0 0 0 10\nopaq 1 1 1 1 10000\n" + LIT), 0, ("beta", (0,))),
    ("light grazing the surface\n(N·L = 0 on the terminator)", deck("sphe 0 0 0 10\nopaq 1 1 1 0.5 3\nplig 1 0 0 255 255 255\n"),
     0, ("light_dirs", (0, 1))),
    ("radius 10⁻³,\nseen from 5·10⁻³", deck("sphe 0 0 0 1e-3\nopaq 1 0.5 0 0.4 10\n" + LIT, "eyep 0 -5e-3 0\nrefp 0 0 0\nvang 40 30\n"),
     0, ("centers", (0, 0))),
    ("radius 10⁵,\nseen from 3·10⁵", deck("sphe 0 0 0 1e5\nopaq 1 0.5 0 0.4 10\n" + LIT, "eyep 0 -3e5 0\nrefp 0 0 0\nvang 40 30\n"),
     0, ("centers", (0, 0))),
    ("eye inside\nan opaque sphere", deck("sphe 0 -50 0 5\nopaq 1 0.5 0.2 0.5 5\n" + LIT), 0, ("ke", ())),
    # the eye 13.6 units off the centre of a glass sphere of radius 20 and n 1.5: rays leave it at
    # up to asin(13.6/20) = 42.8°, past the critical angle asin(1/1.5) = 41.8° within the image
    ("eye in glass, off centre:\ntotal internal reflection", deck("sphe 13.6 -50 0 20\ntrpa 0.9 1.5 0.2 10\n" + BEHIND + LIT),
     3, ("ior", (0,))),
    ("eye inside a small\nglass sphere (n 1.4)", deck("sphe 0 -50 0 5\ntrpa 0.8 1.4 0.3 5\nsphe 0 0 0 10\nopaq 1 1 0 0 1\n"
                                                 "sphe 0 60 0 50\nopaq 0.3 0.6 1 0.6 4\n" + LIT), 3, ("centers", (1, 0))),
]


# %%
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
    rows.append((name.replace("\n", " "), f"{family}{list(index) if index else ''}", *ok, float(jnp.abs(d_image).max())))
    panels.append((name, np.asarray(image), np.asarray(d_image).sum(-1), f"dI/d {family}{list(index) if index else ''}"))

print(f"{'extreme':57s} {'θ':16s} image   dI/dθ   max |dI/dθ|")
for name, theta, a, b, m in rows:
    print(f"{name:57s} {theta:16s} {'finite' if a else 'NOT':7s} {'finite' if b else 'NOT':7s} {m:.3g}")
print(f"\nall images and derivative images finite: {all(r[2] and r[3] for r in rows)}")

# %%
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

# %% [markdown]
# What the derivative images show (row by row, left to right):
#
# * **tangent ray**: growing the radius moves the outline outward over the dark
#   background: a ring at the silhouette, strongest where the lit side meets the
#   background, finite although one pixel's ray grazes the sphere exactly;
# * **β = 10 000**: the highlight is far narrower than a pixel, and dI/dβ is zero
#   but for the one pixel that catches a trace of it, where it is tiny (the
#   table's maximum): finite where cos γ ≤ 0 and where cos γ^β underflows;
# * **light grazing the surface**: tilting the light away from the eye (its y
#   direction) darkens the lit side; finite on the terminator, where N·L = 0 (and
#   zero where the image is clamped at 255);
# * **radius 10⁻³ and 10⁵**: the same picture at scales eight orders of magnitude
#   apart (the tolerances are relative to the scene's size): moving the sphere to
#   the right brightens its right edge, darkens its left, and moves its highlight;
#   the derivatives are per unit length, hence their very different scales;
# * **eye inside an opaque sphere**: only the ambient term reaches the eye, so the
#   image and dI/d ke are one flat colour;
# * **eye in glass, off centre**: rays leave the glass at up to 42.8° from the
#   normal, past the critical angle of 41.8°. In the middle band they are totally
#   reflected, at the same angle at every bounce, never get out, and end black after
#   the depth's segments; at the sides they leave, strongly bent, and show the blue
#   ball. Raising n moves the critical angle, and near it the refracted rays turn
#   very fast: the blue ball's outline next to the band moves quickly — a large
#   derivative, but finite, right at the onset of total internal reflection;
# * **eye inside a small glass sphere**: moving the yellow ball sideways moves its
#   outline, seen through the glass, over the blue ball behind it (which adds up to
#   more levels than the yellow ball here, hence the signs).
#
# `tests/test_extremes.py` checks these extremes and more, on 8-pixel-wide images, in
# float32 and float64, forward and reverse mode, with random directions that reach
# every entry of the Jacobian.
