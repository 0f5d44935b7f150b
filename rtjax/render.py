"""`render`: a scene to a float image (H, W, 3) in 0..255, jit-compiled per structure."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .camera import pixel_grid, rays_through, subpixel_offsets
from .edges import Differentials, edge_pixels
from .errors import RtjaxError
from .scene import Params, Scene, Structure
from .spheres import coherent_order, culls
from .trace import tiled, trace, trace_edges


def resolve_dtype(scene: Scene, dtype) -> jnp.dtype:
    """None keeps the parameters' dtype (float32 for a loaded deck); float64 needs x64."""
    if dtype is None:
        dtype = jnp.result_type(scene.params.centers)
    dtype = jnp.dtype(dtype)
    if dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64)):
        raise RtjaxError(f"dtype must be float32 or float64, not {dtype}")
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise RtjaxError(
            "float64 rendering needs 64-bit JAX: call jax.config.update('jax_enable_x64', True) "
            "first (or set JAX_ENABLE_X64=1)"
        )
    return dtype


def resolve_depth(structure: Structure, depth: int | None) -> int:
    """The scene's default, and 0 whatever is asked when nothing spawns a further ray."""
    if depth is None:
        return structure.default_depth
    if depth < 0:
        raise RtjaxError(f"depth must be ≥ 0, not {depth}")
    return int(depth) if structure.needs_secondary_rays else 0


def render(
    scene: Scene,
    *,
    depth: int | None = None,
    spp: int = 1,
    dtype=None,
    edges: float = 0.0,
    tile: int | None = None,
) -> Float[Array, "h w 3"]:
    """Render `scene` to an (H, W, 3) image in 0..255, clamped, not rounded.

    depth: further segments after the primary ray (default 10 with mirrors or glass,
      else 0); a ray still alive after that contributes black.
    spp: k for k×k samples per pixel on a regular grid, each clamped, then averaged.
    dtype: float32 or float64 (default: the scene's own, float32 for a loaded deck).
    edges: silhouette-aware mode: each pixel's nearest silhouette (seen directly, in a
      mirror or through glass) and each hit's nearest shadow edge are box-filtered over
      `edges` pixels (1 = the pixel's own box), so the image is antialiased at edges and
      its derivative includes their motion (see `rtjax.edges`). 0 (default) renders
      pixel centres. On images of more than `EDGE_CHUNK_MIN` pixels the mode is spent
      where edges are: every pixel is traced plainly first, and only those near a
      change in what their chains meet are traced again in the mode (`image_edges`).
    tile: rays traced together (default: 2¹⁷ on a CPU, 2²⁰ on an accelerator); the
      image does not depend on it, only speed and memory do.

    Differentiable in `scene.params` with jax.grad / jax.jacfwd / jax.jvp.
    """
    depth, spp, dtype, edges, tile = resolve_options(scene, depth, spp, dtype, edges, tile)
    return _render(scene.params.astype(dtype), scene.structure, depth, spp, tile, edges)


def resolve_options(scene: Scene, depth, spp, dtype, edges, tile) -> tuple[int, int, jnp.dtype, float, int]:
    """`render`'s options checked and resolved (a clear `RtjaxError` for a bad one):
    depth, spp, dtype, edges, tile; `render_batch` and `render_frames` share them."""
    if int(spp) < 1:
        raise RtjaxError(f"spp must be ≥ 1, not {spp}")
    dtype = resolve_dtype(scene, dtype)
    tile = resolve_tile(tile)
    edges = float(edges)
    if not (0 <= edges <= 16):
        raise RtjaxError(f"edges (an edge width in pixels) must be in [0, 16], not {edges}")
    return resolve_depth(scene.structure, depth), int(spp), dtype, edges, tile


def resolve_tile(tile: int | None) -> int:
    """Rays traced together: `default_tile()` for None, else a whole number ≥ 1."""
    tile = default_tile() if tile is None else int(tile)
    if tile < 1:
        raise RtjaxError(f"tile must be ≥ 1, not {tile}")
    return tile


def default_tile() -> int:
    """Rays traced together: bounds memory on large images; on a CPU, splitting a
    400×294 frame further measured slower (per-tile loop overhead), so it is one tile."""
    return 1 << 17 if jax.default_backend() == "cpu" else 1 << 20


@functools.partial(jax.jit, static_argnames=("structure", "depth", "spp", "tile", "edges"))
def _render(params: Params, structure: Structure, depth: int, spp: int, tile: int, edges: float = 0.0):
    return render_image(structure, params, depth, spp, tile, edges)


