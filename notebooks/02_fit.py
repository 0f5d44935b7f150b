# %% [markdown]
# # rtjax, inverse: fitting a scene to an image
#
# `fitting.fit(scene, target, free=...)` adjusts the chosen parameters of a scene
# until its render matches a target image, with optimistix's Levenberg–Marquardt
# solver on the residuals of the silhouette-aware render, coarse to fine (see the
# README's "Fitting a scene to an image"). This notebook
#
# 1. makes a target from a known truth, moves the spheres, and fits the centres back;
# 2. then fits the colours and the ambient coefficient `ke`;
# 3. makes a photo-like target (blur, camera response, noise, JPEG, and a date
#    stamp burnt into the picture) and shows what nuisance parameters for the
#    camera and the robust Cauchy loss do;
# 4. recovers a texture from several views of a textured ball;
# 5. fits a photograph that another renderer made (`photo=True`) and reads its verdict.
#
# Every number quoted in the text is printed by the cell above it.

# %%
import io, time

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image, ImageDraw, ImageFont

import fitting
import rtjax

rtjax.tune_cpu()  # before the first JAX computation: XLA's faster CPU code (docs/DEVICES.md)
from nbsetup import QUICK, SCENES, show

WIDTH = 64 if QUICK else 240          # image width of truth, target and fits
STEPS = (10, 8, 6) if QUICK else (30, 20, 25)  # iterations: centres, colours and ke, photo-like target
print(f"quick mode: {QUICK}; images {WIDTH} pixels wide; at most {STEPS} iterations")


# %%
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


# %% [markdown]
# ## A known truth
#
# The truth is a small deck: three balls on a floor, a warm key light and a cool
# fill light. The target is its render rounded to 8-bit levels, as a file would
# hold it.

