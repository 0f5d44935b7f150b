"""A photo's model: what `fit(..., photo=True)` fits besides the geometry.

A photograph is never the model's own render: its shading (measured materials,
Fresnel, indirect light, soft shadows), its camera (exposure, white balance, lens blur,
vignetting, a tone curve, JPEG) and its colours all differ.

The model renders in linear light, as the photo's renderer did: the deck's colours
(diffuse, lights, background, texels) are display values, decoded by a power
`DISPLAY_GAMMA` before the render, so that lights add, glass and its shadow pass kt per
interface, and the ambient term mixes with the rest as they do in the photo. The
geometry is carried by silhouettes, occlusion boundaries and shadow edges; everything
else is absorbed by appearance parameters fitted jointly with it:

- in the scene (`Photo.scene`): the diffuse colour of every opaque sphere but the one
  that looks largest (`Photo.anchor`, a floor say: the camera's gain sets its colour,
  so that gain and colours do not trade), per channel in [0, 1] ('albedo'); the
  background colour ('background'); a factor per channel on every light after the
  first ('lights'); the ambient coefficient ('ke'); each glass sphere's transmission
  ('kt'); the colour glass reflects by Fresnel's law ('fresnel', `rtjax.Params.fresnel`:
  a photo's glass balls mirror their surroundings, most of all at their rims, which the
  deck's glass does not, and a model without it reads the rims as depth); how dark the
  contact shadows are ('occlusion': the weight of every
  sphere but a floor in the sky occlusion of the ambient term, `rtjax.occlusion`, times
  1 − kt² for glass, which passes that much as it does a light's shadow ray; a
  photo's sky light does not reach under and between its balls, and a model without
  that reads those shadows as depth); and an offset of every silhouette, in pixels ('dilate': every
  sphere's radius but a floor's grows by that many pixel footprints at its distance):
  a tone curve, a blur taken in another colour space or darkened limbs move a
  photo's outlines by a fraction of a pixel, which the model would otherwise read as
  depth. Colours are display values, as a deck gives them, per channel in [0, 1] of
  the deck's range;
- in the camera (`Photo.camera`): the render times a smooth illumination field (a
  low-order polynomial in the image's coordinates, of log-gain: vignetting, sky light;
  'field'), a Gaussian lens blur ('blur'), the tone curve to display values
  with a free exponent ('gamma'), a gain per channel on the display values ('gain':
  exposure and white balance; an exposure g before the curve is g^(γ/2.2) after it,
  the same model, but there gain and γ do not trade), and JPEG's chroma blur
  ('chroma').

Every parameter lives in a plausible range (`RANGES`) through a logistic, so no solver
step leaves it; a parameter that ends at an end of its range that is not a natural
limit (`Range.flags`) makes the fit's verdict a failure (`fitting.verdict`).
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import rtjax

from .objective import WHOLE_IMAGE_RENDER, chroma_blur, gaussian_blur

#: The exponent that decodes the deck's colours to linear light (the photo's renderer lit
#: them as sRGB values), and encodes the render back.
DISPLAY_GAMMA = 2.2
#: A sphere larger than this many times the median radius is a floor (or a wall): its
#: silhouette is the horizon, which `dilate` leaves alone.
FLOOR_RATIO = 10.0


@dataclasses.dataclass(frozen=True)
class Range:
    """A parameter kept in [lo, hi] by a logistic of the solver's coordinate, on its own
    scale or (`log`) on its logarithm's; `flags`: which ends are artificial (lo, hi),
    so that ending there means the parameter ran away."""

    lo: float
    hi: float
    log: bool = False
    flags: tuple[bool, bool] = (True, True)

    def _ends(self):
        return (np.log(self.lo), np.log(self.hi)) if self.log else (self.lo, self.hi)

    def value(self, u):
        """The parameter from the solver's coordinate u (traceable)."""
        a, b = self._ends()
        x = a + (b - a) * jax.nn.sigmoid(u)
        return jnp.exp(x) if self.log else x

    def free(self, x) -> np.ndarray:
        """The solver's coordinate of value x (NumPy), a value outside just inside."""
        a, b = self._ends()
        x = np.log(np.asarray(x, np.float64)) if self.log else np.asarray(x, np.float64)
        z = np.clip((x - a) / (b - a), 1e-3, 1 - 1e-3)
        return np.log(z) - np.log1p(-z)

    def share(self, u) -> np.ndarray:
        """Where u lies within the range, 0..1 (NumPy)."""
        return 1 / (1 + np.exp(-np.asarray(u, np.float64)))