def render_image(s: Structure, p: Params, depth: int, spp: int, tile: int, edges: float) -> Float[Array, "h w 3"]:
    """`render`'s image, not compiled on its own (`rtjax.batch` maps it over frames)."""

    def sample(offset):
        step = jnp.asarray(1 / spp, offset.dtype)
        if edges and s.width * s.height > EDGE_CHUNK_MIN:  # smaller: every pixel in one chunk
            return image_edges(s, p, offset, step, depth, tile, edges, reach=math.ceil(edges / spp / 2))
        xy = pixel_grid(s.width, s.height, offset)
        if not culls(s.n_spheres):
            return colours_at(s, p, xy, step, depth, tile, edges)
        # large scenes cull spheres per group of consecutive rays: trace 8×8 blocks together
        order, inverse = coherent_order(s.width, s.height)
        return colours_at(s, p, xy[:, order], step, depth, tile, edges)[:, inverse]

    offsets = subpixel_offsets(spp, p.eye.dtype)
    if spp == 1:
        image = sample(offsets[0])
    else:
        total, _ = jax.lax.scan(lambda acc, off: (acc + sample(off), None), jnp.zeros((3, s.height * s.width), p.eye.dtype), offsets)
        image = total / (spp * spp)
    return image.reshape(3, s.height, s.width).transpose(1, 2, 0)


#: The silhouette mode over a whole image (`image_edges`) traces the pixels near edges
#: in chunks of a sixteenth of the image (at least `EDGE_CHUNK_MIN` pixels, at most
#: `tile`); chunks past the last of them are skipped at run time. Pixels near edges
#: are 9–16 % of the decks in scenes/ at a 1-pixel width: two or three chunks.
EDGE_CHUNKS = 16
EDGE_CHUNK_MIN = 4096