# %%
DECK = """\
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
truth = rtjax.parse_deck(DECK).frames[0].scene.resized(WIDTH)
target = np.floor(np.asarray(rtjax.render(truth)) + 0.5)
print(f"truth: {truth.structure.n_spheres} spheres, {truth.structure.width}×{truth.structure.height}")
show([target], ["target (the truth, rendered)"], height=3.2)

# %% [markdown]
# ## 1. Centres
#
# Each ball's centre is moved by up to ±2.5 units in each direction (a quarter to
# two fifths of a radius); the floor stays. `fitting.fit` with `free="centers"`
# and `spheres=[1, 2, 3]` fits the nine coordinates. Depth along the line of sight
# is seen only through perspective and shadows, so it is the least determined.

# %%
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

# %%
plot_histories([res_c], ["centres (LM, Cauchy loss)"], "fitting the centres: loss per iteration")
img_start = rtjax.render(start)
img_fit = rtjax.render(res_c.scene)
show([img_start, img_fit, target, difference(img_start, target), difference(img_fit, target)],
     ["start", "fitted", "target", "|start − target| ×4", "|fitted − target| ×4"], height=2.3)

# %% [markdown]
# Each pyramid level measures its own image (dotted lines where the width
# changes: quarter size, half size, full size), so the loss jumps where a level
# starts. The full-size level is matched at pixel centres, as the target was
# rendered: an edge pixel counts exactly when its centre lies on the target's side
# of the edge, so the fit is unbiased there; the steep drop at its start is where
# its sharp edges meet the target's. The difference images (white = no difference) show the start's
# misplaced silhouettes and shadows, and what is left after the fit; the table
# gives each ball's remaining error in deck units.
#
# ## 2. Colours and `ke`
#
# Next, starting from the fitted centres, every sphere's colour (the floor's too)
# is set to a neutral grey 0.5 and the ambient coefficient to 0.5; the fit
# recovers 13 numbers: `free="colors,ke"`. Colours and `ke` are bounded to [0, 1]
# by a logistic reparameterisation, so the solver can never leave the valid range.

# %%
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

# %% [markdown]
# Colours enter the image almost linearly: the loss falls steadily on the coarse
# level, and the full-size level brings it to the level of the centres' remaining error
# (the table compares each fitted number with the truth).
#
# ## 3. A photo-like target
#
# A photograph is not a render. The target below is the truth rendered with 4×4
# samples per pixel (antialiased), seen through a camera:
#
# * a **Gaussian blur** of σ = 0.7 pixels (the lens),
# * a **camera response** 255·(1.15·I/255)^0.8 (exposure and gamma),
# * **noise** of σ = 3 levels,
# * **JPEG** compression at quality 75 (Pillow),
# * and a **date stamp** burnt into the lower right corner over the floor, as old
#   cameras did: a few hundred pixels that no scene explains.
#
# The geometry is that of step 1 (the fitted centres); colours and `ke` are fitted
# from grey again, three ways:
#
# 1. `loss="cauchy"` (the default, as in step 2), the scene's parameters only;
# 2. `loss="l2"`, plain least squares, with the nuisance parameters of a camera
#    model fitted jointly (`nuisance=("camera",)`: `gain` and `gamma`, `blur`, a
#    further `chroma` blur for JPEG's subsampled colour, and the `order` of blur
#    and response; `fitting.camera` is the model);
# 3. `loss="cauchy"` with the same nuisance parameters.
#
# The first and the last differ by the nuisance parameters, the last two by the loss.

# %%
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

# %%
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
print(f"\nFIT photo: smallest largest error {errors[best]:.3f} with {best} (truth: ke {float(truth.params.ke):.2f})")

# %%
plot_histories(list(runs.values()), list(runs), "photo-like target: colours and ke, three ways")
labels = list(runs)
show([photo] + [rtjax.render(runs[k].scene) for k in labels], ["photo-like target"] + [f"fitted scene: {k}" for k in labels],
     height=2.4)
model = {k: np.asarray(fitting.camera(rtjax.render(runs[k].scene, spp=4), runs[k].nuisance)) for k in labels}
show([difference(model[k], photo, gain=3) for k in labels], [f"|model − photo| ×3: {k}" for k in labels], height=2.4)

# %% [markdown]
# How to read this (the table above has this run's numbers):
#
# * **Without nuisance parameters** (`cauchy`) nothing in the scene can explain the
#   camera's response: the colours and `ke` take the blame (errors of about a tenth
#   of the colour range), and the fitted scene (first fitted image) is rendered
#   with the photo's exposure and contrast instead of its own; the sky, whose
#   colour is not free, is left over in its `|model − photo|` map.
# * **With the camera model** fitted jointly, the response is absorbed by the
#   numbers it was made with (printed beside each fit), and the scene's
#   own colours and `ke` come out within about 0.02 of the truth. The fitted images
#   are renders of the scene alone, without the camera, and look like the truth.
# * **The loss**: the date stamp is a few hundred pixels of a colour no scene
#   parameter produces. Least squares (`l2 + camera`) lets them pull on whatever
#   can reduce their squared error: the floor's colour, which lies under the
#   stamp, and the camera's gain and gamma come out further from the truth than
#   with the Cauchy loss, which grows only logarithmically for residuals much
#   larger than its scale (10 levels), so the stamp barely pulls. The balls'
#   colours, away from the stamp, are about equally good either way.
# * The losses of the three fits are different functions (and each level of the
#   pyramid measures a different image), so the convergence plot shows how each fit
#   progresses, not which is better. The `|model − photo|` maps show each fitted
#   scene through its fitted camera against the photo: what remains is the stamp,
#   edges softened by JPEG, and noise, which no fit removes.
#
# This is why the Cauchy loss is the default of `fitting.fit` and `rtjax fit`.

# %% [markdown]
# ## 4. Texture recovery from several views
#
# `--free textures` makes every texel a free parameter: thousands of numbers, so each
# step is solved matrix-free (J·v and Jᵀ·w by JAX, LSMR; `fitting.matrixfree`) on one
# full-size level of plain renders (`fitting.texels`). The deck
# `scenes/fit/texture_ball.dat` shows a checker ball from four sides; its texture
# starts flat grey, and the targets are its four frames rendered exactly. A texel is
# *seen* when its summed weight in the views' pixels is at least one fully lit
# pixel's worth; texels no view sees (the poles here) keep their start value.

# %%
ball = rtjax.load_deck(SCENES / "fit" / "texture_ball.dat")
TEX_WIDTH = 48 if QUICK else 160
truths = [f.scene.resized(TEX_WIDTH) for f in ball.frames]
true_texture = np.asarray(truths[0].params.textures[0])
tex_targets = [np.floor(np.asarray(rtjax.render(t)) + 0.5) for t in truths]
tex_starts = [t.replace(textures=(np.full(true_texture.shape, 128.0),)) for t in truths]
t0 = time.perf_counter()
tex_one = fitting.fit(tex_starts[0], tex_targets[0], "textures", max_steps=STEPS[2])
tex_all = fitting.fit(tex_starts, tex_targets, "textures", max_steps=STEPS[2])
print(f"two fits in {time.perf_counter() - t0:.0f} s")
for name, res in (("frame 0 alone", tex_one), ("all four frames", tex_all)):
    fitted = np.asarray(res.scene.params.textures[0])
    seen = res.texels.seen(0)
    err = np.abs(fitted - true_texture)[seen]
    print(f"{name}: {res.texels.lines()[0]}; RMS error over the seen texels {np.sqrt(np.mean(err ** 2)):.2f} levels "
          f"({res.steps} iterations)")

# %%
show([tex_starts[0].params.textures[0], true_texture, tex_one.scene.params.textures[0], tex_all.scene.params.textures[0]],
     ["start (grey)", "truth", "recovered, frame 0 alone", "recovered, four frames"], height=2.2)
show(tex_targets, [f"target, frame {k}" for k in range(4)], height=2.2)
errors = [difference(r.scene.params.textures[0], true_texture, gain=4) for r in (tex_one, tex_all)]
show(errors + [255 * (1 - tex_all.texels.seen(0))], ["|texel error| ×4, frame 0 alone", "|texel error| ×4, four frames",
                                                    "not seen (black), four frames"], height=2.2)

# %% [markdown]
# One view determines about a quarter of the texture (the half facing the camera,
# less the rim, where texels are seen at a grazing angle and share pixels); the four
# frames see about seven tenths, all but the rows near the poles, which no frame
# shows (black in the last map, and grey in the recovered texture: left as they
# started, not invented). Over the texels that are seen, the error is below a level
# but at the checker's sharp steps, where a texel next to a weakly seen one is off by
# a few levels.

# %% [markdown]
# ## 5. A photograph rtjax did not render: `photo=True`
#
# `scenes/photos/` holds photos of deck scenes made by other renderers (POV-Ray,
# Blender's Cycles, Mitsuba 3: sun shadows, sky light, Fresnel glass, plastic highlights) and
# passed through a camera (exposure, white balance, lens blur, vignetting, noise, a
# tone curve, JPEG), with each photo's truth deck and a start deck whose centres are
# moved by 5–15 % of their radii. No shading of the model matches theirs, so
# `fitting.fit(..., photo=True)` (`rtjax fit --photo`) fits appearance (colours, ambient,
# background, lights, a smooth illumination field) and a camera (gain, tone curve, blur,
# JPEG's chroma blur) with the centres, each in a plausible range, and ends with a
# verdict (`fitting.verdict`): a parameter at a bound, a residual no better than a
# flat image or the start geometry, or a centre its own uncertainty does not pin,
# makes it a failure. Errors are in pixel footprints at each sphere's distance (the
# goal: opaque and mirror spheres within 1, glass within 3). The quick mode fits a
# quarter-size copy of the photo with a few iterations.

# %%
import json

from fitting.objective import downsample
from fitting.photo import Photo
from fitting.verdict import footprints

PHOTOS = SCENES / "photos"
PHOTO = next(p for p in json.loads((PHOTOS / "manifest.json").read_text())["photos"] if p["name"] == "two_lights-cycles-1")
assert PHOTO["split"] == "tune"
photo_start = rtjax.load_deck(PHOTOS / PHOTO["start"]).frames[0].scene
photo_truth = rtjax.load_deck(PHOTOS / PHOTO["truth"]).frames[0].scene
photo_target = fitting.load_target(str(PHOTOS / PHOTO["file"]))
if QUICK:  # quarter size: the scene follows the target's width
    w = photo_target.shape[1] // 4
    photo_target = downsample(photo_target, rtjax.image_height(w, *map(float, np.asarray(photo_start.params.vang))), w)
t0 = time.perf_counter()
photo_fit = fitting.fit(photo_start, photo_target, "centers", spheres=PHOTO["free"], photo=True,
                        max_steps=4 if QUICK else 30)
print(f"{photo_fit.steps} iterations, {time.perf_counter() - t0:.1f} s, {photo_fit.result}; exit {0 if photo_fit.ok else 1}")
print("verdict:", photo_fit.verdict.message)

width = photo_target.shape[1]
foot = footprints(photo_truth.params, PHOTO["width"])  # pixel footprints at the photo's own width
true_c = np.asarray(photo_truth.params.centers)
print(f"\n{'sphere':>6s} {'kind':>5s} {'start err':>9s} {'end err':>8s} {'σ':>7s} {'bias':>7s}   (pixel footprints)")
for s in photo_fit.verdict.spheres:
    i = s["index"]
    e0 = np.linalg.norm(np.asarray(photo_start.params.centers)[i] - true_c[i]) / foot[i]
    e1 = np.linalg.norm(np.asarray(photo_fit.scene.params.centers)[i] - true_c[i]) / foot[i]
    scale = PHOTO["width"] / width  # the verdict's pixels are the fitted image's
    print(f"{i:6d} {s['kind']:>5s} {e0:9.2f} {e1:8.2f} {s['sigma_px'] * scale:7.3f} {s['bias_px'] * scale:7.3f}")

# %%
# the photo model of the start at the target's size (as the fit made it), applied to the fitted scene
photo_model = np.asarray(Photo(photo_start.resized(width, photo_target.shape[0])).image(photo_fit.scene, photo_fit.y["photo"]))
show([photo_target, photo_model, difference(photo_model, photo_target, gain=3)],
     ["photo (Cycles)", "fitted scene through the fitted camera", "|model − photo| ×3"], height=2.6)

# %% [markdown]
# The residual map shows what appearance cannot absorb: the other renderer's
# highlights, inter-reflections and soft shadow edges. The centres are carried by
# silhouettes and shadow outlines; depth (along the view) is the least determined
# direction, seen only through each silhouette's size and perspective. The σ column
# is the verdict's cluster-robust (sandwich) uncertainty over 16-pixel blocks, which
# allows for residuals correlated within a block (blur, JPEG); the bias column
# estimates what shading the model lacks does to a centre (the shift of the optimum
# when only the edge pixels keep their weight). The verdict takes 3·√(σ² + bias²)
# against each sphere's goal: it errs on the side of failing, and may call a fit
# undetermined whose centres are in fact within their goals. The README has the
# whole photo set's table (`scripts/eval_photos.py`), docs/FITTING.md its reading.
