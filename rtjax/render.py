"""`render`, `render_samples` and `edge_samples`: a scene to colours, jit-compiled per structure."""

from __future__ import annotations

import dataclasses
import functools
import math
import operator

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .camera import pixel_grid, rays_through, subpixel_offsets
from .compact import pack
from .edges import RIM, Differentials, EdgeSamples, edge_pixels
from .errors import RtjaxError
from .numerics import clamp_colour
from .scene import Params, Scene, Structure
from .spheres import coherent_order
from .trace import BOX, LEVEL, PLAIN, SIDED, Mode, tiled, trace, trace_edges

#: Depths must be below this (`trace.LEVEL` counts segments).
MAX_DEPTH = int(jnp.iinfo(LEVEL).max)
#: The widest edge box the silhouette-aware mode takes, in pixels.
MAX_EDGE_WIDTH = 16.0
#: The most halvings of a box `subdivide` takes (16 × 16 sub-boxes where edges are).
MAX_SUBDIVIDE = 4
#: `subdivide`'s default (None) in the silhouette-aware mode on images of at most
#: `EDGE_CHUNK_MIN` pixels: 16 × 16 sub-boxes where edges are (4 × 4, then 4 × 4 again
#: in the sub-boxes an edge may cross: `trace.sub_box_levels`). In small images a pixel
#: often holds several edges (an outline and its shadow, what mirrors and glass show,
#: compressed near their rims); larger images keep one box, which meets the mode's cost
#: goal (docs/EDGES.md, "Knobs" and "Cost").
SMALL_IMAGE_SUBDIVIDE = 4


@dataclasses.dataclass(frozen=True)
class Options:
    """`render`'s options, checked and resolved (`resolve_options`): static, so they key
    the compiled renderer."""

    depth: int  # further segments after the primary ray
    spp: int  # k for k×k samples per pixel
    dtype: jnp.dtype  # float32 or float64
    edges: float  # the silhouette-aware mode's edge width in pixels (0: pixel centres)
    tile: int  # rays traced together
    subdivide: int = 0  # the silhouette mode: halvings of the box in the pixels an edge may cross (resolved)


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
    if not 0 <= depth < MAX_DEPTH:
        raise RtjaxError(f"depth must be in [0, {MAX_DEPTH}), not {depth}")
    return int(depth) if structure.needs_secondary_rays else 0


def resolve_tile(tile: int | None) -> int:
    """Rays traced together: `default_tile()` for None, else a whole number ≥ 1."""
    tile = default_tile() if tile is None else int(tile)
    if tile < 1:
        raise RtjaxError(f"tile must be ≥ 1, not {tile}")
    return tile


def default_tile() -> int:
    """Rays traced together by default: one tile for a CPU's usual image (splitting a
    frame only adds per-tile loop overhead there), a bound on memory elsewhere."""
    return 1 << 17 if jax.default_backend() == "cpu" else 1 << 20


def resolve_subdivide(edges, subdivide: int | bool | None, default: int = 0) -> int:
    """`subdivide` as a count of halvings (True: 1, False: 0, None: `default`), or a
    clear error: a whole number in [0, MAX_SUBDIVIDE], and none without the
    silhouette-aware mode (it divides that mode's boxes)."""
    if subdivide is None:
        return default
    try:
        halvings = operator.index(subdivide)
    except TypeError:
        halvings = -1
    if not 0 <= halvings <= MAX_SUBDIVIDE:
        raise RtjaxError(f"subdivide (halvings of the box) must be a whole number in [0, {MAX_SUBDIVIDE}], not {subdivide!r}")
    if halvings and isinstance(edges, (int, float)) and edges == 0:
        raise RtjaxError("subdivide needs the silhouette-aware mode (edges > 0)")
    return halvings


def default_subdivide(structure: Structure, edges: float) -> int:
    """`subdivide` when not given: `SMALL_IMAGE_SUBDIVIDE` in the silhouette-aware mode
    on images of at most `EDGE_CHUNK_MIN` pixels, else 0."""
    return SMALL_IMAGE_SUBDIVIDE if edges and traced_whole(structure) else 0


