# %% [markdown]
# # rtjax, forward: decks, levels, re-rendering, Sun rasters, textures
#
# This notebook loads a scene deck, renders one deck per level of the assignment
# (opaque spheres, mirrors, glass, textures), changes parameters and re-renders
# without compiling again, writes and reads a Sun raster file, and plays with a
# texture. Everything below was produced by running the notebook top to bottom; the
# numbers quoted in the text are printed by the cells above them.

# %%
import pathlib, shutil, struct, tempfile, time

import jax
import numpy as np

import rtjax

rtjax.tune_cpu()  # before the first JAX computation: XLA's faster CPU code (docs/DEVICES.md)
from nbsetup import QUICK, SCENES, show

WIDTH = 96 if QUICK else None  # None: every deck at its own size
print(f"rtjax {rtjax.__version__}, jax {jax.__version__} on {jax.default_backend()}; quick mode: {QUICK}")


# %%
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


# %% [markdown]
# ## A deck
#
# A deck is a small text file of commands (`sphe`, `opaq`, `mirr`, `trpa`, `tmap`,
# `plig`, `back`, `elig`, `eyep`, `refp`, `vang`, `size`, `rend`; see
# `docs/DECK.md`). `rtjax.load_deck` parses it into one frame per `rend` line; a
# frame's scene is a pytree of a static `Structure` (what the compiled renderer
# depends on: material kinds, counts, image size) and array `Params` (everything
# differentiable, in the deck's units). Here is the assignment's sample deck.

# %%
print((SCENES / "ex2s3.dat").read_text())
deck = rtjax.load_deck(SCENES / "ex2s3.dat")
scene = sized(deck.frames[0].scene)
st = scene.structure
print(f"{len(deck.frames)} frame(s); structure: {st.n_spheres} spheres {st.kinds}, {st.n_lights} light(s), "
      f"{st.width}×{st.height} pixels, default depth {st.default_depth}")
print("sphere centres (deck units):\n", np.asarray(scene.params.centers))

# %% [markdown]
# `rtjax.render` returns a float image (height × width × 3, levels 0..255, clamped
# but not rounded). The first call compiles the renderer for this structure; later
# calls reuse it. The timing line below shows the difference.

# %%
image, first_ex2s3 = timed_render(scene)
_, second = timed_render(scene)
print(f"{image.shape} {image.dtype}; first render (compile + run) {first_ex2s3:.2f} s, second {1e3 * second:.0f} ms")
show([image], [f"ex2s3.dat, {st.width}×{st.height}"], height=4.0)

# %% [markdown]
# ## One deck per level
#
# `scenes/` holds one deck per level of the assignment: level 1 opaque Phong spheres
# with shadows, level 2 mirrors, level 3 refracting glass, level 4 texture-mapped
# spheres. Each has its own structure, so each compiles once. Opaque-only scenes
# need no secondary rays (depth 0); with mirrors or glass the default depth is 10.

# %%
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

# %% [markdown]
# Each deck's comments say what to look for. Level 1: the four balls' highlights
# grow smaller and sharper from left to right as the Phong exponent β grows (2, 10,
# 50, 400), and every ball casts a shadow. Level 2: the two large mirrors reflect
# the red and yellow balls between them back and forth, a smaller copy in each
# bounce. Level 3: the middle row's glass spheres go from n = 1 (no bending) to
# 2.42 (diamond), and the backdrop balls seen through them turn upside down and
# shrink as n grows; the marble at the front right has a mirror core and shows
# total internal reflection. Level 4: the planet, the checker ball, the bands and a
# tiny 5 × 3 texture are texture-mapped; the glass lens shows the checker ball, and
# the mirror ball at the back reflects the textured spheres.
#
# ## Change a parameter, render again: no recompilation
#
# Only the `Structure` is compiled in. Parameters are arrays: a new ambient
# coefficient, moved spheres, other colours or another light direction reuse the
# compiled renderer. The cell counts XLA compilations while it renders four
# variants of the sample deck.

# %%
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

# %% [markdown]
# What is compiled in is the structure: another image size, depth or number of
# samples is another renderer. The next cell renders the same scene at another
# width and counts the compilations that causes; rendering that size again costs
# none.

# %%
before = len(COMPILES)
small = scene.resized(st.width // 2)
img_small, t_small = timed_render(small)
after_first = len(COMPILES) - before
_, t_again = timed_render(small.replace(ke=0.6))
print(f"width {st.width} → {small.structure.width}: {after_first} compilation(s), {t_small:.2f} s; "
      f"the same size with other parameters: {len(COMPILES) - before - after_first} more, {1e3 * t_again:.0f} ms")

# %% [markdown]
# ## The Sun raster round trip
#
# The assignment writes Sun raster files. `rtjax.save_image` picks the format by
# extension (`.sunimg`, `.ras`, … through rtjax's own codec; PNG, JPEG, EXR, …
# through OpenImageIO), rounding to the nearest level; `rtjax.load_image` reads any
# of them back. The cell writes the render, decodes the 32-byte header, reads the
# file back with rtjax and, independently, with Pillow, and compares both with the
# 8-bit image.

# %%
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
shutil.rmtree(tmp)
print("assignment order read in assignment order is the image:", np.array_equal(literal, want))
show([image, back, swapped], ["render", "written and read back (.sunimg)", "assignment order read as standard"], height=2.6)

# %% [markdown]
# ## A texture
#
# A `tmap` sphere takes its diffuse colour from an equirectangular texture (columns
# are longitude, rows colatitude from the north pole). Textures are Sun raster
# files too, and once loaded their texels are parameters like any other: below the
# planet of level 4 is turned by a quarter of a revolution (texel columns rolled),
# its oceans recoloured, and the scene rendered again without compiling anything.

# %%
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


# %% [markdown]
# ## Derivatives come with it
#
# The renderer is a JAX function of the parameters, so `jax.grad` differentiates any
# scalar of the image: below, the mean level of the sample deck's image against the
# ambient coefficient and against each sphere's radius, all in one reverse pass.
#
# This is the plain render, sampled at pixel centres: piecewise constant across
# silhouettes, so its derivative sees how a sphere's shading changes as the radius
# grows but not its outline moving over what lies behind. The silhouette-aware
# mode (`render(scene, edges=1)`, README) includes that motion; `03_tradeoff.ipynb`
# shows derivative images made with it, and `02_fit.ipynb` fits scenes to images
# with it.

# %%
def mean_level(params):
    return rtjax.render(rtjax.Scene(st, params)).mean()

g = jax.grad(mean_level)(scene.params)
print(f"d(mean level)/d ke = {float(g.ke):.1f} levels per unit")
for i, (kind, dr) in enumerate(zip(st.kinds, np.asarray(g.radii))):
    print(f"  sphere {i} ({kind}): d(mean level)/d radius = {dr:+.3f} levels per unit")
