"""Checks that need several devices, run as a script in a process of its own
(XLA_FLAGS=--xla_force_host_platform_device_count=4 must be set before JAX starts;
`tests/test_batch.py` and `tests/test_multistart.py` launch it).

    python tests/multidevice.py render OUTDIR     sharded and batched renders vs rtjax.render
    python tests/multidevice.py fit JSON          a multi-start fit with its starts sharded

Prints one JSON object on stdout (the last line); every comparison is computed here and
asserted by the tests.
"""

from __future__ import annotations

import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENES = os.path.join(ROOT, "scenes")

import jax  # noqa: E402
import numpy as np  # noqa: E402

import rtjax  # noqa: E402

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)
from rtjax import batch  # noqa: E402

def timed(fn):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t


def same(a, b) -> bool:
    return bool(np.array_equal(np.asarray(a), np.asarray(b)))


def check_render(outdir: str) -> dict:
    out: dict = {"devices": len(jax.devices()), "platform": jax.devices()[0].platform, "times": {}}
    t = out["times"]
    sample = rtjax.load_deck(os.path.join(SCENES, "ex2s3.dat")).frames[0].scene

    # the sample deck at full size, pixels over 4 devices (294 rows: padded to 296)
    ref, t["render_compile"] = timed(lambda: rtjax.render(sample))
    sharded, t["sharded_compile"] = timed(lambda: batch.render_sharded(sample, devices=4))
    out["sample_full_4"] = same(ref, sharded)
    out["sample_shape"] = list(np.shape(sharded))
    out["sample_sharding_devices"] = len(sharded.sharding.device_set)
    _, t["render"] = timed(lambda: rtjax.render(sample))
    _, t["sharded"] = timed(lambda: batch.render_sharded(sample, devices=4))

    # the multi-frame deck: frame by frame, batched on one device, batched over 4
    deck = rtjax.load_deck(os.path.join(SCENES, "multi_frame.dat"))
    scenes = [f.scene for f in deck.frames]
    frames = [np.asarray(rtjax.render(s)) for s in scenes]
    _, t["frame_by_frame"] = timed(lambda: [rtjax.render(s) for s in scenes])
    batched, t["batched_compile"] = timed(lambda: rtjax.render_frames(scenes))
    out["multi_batched_1"] = [same(a, b) for a, b in zip(frames, batched)]  # lax.map in the call (a CPU's default)
    _, t["batched"] = timed(lambda: rtjax.render_frames(scenes))
    params = rtjax.stack_params([s.params for s in scenes])
    vmapped, t["vmap_compile"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, mode="vmap"))
    out["multi_vmap_1"] = [same(a, b) for a, b in zip(frames, vmapped)]
    _, t["vmap"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, mode="vmap"))
    by_frames, t["frames_4_compile"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, devices=4, split="frames"))
    out["multi_frames_4"] = [same(a, b) for a, b in zip(frames, by_frames)]
    _, t["frames_4"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, devices=4, split="frames"))
    by_pixels, t["pixels_4_compile"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, devices=4, split="pixels",
                                                                        mode="vmap"))
    out["multi_pixels_4"] = [same(a, b) for a, b in zip(frames, by_pixels)]
    _, t["pixels_4"] = timed(lambda: rtjax.render_batch(scenes[0].structure, params, devices=4, split="pixels", mode="vmap"))

    # `rtjax render --devices 4` writes what frame-by-frame rendering gives
    from rtjax import cli
    from rtjax.sunraster import read_sunraster

    t0 = time.perf_counter()
    code = cli.main(["render", os.path.join(SCENES, "multi_frame.dat"), "-o", outdir, "--devices", "4"])
    t["cli"] = time.perf_counter() - t0
    out["cli_code"] = code
    out["cli_files"] = [
        same(read_sunraster(os.path.join(outdir, f.output)), rtjax.to_uint8(image)) for f, image in zip(deck.frames, frames)
    ]
    return out


def check_fit(path: str) -> dict:
    """A multi-start fit (the spec's options) with its starts over 4 devices; the test
    compares it with the same fit on one device."""
    jax.config.update("jax_enable_x64", True)  # as the tests' own process (conftest.py)
    import fitting

    with open(path) as f:
        spec = json.load(f)
    truth = rtjax.parse_deck(spec["deck"]).frames[0].scene
    start = truth.replace(centers=np.asarray(truth.params.centers) + np.asarray(spec["offset"]))
    target = np.floor(np.asarray(rtjax.render(truth)) + 0.5)
    t = time.perf_counter()
    res = fitting.fit_multistart(start, target, "centers", devices=4, **spec["options"])
    return {
        "devices": res.devices,
        "losses": res.losses,
        "converged": res.converged,
        "results": res.results,
        "index": res.index,
        "centers": np.asarray(res.scene.params.centers).tolist(),
        "seconds": time.perf_counter() - t,
    }


if __name__ == "__main__":
    what, arg = sys.argv[1], sys.argv[2]
    result = check_render(arg) if what == "render" else check_fit(arg)
    print(json.dumps(result))
