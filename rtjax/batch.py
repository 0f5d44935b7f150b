"""Past one device: batched frames (vmap) and sharded rendering (`jax.sharding`).

* `render_batch(structure, params)`: frames that share a `Structure` (the `rend` lines
  of a deck where only the camera or some numbers change, a camera path, a parameter
  sweep) as one jit-compiled call over a leading frame axis of `params`: `jax.vmap`
  (the default on accelerators), or `lax.map` inside the call (the default on a CPU,
  where it keeps the renderer's run-time skipping of finished ray segments).
* `render_frames(scenes)`: any list of scenes; those sharing a structure are grouped,
  their `Params` stacked (`jax.tree.map(jnp.stack, ...)`) and rendered by
  `render_batch`, in chunks that bound memory; the images come back in order.
* `render_sharded(scene, devices="all")`: one image over several devices.

With `devices` (an int, "all", or a list of `jax.Device`), the work is sharded over a
one-axis `jax.sharding.Mesh` by `jax.shard_map` (in/out `PartitionSpec`s, i.e.
`NamedSharding`s of the mesh): either the pixels (rows of the image, dealt out to the
devices in turn so that each gets a share of the sky and of the spheres; padded with
copies of the last row so the count divides the device count) or, when a batch has at
least as many frames as devices, the frames (padded with copies of the last frame).
Every device runs the renderer's own per-pixel arithmetic on its share, so the result
equals `rtjax.render` bit for bit (the tests check it with 4 forced host devices).

Several hosts: call `init_distributed()` (`jax.distributed.initialize`) in every
process first; `devices="all"` then means every device of every process, and each
process gets the whole image back.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .errors import RtjaxError
from .render import Options, colours_at, render, render_image, resolve_options, supersample
from .scene import Params, Scene, Structure
from .spheres import GROUP, coherent_order
from .trace import BOX, PLAIN

#: The mesh axis name.
AXIS = "d"
#: Samples per device in one batched call (frames × pixels): bounds memory when
#: `render_frames` chunks a long camera path. 2²¹ ≈ 17 frames of 400 × 294 per device.
SAMPLES_PER_CALL = 1 << 21


# ---- devices ------------------------------------------------------------------------------


def init_distributed(**kwargs) -> None:
    """Join a multi-host run: `jax.distributed.initialize(**kwargs)`. Call it in every
    process before any JAX computation; afterwards `jax.devices()` lists every host's
    devices. What is not given comes from the environment: JAX_COORDINATOR_ADDRESS
    (host:port of process 0; read by JAX), JAX_NUM_PROCESSES and JAX_PROCESS_ID (read
    here), or JAX's own detection of Slurm, Open MPI, Kubernetes and Cloud TPU."""
    import os

    for key, name in (("num_processes", "JAX_NUM_PROCESSES"), ("process_id", "JAX_PROCESS_ID")):
        if kwargs.get(key) is None and os.environ.get(name):
            try:
                kwargs[key] = int(os.environ[name])
            except ValueError:
                raise RtjaxError(f"{name} must be a whole number, not {os.environ[name]!r}") from None
    jax.distributed.initialize(**kwargs)


def resolve_devices(devices=None) -> list:
    """None or 1: the default device only; "all": every device (of every process);
    an int N: the first N; or a sequence of `jax.Device`s as given."""
    if devices is None:
        return [jax.devices()[0]]
    if isinstance(devices, str):
        if devices.strip().lower() != "all":
            try:
                devices = int(devices)
            except ValueError:
                raise RtjaxError(f"devices must be a count or 'all', not {devices!r}") from None
        else:
            return list(jax.devices())
    if isinstance(devices, (int, np.integer)):
        n = int(devices)
        available = jax.devices()
        if n < 1:
            raise RtjaxError(f"devices must be ≥ 1, not {n}")
        if n > len(available):
            platform = available[0].platform
            hint = (f"; on a CPU, XLA_FLAGS=--xla_force_host_platform_device_count={n} splits it into {n}"
                    if platform == "cpu" else "")
            raise RtjaxError(f"{n} devices asked for, {len(available)} available ({platform}){hint}")
        return list(available[:n])
    out = list(devices)
    if not out:
        raise RtjaxError("no devices given")
    return out


def device_mesh(devices=None) -> Mesh | None:
    """A one-axis `Mesh` over `resolve_devices(devices)`, or None for a single device."""
    devs = resolve_devices(devices)
    if len(devs) == 1:
        return None
    return Mesh(np.array(devs), (AXIS,))