def resolve_options(scene: Scene, depth, spp, dtype, edges, tile, subdivide: int | bool | None = None) -> Options:
    """`render`'s options checked (a clear `RtjaxError` for a bad one) and resolved;
    `render_batch` and `render_frames` share them."""
    if int(spp) != spp or spp < 1:
        raise RtjaxError(f"spp must be a whole number ≥ 1, not {spp}")
    edges = float(edges)
    if not (0 <= edges <= MAX_EDGE_WIDTH):
        raise RtjaxError(f"edges (an edge width in pixels) must be in [0, {MAX_EDGE_WIDTH:g}], not {edges}")
    depth = resolve_depth(scene.structure, depth)
    return Options(depth, int(spp), resolve_dtype(scene, dtype), edges, resolve_tile(tile),
                   resolve_subdivide(edges, subdivide, default_subdivide(scene.structure, edges)))


def render(
    scene: Scene,
    *,
    depth: int | None = None,
    spp: int = 1,
    dtype=None,
    edges: float = 0.0,
    tile: int | None = None,
    subdivide: int | bool | None = None,
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
      pixel centres. The mode is spent where edges are (`image_edges`).
    subdivide: with `edges`, the pixels whose box an edge may cross (a silhouette or an
      intersection curve, seen directly, in a mirror or through glass, or a shadow edge
      or a terminator at any hit), or with a highlight narrow across the box or the rim
      of a sphere met near it, where the colour is far from linear, are box-filtered
      as the mean of k × k sub-boxes, k = 2^`subdivide` (1 or True: 2 × 2; 2: 4 × 4; 3
      and 4: 4 × 4, then 2 × 2 or 4 × 4 in each sub-box an edge may cross:
      `trace.sub_box_levels`), each with its own nearest edge (`trace.trace_edges`):
      derivatives far closer to the truth where a pixel holds several edges and inside
      mirrors and glass, at several times the mode's cost. None (default): 4 (16 × 16
      where edges are) on images of at most 4,096 pixels, else one box
      (`default_subdivide`; docs/EDGES.md).
    tile: rays traced together (default: 2¹⁷ on a CPU, 2²⁰ on an accelerator); the
      image does not depend on it, only speed and memory do.

    Differentiable in `scene.params` with jax.grad / jax.jacfwd / jax.jvp.
    """
    options = resolve_options(scene, depth, spp, dtype, edges, tile, subdivide)
    return _render(scene.params.astype(options.dtype), scene.structure, options)


@functools.partial(jax.jit, static_argnames=("structure", "options"))
def _render(params: Params, structure: Structure, options: Options):
    return render_image(structure, params, options)


def supersample(sample, spp: int, shape: tuple[int, ...], dtype) -> Array:
    """The mean of `sample(offset)` over the k×k sub-pixel offsets (k = `spp`), summed in
    order by a `lax.scan` (one compiled sample, whatever k)."""
    offsets = subpixel_offsets(spp, dtype)
    if spp == 1:
        return sample(offsets[0])
    total, _ = jax.lax.scan(lambda acc, off: (acc + sample(off), None), jnp.zeros(shape, dtype), offsets)
    return total / (spp * spp)


def render_image(s: Structure, p: Params, options: Options) -> Float[Array, "h w 3"]:
    """`render`'s image, not compiled on its own (`rtjax.batch` maps it over frames)."""
    step = jnp.asarray(1 / options.spp, p.eye.dtype)

    def sample(offset):
        if options.edges and not traced_whole(s):
            return image_edges(s, p, offset, step, options, reach=edge_reach(options))
        mode = BOX if options.edges else PLAIN
        xy = pixel_grid(s.width, s.height, offset)
        if not s.culls:
            return colours_at(s, p, xy, step, options.depth, options.tile, mode, options.edges, subdivide=options.subdivide)
        # culled scenes test spheres per group of consecutive rays: trace 8×8 blocks together
        order, inverse = coherent_order(s.width, s.height)
        return colours_at(s, p, xy[:, order], step, options.depth, options.tile, mode, options.edges,
                          subdivide=options.subdivide)[:, inverse]

    image = supersample(sample, options.spp, (3, s.height * s.width), p.eye.dtype)
    return image.reshape(3, s.height, s.width).transpose(1, 2, 0)


