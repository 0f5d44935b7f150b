"""The figures quoted in the README and the issues' closing notes, measured side by side
in one run on the sample deck (400×294, float32, depth 10):

compile time and median forward time, plain and silhouette-aware; reverse gradient
(jax.grad of the mean image w.r.t. all parameters, timed in turn with the forward
render, round by round) and jacfwd w.r.t. the 24 centre coordinates, each as a ratio
to the plain forward time of the same run and to the forward time of its own mode;
and the reverse gradient's peak temporary memory at each of `--depths` (XLA's
compiled memory analysis), per mode.

  python scripts/timings.py [--runs 5] [--deck scenes/ex2s3.dat] [--depths 0 2 10]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import rtjax

rtjax.tune_cpu()  # before any JAX computation (rtjax.xla)


def timed(calls, runs: int):
    """Compile time and median run time of each (fn, args) in `calls`, run in turn in
    each of `runs` rounds (interleaved, so that a slow spell of the machine slows all
    of them alike: their ratios are what is quoted)."""
    first = []
    for fn, args in calls:
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        first.append(time.perf_counter() - t)
    times = [[] for _ in calls]
    for _ in range(runs):
        for (fn, args), out in zip(calls, times):
            t = time.perf_counter()
            jax.block_until_ready(fn(*args))
            out.append(time.perf_counter() - t)
    return [(f - statistics.median(ts), statistics.median(ts)) for f, ts in zip(first, times)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deck", default="scenes/ex2s3.dat")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--depths", type=int, nargs="*", default=[0, 2, 10], help="depths for the gradient's memory (none: skip)")
    args = ap.parse_args()
    scene = rtjax.load_deck(args.deck).frames[0].scene
    s = scene.structure
    rows = []
    base = None
    widths = (0.0, 1.0)  # plain, then the silhouette-aware mode
    for edges in widths:
        def image(p):
            return rtjax.render(rtjax.Scene(s, p), edges=edges)

        def image_c(c):
            return rtjax.render(scene.replace(centers=c), edges=edges)

        fwd = jax.jit(image)
        grad = jax.jit(jax.grad(lambda p: jnp.mean(image(p))))
        jac = jax.jit(jax.jacfwd(image_c))
        (c_f, t_f), (c_g, t_g) = timed([(fwd, (scene.params,)), (grad, (scene.params,))], runs=args.runs)
        base = base or t_f
        ((c_j, t_j),) = timed([(jac, (scene.params.centers,))], runs=max(1, args.runs // 2))
        mode = "silhouette-aware (edges=1)" if edges else "plain"
        rows.append((mode, c_f, t_f, c_g, t_g, c_j, t_j, []))
    # memory analysed after every timing, so that no other program's compile comes between
    # the two modes' timings
    for edges, row in zip(widths, rows):
        for depth in args.depths:
            def loss(p, depth=depth, edges=edges):
                return jnp.mean(rtjax.render(rtjax.Scene(s, p), edges=edges, depth=depth))

            analysis = jax.jit(jax.grad(loss)).lower(scene.params).compile().memory_analysis()
            row[-1].append((depth, analysis.temp_size_in_bytes))
    print(f"{s.width}x{s.height}, depth {s.default_depth}, float32, median of {args.runs} runs after compile, {jax.devices()[0].platform}")
    print(f"{'mode':28s} {'forward':>18s} {'reverse grad':>22s} {'jacfwd (24 centres)':>24s}")
    for mode, c_f, t_f, c_g, t_g, c_j, t_j, _ in rows:
        print(f"{mode:28s} {t_f*1e3:7.1f} ms ({t_f/base:4.2f}x) {t_g*1e3:9.1f} ms ({t_g/base:5.2f}x) {t_j*1e3:10.1f} ms ({t_j/base:6.2f}x)")
    print("reverse / forward of the same mode:", "; ".join(f"{m}: {t_g/t_f:.1f}x" for m, _, t_f, _, t_g, *_ in rows))
    print("compile (s):", "; ".join(f"{m}: forward {c_f:.1f}, grad {c_g:.1f}, jacfwd {c_j:.1f}" for m, c_f, _, c_g, _, c_j, _, _ in rows))
    for mode, *_, memory in rows:
        if memory:
            print(f"gradient memory, {mode}:", ", ".join(f"depth {d} {b / 2**20:.1f} MiB" for d, b in memory))


if __name__ == "__main__":
    main()