def image_edges(s: Structure, p: Params, offset, step, depth: int, tile: int, edges: float, reach: int):
    """The silhouette mode over the image's pixels at sub-pixel `offset`: clamped
    colours (3, H·W), row-major.

    Edges cover a few per cent of an image, so the mode's cost is spent there: a plain
    trace of every pixel (and of a ring `reach` pixels wide around the image) also
    hashes each chain's hits and shadows into a key (`trace.hit_key`); the pixels near
    a change of key (`edges.edge_pixels`) are traced again in the silhouette mode
    (`colours_at`), in chunks of which only those holding such pixels run (each
    checkpointed: its reverse mode recomputes it rather than storing it); every other
    pixel keeps its plain colour, which is its box-filtered one (no edge crosses its
    box), and so is its derivative. Under `jax.vmap` every chunk runs.
    """
    w, h, n = s.width + 2 * reach, s.height + 2 * reach, s.width * s.height
    ring = pixel_grid(w, h, offset - reach)  # the image's pixels and the ring around them
    order, inverse = coherent_order(w, h) if culls(s.n_spheres) else (None, None)
    o, d = rays_through(p.eye, p.refp, p.vang, s.width, s.height, ring if order is None else ring[:, order])
    colour, keys = tiled(lambda o, d: trace(s, p, o, d, depth, keyed=True), tile, o, d)
    if order is not None:
        colour, keys = colour[:, inverse], keys[inverse]
    inner = (slice(None), slice(reach, h - reach), slice(reach, w - reach))
    colour = colour.reshape(3, h, w)[inner].reshape(3, n)
    near = edge_pixels(keys.reshape(h, w), reach).reshape(n)
    xy = pixel_grid(s.width, s.height, offset)
    if culls(s.n_spheres):  # traced again in 8×8 blocks
        order = coherent_order(s.width, s.height)[0]
        near = near[order]
    (sel,) = jnp.nonzero(near, size=n, fill_value=0)
    count = jnp.sum(near)
    if culls(s.n_spheres):
        sel = jnp.asarray(order)[sel]
    chunk = min(tile, max(EDGE_CHUNK_MIN, -(-n // EDGE_CHUNKS)))
    blended = colours_at(s, p, xy[:, sel], step, depth, chunk, edges, capacity=chunk, count=count)
    # padding slots (pixel 0 repeated) write nowhere: pixel 0 may itself be near an edge
    to = jnp.where(jnp.arange(n) < count, sel, n)
    return jnp.clip(colour, 0, 255).at[:, to].set(blended, mode="drop")


def colours_at(s: Structure, p: Params, xy, step, depth: int, tile: int, edges: float, parts: bool = False,
               capacity: int | None = None, count=None):
    """Clamped colours (3, K) seen through image positions xy (2, K) (pixels of the
    scene's image). In the silhouette mode, `step` is the sample spacing in pixels: the
    box over which edges are filtered is `edges`·`step` pixels wide; `parts`: (14, K),
    the centre colours and the edge blend's parts (`trace.trace_edges`); `capacity`:
    the edge pixels its pass 2 takes per `tile` (`trace.trace_edges`); `count`
    (traced): only the first `count` positions are wanted (`trace.tiled`)."""
    if isinstance(edges, (int, float)) and edges == 0:
        o, d = rays_through(p.eye, p.refp, p.vang, s.width, s.height, xy)
        return jnp.clip(tiled(lambda o, d: trace(s, p, o, d, depth), tile, o, d), 0, 255)

    def directions(xy):
        return rays_through(p.eye, p.refp, p.vang, s.width, s.height, xy)[1]

    zero = jnp.zeros_like(step)
    d, dx = jax.jvp(directions, (xy,), (jnp.broadcast_to(jnp.stack([step, zero])[:, None], xy.shape),))
    _, dy = jax.jvp(directions, (xy,), (jnp.broadcast_to(jnp.stack([zero, step])[:, None], xy.shape),))
    o = jnp.broadcast_to(p.eye[:, None], d.shape)
    still = jnp.zeros_like(d)  # all primary rays leave the eye

    def run(o, d, ox, dx, oy, dy):
        return trace_edges(s, p, o, d, Differentials(ox, dx, oy, dy), depth, edges, parts, capacity)

    return tiled(run, tile, o, d, still, dx, still, dy, count=count)


class EdgeSamples(NamedTuple):
    """`render_samples(..., parts=True)`: what matching a target sampled at pixel
    centres needs. The colour at each sample's centre (shadows sharp); for its nearest
    silhouette, the colours traced just on the edge sphere's side of it and just on the
    other, where it passes nearest to the centre, and the centre's signed distance to
    that edge; for its nearest shadow edge (over the chain: seen directly, in mirrors,
    through glass), the centre's colour had it lain on the edge's other side, and its
    distance to that edge. Without a silhouette, inside = outside = centre and x = 0;
    without a shadow edge within reach, flipped = centre and shadow_x = inf."""

    centre: Float[Array, "k 3"]
    inside: Float[Array, "k 3"]  # traced on the edge sphere's side
    outside: Float[Array, "k 3"]  # traced on the other side
    x: Float[Array, " k"]  # the centre's signed distance to the silhouette in box widths, > 0 inside
    flipped: Float[Array, "k 3"]  # the centre's colour across its nearest shadow edge
    shadow_x: Float[Array, " k"]  # the centre's distance to that edge in box widths (≥ 0)


def render_samples(
    scene: Scene,
    xy,
    *,
    step: float = 1.0,
    depth: int | None = None,
    edges: float = 0.0,
    dtype=None,
    tile: int | None = None,
    parts: bool = False,
) -> Float[Array, "k 3"] | EdgeSamples:
    """Colours (K, 3) in 0..255 seen through K image positions `xy` (K, 2), in pixels of
    the scene's image ((i + ½, j + ½) is pixel (i, j)'s centre).

    A render of any subset or lattice of the image: fitting uses it to render a coarse
    grid and then a band of pixels around edges with one compiled function (K fixed;
    positions, `step` and a non-zero `edges` traced). `step` is the spacing the samples
    stand for, in pixels: with `edges`, edges are box-filtered over `edges`·`step` pixels.
    `parts` (with `edges`): an `EdgeSamples` instead, the centre colours and the edge
    blend's parts (fitting uses them to match a target sampled at pixel centres).
    """
    dtype = resolve_dtype(scene, dtype)
    tile = resolve_tile(tile)
    xy = jnp.asarray(xy, dtype)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise RtjaxError(f"xy must have shape (K, 2), not {xy.shape}")
    depth = resolve_depth(scene.structure, depth)
    aware = not (isinstance(edges, (int, float)) and edges == 0)  # a traced width means the mode is on
    if parts and not aware:
        raise RtjaxError("parts=True needs the silhouette-aware mode (edges > 0)")
    width = jnp.asarray(edges, dtype)
    out = _render_samples(scene.params.astype(dtype), xy.T, jnp.asarray(step, dtype), width, scene.structure, depth, tile,
                          aware, parts)
    return EdgeSamples(out[:3].T, out[3:6].T, out[6:9].T, out[9], out[10:13].T, out[13]) if parts else out.T


@functools.partial(jax.jit, static_argnames=("structure", "depth", "tile", "aware", "parts"))
def _render_samples(params: Params, xy, step, width, structure: Structure, depth: int, tile: int, aware: bool, parts: bool):
    return colours_at(structure, params, xy, step, depth, tile, width if aware else 0, parts)
