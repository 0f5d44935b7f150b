"""The bench's derivative costs: the reverse gradient of the mean image, the forward
Jacobian in the centres and one Levenberg–Marquardt step of optimistix on the image
residual, each timed like a render and given as a ratio to the plain forward render
timed in the same run at the same size.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from .config import Config
from .measure import timed
from .settings import scaled


def measure_derivatives(scene, cfg: Config, log: Callable[[str], None]) -> dict:
    """Time the forward render and its derivatives at `cfg.derivative_scale`.

    **Arguments:**

    - `scene`: the scene (float32, its own depth).
    - `cfg`: `derivative_scale`, `repeats` and `lm_step`.
    - `log`: called with each progress line.

    **Returns:** a dict with `width`, `height`, `n_params_centers`, and `timed`'s figures
    under `forward`, `grad`, `jacfwd_centers` and (with `cfg.lm_step`) `lm_step`, each
    derivative's with its `ratio` to the forward render's median.
    """
    import jax

    import rtjax

    sc = scaled(scene, cfg.derivative_scale)
    st, p0 = sc.structure, sc.params
    log(f"derivatives at {st.width}×{st.height} (float32, depth {st.default_depth}) …")

    def image(p):
        return rtjax.render(rtjax.Scene(st, p))

    fwd = jax.jit(image)
    grad = jax.jit(jax.grad(lambda p: image(p).mean()))
    jac = jax.jit(jax.jacfwd(lambda c: image(replace_params(p0, centers=c))))
    result = {"width": st.width, "height": st.height, "n_params_centers": int(p0.centers.size)}
    for name, fn, arg in (("forward", fwd, p0), ("grad", grad, p0), ("jacfwd_centers", jac, p0.centers)):
        m = timed(lambda fn=fn, arg=arg: fn(arg), cfg.repeats)
        m.pop("out")
        result[name] = m
        log(f"  {name:15s} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    if cfg.lm_step:
        step = lm_step(p0, image)
        m = timed(step, cfg.repeats)
        m.pop("out")
        result["lm_step"] = m
        log(f"  {'lm_step':15s} {1e3 * m['median_s']:9.1f} ms  compile {m['compile_s']:5.1f} s")
    base = result["forward"]["median_s"]
    for name in ("grad", "jacfwd_centers", "lm_step"):
        if name in result:
            result[name]["ratio"] = result[name]["median_s"] / base
    return result


def replace_params(p, **changes):
    """`rtjax.Params` `p` with some fields replaced as given (no casting: traced values pass through)."""
    fields = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    fields.update(changes)
    return type(p)(**fields)


def lm_step(p0, image: Callable) -> Callable[[], object]:
    """One Levenberg–Marquardt step of optimistix on the centres, stepped by hand.

    **Arguments:**

    - `p0`: the parameters; the step starts from their centres.
    - `image`: params → rendered image.

    **Returns:** a zero-argument call (for `timed`) taking the step from the initial
    solver state toward the image of the scene with every centre moved by 0.5, and
    returning the new centres. The state is initialised (and compiled) here, so the call
    times the step alone.
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    target = jax.lax.stop_gradient(image(replace_params(p0, centers=p0.centers + 0.5)))
    # the solver's coordinates in the default float type (float64 with x64: optimistix
    # builds its damped system in it), the render in the scene's own (as `fitting` does)
    y0 = jnp.asarray(p0.centers, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)

    def residuals(c, args):
        r = image(replace_params(p0, centers=c.astype(p0.centers.dtype))) - args
        return r.ravel().astype(y0.dtype), None

    solver = optx.LevenbergMarquardt(rtol=1e-5, atol=1e-7)

    @eqx.filter_jit
    def init(y, args):
        f_struct, aux_struct = jax.eval_shape(lambda: residuals(y, args))
        return solver.init(residuals, y, args, {}, f_struct, aux_struct, frozenset())

    @eqx.filter_jit
    def step(y, state, args):
        y, state, _ = solver.step(residuals, y, args, {}, state, frozenset())
        return y, state

    state = init(y0, target)
    jax.block_until_ready(state)
    return lambda: step(y0, state, target)[0]