# ---- stacking ---------------------------------------------------------------------------------


def stack_params(params: Sequence[Params]) -> Params:
    """Params of several frames of one structure, stacked along a new leading axis."""
    if not params:
        raise RtjaxError("no frames to stack")
    return jax.tree.map(lambda *a: jnp.stack(a), *params)


def unstack_params(params: Params) -> list[Params]:
    n = jax.tree.leaves(params)[0].shape[0]
    return [jax.tree.map(lambda a: a[i], params) for i in range(n)]


def group_by_structure(scenes: Sequence[Scene]) -> list[tuple[Structure, list[int]]]:
    """Indices of the scenes sharing each structure, in order of first appearance (two
    scenes differing only in texture file names share one)."""
    groups: dict[Structure, list[int]] = {}
    for i, scene in enumerate(scenes):
        groups.setdefault(scene.structure, []).append(i)
    return list(groups.items())


# ---- the sharded, batched renderer -----------------------------------------------------------


def _layout(s: Structure, n: int) -> tuple[int, int]:
    """(unit, padded pixel count) for dealing pixels out to n devices: whole rows in
    turn (8×8 blocks, `GROUP` rays, in culled scenes' coherent order), padded so that
    every device gets as many units."""
    p = s.width * s.height
    unit = GROUP if s.culls else s.width
    units = -(-p // unit)
    return unit, -(-units // n) * n * unit


def _pixel_indices(s: Structure, n: int):
    """Which pixel each of the padded sample slots holds (int32, slot order: device 0's
    share, then device 1's, …) and how to put the slots back in row-major order."""
    p = s.width * s.height
    unit, padded = _layout(s, n)
    per = padded // n // unit  # units per device
    q = jnp.arange(padded, dtype=jnp.int32)
    dev, r = q // (padded // n), q % (padded // n)
    k = jnp.minimum(((r // unit) * n + dev) * unit + r % unit, p - 1)  # padding: copies of the last one
    if s.culls:
        order, _ = coherent_order(s.width, s.height)
        k = jnp.asarray(order.astype(np.int32))[k]
    return k, (unit, per)


def _reassemble(s: Structure, colours, n: int, unit: int, per: int):
    """(..., 3, padded) in slot order → (..., H, W, 3) row-major."""
    lead = colours.shape[:-2]
    c = colours.reshape(lead + (3, n, per, unit))
    c = jnp.swapaxes(c, -3, -2).reshape(lead + (3, n * per * unit))
    p = s.width * s.height
    c = c[..., :p]
    if s.culls:
        _, inverse = coherent_order(s.width, s.height)
        c = c[..., jnp.asarray(inverse.astype(np.int32))]
    return jnp.moveaxis(c.reshape(lead + (3, s.height, s.width)), -3, -1)


def _shade(s: Structure, p: Params, k, options: Options):
    """Colours (3, K) of pixels `k` (row-major indices): `rtjax.render`'s arithmetic
    (the positions i + ox, j + oy; K×K samples summed in the same order, then divided)."""
    dtype = p.eye.dtype
    ij = jnp.stack([(k % s.width).astype(dtype), (k // s.width).astype(dtype)])
    step = jnp.asarray(1 / options.spp, dtype)
    mode = BOX if options.edges else PLAIN

    def sample(offset):
        return colours_at(s, p, ij + offset[:, None], step, options.depth, options.tile, mode, options.edges,
                          subdivide=options.subdivide)

    return supersample(sample, options.spp, (3, k.shape[0]), dtype)


@functools.partial(jax.jit, static_argnames=("structure", "options", "mesh", "batched", "split", "mode"))
def _render_grid(params, structure: Structure, options: Options, mesh: Mesh | None, batched: bool, split: str,
                 mode: str = "vmap"):
    """Images (F, H, W, 3) of stacked params (or (H, W, 3) of one, `batched=False`),
    sharded over `mesh` by pixels or by frames; a device's frames are `jax.vmap`-ped
    (mode "vmap") or taken one after another by `lax.map` (mode "map")."""
    s = structure
    n = 1 if mesh is None or split == "frames" else mesh.devices.size
    k, (unit, per) = _pixel_indices(s, n)
    whole = bool(options.edges) and n == 1  # the silhouette mode on whole images is `rtjax.render`'s own

    def one(p, k):
        if whole:
            return render_image(s, p, options)
        return _shade(s, p, k, options)

    def local(p, k):
        if not batched:
            return one(p, k)
        if mode == "map":
            return jax.lax.map(lambda q: one(q, k), p)
        return jax.vmap(one, in_axes=(0, None))(p, k)

    if mesh is None:
        colours = local(params, k)
    elif split == "pixels":
        out = PartitionSpec(None, None, AXIS) if batched else PartitionSpec(None, AXIS)
        colours = jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec(), PartitionSpec(AXIS)), out_specs=out, check_vma=False)(params, k)
    else:
        colours = jax.shard_map(local, mesh=mesh, in_specs=(PartitionSpec(AXIS), PartitionSpec()),
                                out_specs=PartitionSpec(AXIS), check_vma=False)(params, k)
    return colours if whole else _reassemble(s, colours, n, unit, per)


def _global(tree, mesh: Mesh | None, spec: PartitionSpec):
    """With several processes, host arrays become global arrays of the mesh (every
    process holds the same values); with one, they are passed as they are."""
    if mesh is None or jax.process_count() == 1:
        return tree
    sharding = NamedSharding(mesh, spec)

    def put(a):
        a = np.asarray(a)
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])

    return jax.tree.map(put, tree)


def _local_copy(image):
    """The whole image on this process (several processes: gathered from all)."""
    if jax.process_count() == 1 or image.is_fully_addressable:
        return image
    from jax.experimental import multihost_utils

    return jnp.asarray(multihost_utils.process_allgather(image, tiled=True))


def render_batch(
    structure: Structure,
    params: Params,
    *,
    depth: int | None = None,
    spp: int = 1,
    dtype=None,
    edges: float = 0.0,
    tile: int | None = None,
    subdivide: int | bool | None = None,
    devices=None,
    split: str = "auto",
    mode: str = "auto",
):
    """Images (F, H, W, 3) of F frames of one structure in one jit-compiled call:
    `params` has a leading frame axis on every leaf (`stack_params`, or a sweep built
    with `jax.vmap`/`jnp.linspace`). Each image equals `rtjax.render` of that frame
    bit for bit. Options as `rtjax.render`; `devices` (None: one; an int; "all"; a list
    of devices) shards the work: `split` "pixels", "frames", or "auto" (frames when
    there are at least as many frames as devices, else pixels).

    mode: how a device takes its frames within the call: "vmap" (all at once, one
    vectorised program: what an accelerator wants), "map" (one after another,
    `lax.map`: each frame keeps the renderer's run-time skipping of finished ray
    segments, which `vmap` turns into computing both sides of a select: faster on a
    CPU), or "auto" (default: "map" on a
    CPU, "vmap" on a GPU or TPU). Differentiable in `params`."""
    leaves = jax.tree.leaves(params)
    if not leaves or np.ndim(leaves[0]) < 1:
        raise RtjaxError("render_batch needs params with a leading frame axis (see stack_params)")
    frames = int(np.shape(leaves[0])[0])
    if any(np.shape(a)[:1] != (frames,) for a in leaves):
        raise RtjaxError("every parameter needs the same leading frame axis")
    if split not in ("auto", "pixels", "frames"):
        raise RtjaxError(f"split must be 'auto', 'pixels' or 'frames', not {split!r}")
    if mode not in ("auto", "vmap", "map"):
        raise RtjaxError(f"mode must be 'auto', 'vmap' or 'map', not {mode!r}")
    first = jax.tree.map(lambda a: a[0], params)
    options = resolve_options(Scene(structure, first), depth, spp, dtype, edges, tile, subdivide)
    mesh = device_mesh(devices)
    n = 1 if mesh is None else mesh.devices.size
    if split == "auto":
        split = "frames" if frames >= n else "pixels"
    if mode == "auto":
        platform = (jax.devices()[0] if mesh is None else mesh.devices.flat[0]).platform
        mode = "map" if platform == "cpu" else "vmap"
    params = params.astype(options.dtype)
    padded = frames
    if mesh is not None and split == "frames" and frames % n:
        padded = -(-frames // n) * n
        params = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], padded - frames, axis=0)]), params)
    params = _global(params, mesh, PartitionSpec(AXIS) if split == "frames" else PartitionSpec())
    images = _render_grid(params, structure, options, mesh, True, split, mode)
    images = _local_copy(images)
    return images[:frames] if padded != frames else images