#: Each parameter's plausible range. Colours (albedo, background, fresnel) are the
#: scene's own, display values as a deck gives them (decoded for the render), on their
#: whole range (a diffuse 0..1, a colour 0..255 as a share of 255), whose ends are
#: natural (a black or white channel); factors (lights, gain) are relative to the
#: deck's values; the field's coefficients are log-gains at the image's
#: edges; blur and chroma are Gaussian σ in pixels (0.1, a sharp image, is a natural
#: limit); ke and kt are the deck's own [0, 1]; dilate is in pixels; occlusion is an
#: occluder's weight, from none (0) to one that sends back no light (1).
RANGES = {
    "albedo": Range(0.0, 1.0, flags=(False, False)),
    "background": Range(0.0, 1.0, flags=(False, False)),
    "lights": Range(0.25, 4.0, log=True),
    "ke": Range(0.0, 1.0, flags=(False, True)),
    "kt": Range(0.0, 1.0, flags=(False, False)),
    "dilate": Range(-1.5, 1.5),
    "occlusion": Range(0.0, 1.0, flags=(False, False)),
    "fresnel": Range(0.0, 1.0, flags=(False, False)),
    "gain": Range(0.25, 4.0, log=True),
    "field": Range(-1.0, 1.0),
    "blur": Range(0.1, 3.0, flags=(False, True)),
    "gamma": Range(0.3, 3.0, log=True),
    "chroma": Range(0.1, 3.0, flags=(False, True)),
}
#: The parameters that act on the rendered image (the rest change the scene).
CAMERA = ("gain", "field", "blur", "gamma", "chroma")
#: Start values of the camera's parameters: no change but a slight blur (a lens, a
#: renderer's pixel filter) and JPEG's usual chroma blur.
CAMERA_START = {"blur": 0.7, "gamma": 1.0, "chroma": 0.5}
#: Colours (albedo, background), ke and kt start at the deck's (glass's fresnel colour at
#: the background's), at least this far inside their [0, 1] range: at an end the
#: logistic's slope would hold them there.
START_MARGIN = 0.02
#: The occluders' weight at the start: halfway, as likely to send back light as not.
OCCLUSION_START = 0.5
#: The smooth illumination field's terms, in the image's coordinates u, v ∈ [−1, 1].
FIELD_TERMS = 5


def decode(x):
    """Display values 0..1 to linear light (works on NumPy and JAX arrays)."""
    return x ** DISPLAY_GAMMA


def field_basis(u, v):
    """The field's terms (…, FIELD_TERMS) at image coordinates u, v (−1..1, across and down)."""
    return jnp.stack([u, v, u * u, u * v, v * v], -1)