#: The silhouette mode over a whole image (`image_edges`) traces the pixels near edges
#: in chunks of a sixteenth of the image (at least `EDGE_CHUNK_MIN` pixels, at most
#: `tile`); chunks past the last of them are skipped at run time. Images of at most
#: `EDGE_CHUNK_MIN` pixels are traced in the mode whole.
EDGE_CHUNKS = 16
EDGE_CHUNK_MIN = 4096


def traced_whole(s: Structure) -> bool:
    """Whether the silhouette mode traces every pixel of `s`'s image in one chunk (at
    most `EDGE_CHUNK_MIN` pixels) rather than the pixels near edges (`image_edges`)."""
    return s.width * s.height <= EDGE_CHUNK_MIN


def edge_reach(options: Options) -> int:
    """How far from a change of key (`image_edges`) a pixel may lie, in pixels, and still
    need the silhouette mode: half a box (an edge crossing its box, `edges.CROSSING`),
    or with sub-boxes `edges.RIM` boxes and one more (a rim near its box,
    `trace.subdivided_pixels`, whose distance the rule bounds from below)."""
    box = options.edges / options.spp
    return math.ceil(box * (RIM + 1)) if options.subdivide else math.ceil(box / 2)


def image_edges(s: Structure, p: Params, offset, step, options: Options, reach: int):
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
    order, inverse = coherent_order(w, h) if s.culls else (None, None)
    o, d = rays_through(p.eye, p.refp, p.vang, s.width, s.height, ring if order is None else ring[:, order])
    traced = tiled(lambda o, d: trace(s, p, o, d, options.depth, keyed=True), options.tile, o, d)
    colour, keys = traced.colour, traced.key
    if order is not None:
        colour, keys = colour[:, inverse], keys[inverse]
    inner = (slice(None), slice(reach, h - reach), slice(reach, w - reach))
    colour = colour.reshape(3, h, w)[inner].reshape(3, n)
    near = edge_pixels(keys.reshape(h, w), reach).reshape(n)
    xy = pixel_grid(s.width, s.height, offset)
    if s.culls:  # traced again in 8×8 blocks
        order = coherent_order(s.width, s.height)[0]
        near = near[order]
    packed = pack(near, n)
    if s.culls:
        packed = packed.renumbered(jnp.asarray(order))
    chunk = min(options.tile, max(EDGE_CHUNK_MIN, -(-n // EDGE_CHUNKS)))
    blended = colours_at(s, p, packed.gather(xy), step, options.depth, chunk, BOX, options.edges, capacity=chunk,
                         count=packed.count, subdivide=options.subdivide)
    return packed.scatter(clamp_colour(colour), blended)


def _differentials(s: Structure, p: Params, xy, step):
    """Primary rays through image positions xy (2, K) and their differentials: how
    they change per sample step (`step` pixels) across and down."""

    def directions(xy):
        return rays_through(p.eye, p.refp, p.vang, s.width, s.height, xy)[1]

    zero = jnp.zeros_like(step)
    d, dx = jax.jvp(directions, (xy,), (jnp.broadcast_to(jnp.stack([step, zero])[:, None], xy.shape),))
    _, dy = jax.jvp(directions, (xy,), (jnp.broadcast_to(jnp.stack([zero, step])[:, None], xy.shape),))
    o = jnp.broadcast_to(p.eye[:, None], d.shape)
    still = jnp.zeros_like(d)  # all primary rays leave the eye
    return o, d, Differentials(still, dx, still, dy)


def colours_at(s: Structure, p: Params, xy, step, depth: int, tile: int, mode: Mode, width=0.0,
               capacity: int | None = None, count=None, subdivide: int = 0) -> Float[Array, "3 k"]:
    """Clamped colours (3, K) seen through image positions xy (2, K) (pixels of the
    scene's image): at their centres (`PLAIN`) or box-filtered at edges (`BOX`), the
    box `width`·`step` pixels wide (`step`: the samples' spacing in pixels).
    `capacity`: the edge pixels pass 2 takes per `tile` (`trace.trace_edges`); `count`
    (traced): only the first `count` positions are wanted (`trace.tiled`); `subdivide`:
    the box mode's halvings of the box in the pixels an edge may cross (`trace.trace_edges`)."""
    if mode == PLAIN:
        o, d = rays_through(p.eye, p.refp, p.vang, s.width, s.height, xy)
        return clamp_colour(tiled(lambda o, d: trace(s, p, o, d, depth).colour, tile, o, d))

    def run(o, d, diff):
        return trace_edges(s, p, o, d, diff, depth, width, BOX, capacity, subdivide).blended

    return tiled(run, tile, *_differentials(s, p, xy, step), count=count)


def check_positions(xy, dtype) -> Array:
    """Image positions as a (K, 2) array of `dtype`, or a clear error."""
    xy = jnp.asarray(xy, dtype)
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] == 0:
        raise RtjaxError(f"xy must have shape (K, 2) with K ≥ 1, not {xy.shape}")
    return xy


def render_samples(
    scene: Scene,
    xy,
    *,
    step: float = 1.0,
    depth: int | None = None,
    edges: float = 0.0,
    dtype=None,
    tile: int | None = None,
    subdivide: int | bool = 0,
) -> Float[Array, "k 3"]:
    """Colours (K, 3) in 0..255 seen through K image positions `xy` (K, 2), in pixels of
    the scene's image ((i + ½, j + ½) is pixel (i, j)'s centre).

    A render of any subset or lattice of the image: fitting uses it to render a coarse
    grid and then a band of pixels around edges with one compiled function (K fixed;
    positions, `step` and a non-zero `edges` traced). `step` is the spacing the samples
    stand for, in pixels: with `edges`, edges are box-filtered over `edges`·`step` pixels
    (`subdivide` as `render`'s, but 0 by default: positions are not an image).
    """
    dtype = resolve_dtype(scene, dtype)
    xy = check_positions(xy, dtype)
    subdivide = resolve_subdivide(edges, subdivide)
    mode = PLAIN if isinstance(edges, (int, float)) and edges == 0 else BOX  # a traced width means the mode is on
    out = _render_samples(scene.params.astype(dtype), xy.T, jnp.asarray(step, dtype), jnp.asarray(edges, dtype),
                          scene.structure, resolve_depth(scene.structure, depth), resolve_tile(tile), mode,
                          subdivide)
    return out.T


@functools.partial(jax.jit, static_argnames=("structure", "depth", "tile", "mode", "subdivide"))
def _render_samples(params: Params, xy, step, width, structure: Structure, depth: int, tile: int, mode: Mode,
                    subdivide: int = 0):
    return colours_at(structure, params, xy, step, depth, tile, mode, width, subdivide=subdivide)


def edge_samples(
    scene: Scene,
    xy,
    *,
    step: float = 1.0,
    depth: int | None = None,
    edges: float = 1.0,
    dtype=None,
    tile: int | None = None,
) -> EdgeSamples:
    """What matching a target sampled at pixel centres needs, at K image positions `xy`
    (K, 2) (as `render_samples`): an `EdgeSamples` whose colours are (K, 3).

    The colour at each sample's centre (shadows sharp); for its nearest silhouette, the
    colours traced just on the edge sphere's side of it and just on the other, where it
    passes nearest to the centre, and the centre's signed distance to that edge; for
    its nearest shadow edge (over the chain: seen directly, in mirrors, through glass),
    the centre's colour had it lain on the edge's other side, and its distance to that
    edge. Distances are in box widths (`edges`·`step` pixels; `edges` > 0, may be traced).
    """
    dtype = resolve_dtype(scene, dtype)
    xy = check_positions(xy, dtype)
    if isinstance(edges, (int, float)) and not 0 < edges <= MAX_EDGE_WIDTH:
        raise RtjaxError(f"edges (an edge width in pixels) must be in (0, {MAX_EDGE_WIDTH:g}], not {edges}")
    out = _edge_samples(scene.params.astype(dtype), xy.T, jnp.asarray(step, dtype), jnp.asarray(edges, dtype),
                        scene.structure, resolve_depth(scene.structure, depth), resolve_tile(tile))
    return EdgeSamples(*(a.T for a in out))


@functools.partial(jax.jit, static_argnames=("structure", "depth", "tile"))
def _edge_samples(params: Params, xy, step, width, structure: Structure, depth: int, tile: int) -> EdgeSamples:
    def run(o, d, diff):
        return trace_edges(structure, params, o, d, diff, depth, width, SIDED)

    return tiled(run, tile, *_differentials(structure, params, xy, step))