def render_sharded(scene: Scene, *, devices="all", depth: int | None = None, spp: int = 1, dtype=None,
                   edges: float = 0.0, tile: int | None = None, subdivide: int | bool | None = None):
    """One image (H, W, 3) with its pixels sharded over `devices` (default every
    device): equal to `rtjax.render(scene)` bit for bit; on one device it is that.

    The silhouette-aware mode (`edges` > 0) is the exception: XLA optimises the
    several-device program a little differently (a few float32 ulps in the ray
    differentials), and its discrete choice of each pixel's nearest edge amplifies
    that at some pixels (README "Several devices and hosts")."""
    mesh = device_mesh(devices)
    if mesh is None:
        return render(scene, depth=depth, spp=spp, dtype=dtype, edges=edges, tile=tile, subdivide=subdivide)
    options = resolve_options(scene, depth, spp, dtype, edges, tile, subdivide)
    params = _global(scene.params.astype(options.dtype), mesh, PartitionSpec())
    return _local_copy(_render_grid(params, scene.structure, options, mesh, False, "pixels"))


def batch_chunks(structure: Structure, frames: int, devices: int = 1, batch: int | None = None) -> list[range]:
    """Consecutive chunks of a group's frames rendered per call: `batch` frames, or as
    many as keep frames × pixels within `SAMPLES_PER_CALL` per device (at least one
    frame per device)."""
    if batch is None:
        per_device = max(1, SAMPLES_PER_CALL // (structure.width * structure.height))
        batch = per_device * devices
    batch = max(1, int(batch))
    return [range(i, min(frames, i + batch)) for i in range(0, frames, batch)]


def plan_batches(scenes: Sequence[Scene], devices: int = 1, batch: int | None = None) -> list[list[int]]:
    """The calls that render `scenes`: lists of indices of scenes sharing a structure
    (groups in order of first appearance, each cut by `batch_chunks`)."""
    out = []
    for structure, indices in group_by_structure(scenes):
        out += [[indices[i] for i in part] for part in batch_chunks(structure, len(indices), devices, batch)]
    return out


def render_chunk(scenes: Sequence[Scene], *, depth=None, spp=1, dtype=None, edges=0.0, tile=None, subdivide=None,
                 devices=None, mode: str = "auto") -> list:
    """Images of scenes that share one structure, in one call: `render_batch` of their
    stacked params; a lone scene is `render_sharded` (on one device, `rtjax.render`)."""
    scenes = list(scenes)
    if len({s.structure for s in scenes}) != 1:
        raise RtjaxError("render_chunk needs scenes of one structure (see group_by_structure)")
    options = {"depth": depth, "spp": spp, "dtype": dtype, "edges": edges, "subdivide": subdivide}
    if tile is not None:
        options["tile"] = tile
    if len(scenes) == 1:
        if len(resolve_devices(devices)) == 1:
            return [render(scenes[0], **options)]
        return [render_sharded(scenes[0], devices=devices, **options)]
    out = render_batch(scenes[0].structure, stack_params([s.params for s in scenes]), devices=devices, mode=mode, **options)
    return [out[i] for i in range(len(scenes))]


def render_frames(
    scenes: Sequence[Scene],
    *,
    depth: int | None = None,
    spp: int = 1,
    dtype=None,
    edges: float = 0.0,
    tile: int | None = None,
    subdivide: int | bool | None = None,
    devices=None,
    batch: int | None = None,
    mode: str = "auto",
) -> list:
    """Images (H, W, 3) of `scenes`, in order: scenes that share a structure render
    together, one `render_batch` call per chunk of up to `batch` frames (default: a
    memory bound, `batch_chunks`; `mode` as `render_batch`); a lone scene on one
    device is `rtjax.render`. Every image equals `rtjax.render` of its scene bit for bit."""
    scenes = list(scenes)
    images: list = [None] * len(scenes)
    n = len(resolve_devices(devices))
    for chunk in plan_batches(scenes, n, batch):
        out = render_chunk([scenes[i] for i in chunk], depth=depth, spp=spp, dtype=dtype, edges=edges, tile=tile,
                           subdivide=subdivide, devices=devices, mode=mode)
        for i, image in zip(chunk, out):
            images[i] = image
    return images


__all__ = [
    "batch_chunks", "device_mesh", "group_by_structure", "init_distributed", "plan_batches", "render_batch",
    "render_chunk", "render_frames", "render_sharded", "resolve_devices", "stack_params", "unstack_params",
]