class Photo:
    """The appearance and camera parameters of a photo of `scene` (full size): which
    spheres and lights they touch, their start in the solver's coordinates (`y0`), and
    the maps from those coordinates to a scene (`scene`) and to a photo of its render
    (`camera`, `camera_at`)."""

    #: the parameters that act on the rendered image (`Objective.stages`)
    camera_keys = CAMERA

    def __init__(self, scene: rtjax.Scene):
        s, p = scene.structure, scene.params
        self.structure = s
        radii = np.asarray(p.radii, np.float64)
        eye = np.asarray(p.eye, np.float64)
        distance = np.linalg.norm(np.asarray(p.centers, np.float64) - eye, axis=1)
        angle = 2 * np.tan(np.radians(float(np.asarray(p.vang)[0])) / 2) / s.width
        #: each sphere's pixel footprint at its start distance (scene units per pixel)
        self.footprint = distance * angle
        opaque = np.flatnonzero(s.mask("opaq"))
        #: the opaque sphere that looks largest keeps its colour (the gain sets it)
        self.anchor = int(opaque[np.argmax(radii[opaque] / np.maximum(distance[opaque] - radii[opaque], 1e-9))]) \
            if len(opaque) else -1
        self.opaque = opaque[opaque != self.anchor]
        self.glass = np.flatnonzero(s.mask("trpa"))
        self.rounded = np.flatnonzero(radii <= FLOOR_RATIO * np.median(radii)) if len(radii) else np.zeros(0, int)
        background = np.clip(np.asarray(p.background, np.float64) / 255, START_MARGIN, 1 - START_MARGIN)
        start = {
            "albedo": np.clip(np.asarray(p.diffuse, np.float64)[self.opaque].reshape(-1, 3), START_MARGIN, 1 - START_MARGIN),
            "background": background,
            "lights": np.ones((max(s.n_lights - 1, 0), 3)),
            "ke": np.clip(float(p.ke), START_MARGIN, 0.9),
            "kt": np.clip(np.asarray(p.kt, np.float64)[self.glass], START_MARGIN, 1 - START_MARGIN),
            "dilate": 0.0,
            "occlusion": OCCLUSION_START,
            "fresnel": background if len(self.glass) else np.zeros(0),
            "gain": np.ones(3),
            "field": np.zeros(FIELD_TERMS),
            **CAMERA_START,
        }
        self.start = {k: v for k, v in start.items() if np.size(v) or k in ("ke", "dilate")}

    def at(self, footprint) -> "Photo":
        """This photo model with other footprints (`Objective.at`'s part)."""
        out = copy.copy(self)
        out.footprint = footprint
        return out

    def label(self, name: str, n: int, size: int) -> str:
        """A name for entry n (of `size`) of parameter `name`: which sphere, light or
        channel it is."""
        if size == 1:
            return name
        channel = ("red", "green", "blue")
        if name == "albedo":
            return f"colour of sphere {int(self.opaque[n // 3])} ({channel[n % 3]})"
        if name == "lights":
            return f"light {n // 3 + 1} ({channel[n % 3]})"
        if name == "kt":
            return f"kt of sphere {int(self.glass[n])}"
        if name in ("gain", "background", "fresnel"):
            return f"{name} ({channel[n]})"
        return f"{name}[{n}]"

    def y0(self, dtype) -> dict:
        """The start in the solver's coordinates."""
        return {k: jnp.asarray(RANGES[k].free(v), dtype) for k, v in self.start.items()}

    def values(self, y: dict) -> dict:
        """The parameters in their own units (traceable)."""
        return {k: RANGES[k].value(u) for k, u in y.items()}

    def scene(self, params: rtjax.Params, y: dict) -> rtjax.Params:
        """`params` with the scene's appearance parameters applied (differentiable)."""
        v = self.values(y)
        dtype = params.diffuse.dtype
        diffuse = params.diffuse.at[self.opaque].set(v["albedo"].astype(dtype)) if len(self.opaque) else params.diffuse
        new = {
            "diffuse": decode(diffuse),
            "light_colors": 255 * decode(params.light_colors / 255),
            "textures": tuple(255 * decode(t / 255) for t in params.textures),
            "background": 255 * decode(v["background"].astype(dtype)),
            "ke": v["ke"].astype(dtype),
            "radii": params.radii.at[self.rounded].add((v["dilate"] * self.footprint[self.rounded]).astype(dtype)),
        }
        if "lights" in v:
            new["light_colors"] = new["light_colors"].at[1:].multiply(v["lights"].astype(dtype))
        if "fresnel" in v:
            new["fresnel"] = 255 * decode(v["fresnel"].astype(dtype))
        if "kt" in v:
            new["kt"] = params.kt.at[self.glass].set(v["kt"].astype(dtype))
        # glass hides the sky as it shadows the lights: all but kt² of it
        passes = jnp.where(jnp.asarray(self.structure.mask("trpa")), new.get("kt", params.kt) ** 2, 0)
        new["occlusion"] = jnp.zeros_like(params.radii).at[self.rounded].set(v["occlusion"].astype(dtype)) * (1 - passes)
        return dataclasses.replace(params, **new)

    def linear(self, colours, xy, y: dict):
        """Colours (…, 3) in 0..255 at image positions xy (…, 2) to the photo's linear
        light: decoded, times the illumination field."""
        v = self.values(y)
        u = 2 * xy[..., 0] / self.structure.width - 1
        w = 2 * xy[..., 1] / self.structure.height - 1
        field = jnp.exp(field_basis(u, w) @ v["field"].astype(colours.dtype))
        return jnp.clip(colours / 255, 0, 1) * field[..., None]

    def display(self, light, y: dict):
        """Linear light back to display values 0..255: the tone curve x^(γ/2.2), times the
        gain, clipped as 8 bits are."""
        v = self.values(y)
        x = jnp.clip(light, 0, 1)
        pos = x > 1e-6
        xs = jnp.where(pos, x, 1)
        toned = jnp.where(pos, jnp.exp(v["gamma"] / DISPLAY_GAMMA * jnp.log(xs)), 0)
        return 255 * jnp.clip(toned * v["gain"].astype(toned.dtype), 0, 1)

    def camera(self, image, y: dict):
        """A photo (H, W, 3) of a render `image` (H, W, 3): to linear light, blurred
        ('blur'), toned to display values, its chroma blurred further ('chroma')."""
        v = self.values(y)
        h, w = image.shape[:2]
        j, i = jnp.meshgrid(jnp.arange(h, dtype=image.dtype) + 0.5, jnp.arange(w, dtype=image.dtype) + 0.5, indexing="ij")
        light = gaussian_blur(self.linear(image, jnp.stack([i, j], -1), y), v["blur"])
        out = self.display(light, y)
        return chroma_blur(out, v["chroma"])

    def image(self, scene: rtjax.Scene, y: dict, depth: int | None = None):
        """The photo (H, W, 3) the model makes of `scene` (its geometry; the appearance
        and camera from `y`): the silhouette-aware render (edges 1 pixel wide) through
        `camera`. What a photo fit's full-size level matches."""
        shown = rtjax.Scene(scene.structure, self.scene(scene.params, y))
        return self.camera(rtjax.render(shown, depth=depth, **WHOLE_IMAGE_RENDER), y)

    def camera_at(self, colours, xy, y: dict):
        """The camera at sample positions xy (K, 2) whose colours (K, 3) were box-filtered
        to the blur's size already (a coarse level): no blur of its own."""
        return self.display(self.linear(colours, xy, y), y)
