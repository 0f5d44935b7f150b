"""The `rtjax` command: `render` decks (and, wired to `fitting`, `fit`; `bench`).

Bad input (a deck, an image, an option) is one line on stderr, `file:line: ...`,
exit code 2, and nothing written; the command line is the only place that sees
both `rtjax` and `fitting`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

from .errors import DeckError, RtjaxError, shown
from .render import EDGE_CHUNK_MIN, MAX_EDGE_WIDTH, MAX_SUBDIVIDE, SMALL_IMAGE_SUBDIVIDE
from .xla import tune_cpu, use_compilation_cache

#: Image sides beyond this need --allow-large (a typo like `size 40000` would take minutes and GBs).
MAX_SIDE = 16384


def _int_at_least(text: str, low: int, expected: str, expected_bound: str) -> int:
    """`text` as a whole number ≥ `low` (an argparse type); the errors say "expected
    `expected`" when it is not a whole number, "expected `expected_bound`" when too small."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, found {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected {expected_bound}, found {value}")
    return value


def _positive_int(text: str) -> int:
    return _int_at_least(text, 1, "a whole number", "a number ≥ 1")


def _depth(text: str) -> int:
    return _int_at_least(text, 0, "a whole number ≥ 0", "a whole number ≥ 0")


def _halvings(text: str) -> int:
    value = _int_at_least(text, 0, "a whole number", "a whole number ≥ 0")
    if value > MAX_SUBDIVIDE:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_SUBDIVIDE} halvings, found {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number > 0, found {text}")
    return value


def _edge_width(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of pixels, found {text!r}") from None
    if not (0 <= value <= MAX_EDGE_WIDTH):
        raise argparse.ArgumentTypeError(f"expected a width in [0, {MAX_EDGE_WIDTH:g}] pixels, found {text}")
    return value


def resolve_output(outdir: str, name: str, *, allow_any: bool) -> str:
    """Where a `rend` name goes: inside `outdir` unless any path is explicitly allowed."""
    if os.path.isabs(name):
        if not allow_any:
            raise ValueError(f"rend: output path {name!r} is absolute; pass --allow-any-path to allow it")
        return name
    path = os.path.normpath(os.path.join(outdir, name))
    inside = os.path.commonpath([os.path.abspath(outdir), os.path.abspath(path)]) == os.path.abspath(outdir)
    if not inside and not allow_any:
        raise ValueError(f"rend: output path {name!r} leaves the output folder; pass --allow-any-path to allow it")
    return path


def _plan(deck, args) -> list[tuple[object, str]]:
    """Check every frame before rendering any: paths, formats, sizes. Nothing is written yet."""
    from .images import check_writable

    plan = []
    for frame in deck.frames:
        try:
            path = resolve_output(args.outdir, frame.output, allow_any=args.allow_any_path)
        except ValueError as e:
            raise DeckError(deck.path, frame.line, str(e)) from None
        try:
            check_writable(path)
        except RtjaxError as e:
            raise DeckError(deck.path, frame.line, f"rend: {e}") from None
        s = frame.scene.structure
        if max(s.width, s.height) > MAX_SIDE and not args.allow_large:
            raise DeckError(
                deck.path,
                frame.line,
                f"rend: the image would be {s.width}×{s.height}, beyond {MAX_SIDE} pixels a side; pass --allow-large to render it",
            )
        plan.append((frame, path))
    return plan


def _devices(text: str) -> int | str:
    if text.strip().lower() == "all":
        return "all"
    return _int_at_least(text, 1, "a number of devices or 'all'", "a number ≥ 1 or 'all'")


def _start_distributed(args) -> None:
    """--distributed: join a multi-host run (`rtjax.init_distributed`, configured by the
    environment: JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID, or what
    JAX detects of Slurm, Open MPI, Kubernetes, Cloud TPU) before anything touches JAX."""
    if getattr(args, "distributed", False):
        from .batch import init_distributed

        try:
            init_distributed()
        except (RuntimeError, ValueError) as e:
            raise RtjaxError(f"--distributed: {_one_line(e)[:300]}") from None


def cmd_render(args) -> int:
    from .deck import load_deck
    from .render import resolve_subdivide

    resolve_subdivide(args.edges, args.subdivide)  # before the deck is read: a usage error
    deck = load_deck(args.deck)
    if not deck.frames:
        raise DeckError(deck.path, None, "the deck has no rend line: nothing to render")
    plan = _plan(deck, args)
    if args.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    import jax

    from .batch import plan_batches, render_chunk, resolve_devices
    from .images import save_image, to_uint8

    n_devices = len(resolve_devices(args.devices))
    writer = jax.process_index() == 0  # several hosts: every process renders, the first one writes
    options = {"depth": args.depth, "spp": args.spp, "dtype": args.dtype, "edges": args.edges, "subdivide": args.subdivide,
               "devices": args.devices, "mode": args.batch_mode}
    # Frames sharing a structure render together (one batched call per chunk); frames are
    # still written and reported in deck order, each with its share of its call's time.
    scenes = [frame.scene for frame, _ in plan]
    chunks = plan_batches(scenes, n_devices, args.batch)
    chunk_of = {i: c for c, chunk in enumerate(chunks) for i in chunk}
    ready: dict[int, tuple[object, float]] = {}
    for i, (frame, path) in enumerate(plan):
        try:
            with _out_of_memory():
                if i not in ready:
                    chunk = chunks[chunk_of[i]]
                    start = time.perf_counter()
                    with args.interrupts.deferring():
                        images = render_chunk([scenes[j] for j in chunk], **options)
                        jax.block_until_ready(images)
                    share = (time.perf_counter() - start) / len(chunk)
                    ready.update({j: (image, share) for j, image in zip(chunk, images)})
                image, elapsed = ready.pop(i)
                # Clamp, round and refuse non-finite values before anything touches the disk.
                pixels = to_uint8(image)
                del image
                written = [path]
                if args.png and not path.lower().endswith(".png"):
                    written.append(os.path.splitext(path)[0] + ".png")
                if writer:
                    folder = os.path.dirname(path)
                    if folder:
                        os.makedirs(folder, exist_ok=True)
                    save_image(path, pixels, assignment_order=args.assignment_order)
                    if len(written) > 1:
                        save_image(written[1], pixels)
        except RtjaxError as e:
            raise DeckError(deck.path, frame.line, f"rend {shown(frame.output)}: {e}") from None
        except OSError as e:
            where = f"{e.filename}: " if e.filename else ""
            raise DeckError(deck.path, frame.line, f"rend {shown(frame.output)}: {where}{e.strerror or e}") from None
        s = frame.scene.structure
        if writer:
            print(f"{' + '.join(written)}  {s.width}x{s.height}  {elapsed:.2f} s", flush=True)
    return 0


def _int_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected whole numbers separated by commas, found {text!r}") from None


def _float_list(text: str) -> list[float]:
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, found {text!r}") from None
    if not values or any(not (0 < v <= MAX_EDGE_WIDTH) for v in values):
        raise argparse.ArgumentTypeError(f"expected edge widths in (0, {MAX_EDGE_WIDTH:g}] pixels, found {text!r}")
    return values


class _Progress:
    """A line when the fit starts (its first step waits for the trace and XLA's compile:
    up to a minute that would otherwise pass in silence), then one per iteration with the
    step's time and the time since the start; on a terminal, a bar that fills as the
    steps are used. Each iteration is a safe point for a signal (`Interrupts.check`)."""

    def __init__(self, max_steps: int, quiet: bool, interrupts: "Interrupts"):
        self.max_steps, self.quiet, self.tty = max_steps, quiet, sys.stdout.isatty()
        self.interrupts = interrupts

    def start(self, cache: str | None) -> None:
        if not self.quiet:
            kept = f"kept in {cache} for later runs" if cache else "not kept: RTJAX_CACHE=off"
            print(f"the first step waits while the fit's programs are traced and compiled (seconds to a minute; "
                  f"compiled programs {kept})", flush=True)

    def __call__(self, row: dict) -> None:
        self.interrupts.check()
        if self.quiet:
            return
        text = (f"step {row['step']:3d}  {row['width']:4d} px  loss {row['loss']:.4e}  "
                f"rms {row['rmse_levels']:.3g} levels  {row['seconds']:.2f} s  at {row['elapsed']:.0f} s")
        if "active" in row:  # a multi-start fit: the leading start, and how many are still going
            text += f"  start {row['start']}, {row['active']} going"
        if self.tty:
            done = int(30 * row["step"] / self.max_steps)
            print(f"\r[{'#' * done}{'.' * (30 - done)}] {text}", end="", flush=True)
        else:
            print(text, flush=True)

    def close(self) -> None:
        if self.tty and not self.quiet:
            print()


def cmd_fit(args) -> int:
    """`rtjax fit`: fit a deck's free parameters to a target image, write the results."""
    import fitting
    from fitting.objective import match_size, prepare_mask
    from fitting.report import add_to_report, save_outputs, summary_line, table_text

    from .deck import load_deck

    deck = load_deck(args.deck)
    if not deck.frames:
        raise DeckError(deck.path, None, "the deck has no rend line: nothing to fit")
    targets = args.target
    chosen = args.frames if args.frames is not None else [args.frame] if len(targets) == 1 else list(range(len(targets)))
    if len(chosen) != len(targets):
        raise RtjaxError(f"{len(targets)} targets for {len(chosen)} frames (--frames): give one target per frame")
    for k in chosen:
        if not 0 <= k < len(deck.frames):
            flag = "--frame " if args.frames is None and len(targets) == 1 else "frame "
            raise RtjaxError(f"{flag}{k}: the deck has {len(deck.frames)} frames (0..{len(deck.frames) - 1})")
    several_frames = len(chosen) > 1
    frame = deck.frames[chosen[0]]
    out = args.output or os.path.splitext(os.path.basename(args.deck))[0] + "_fitted.dat"
    outdir, stem = os.path.dirname(out) or ".", os.path.splitext(os.path.basename(out))[0]
    import jax

    if jax.process_index() == 0:  # several hosts: the first one writes
        _check_output_folder(outdir, "the fit's outputs")
    options = fitting.FitOptions(
        solver=args.solver,
        max_steps=args.max_steps,
        levels=args.levels if args.levels is None or len(args.levels) > 1 else args.levels[0],
        edges=args.edges,
        polish=args.polish or None,
        exact_polish=args.exact_polish,
        loss=args.loss,
        loss_scale=args.loss_scale,
        nuisance=args.nuisance.split(",") if args.nuisance else (),
        mask=args.mask,
        assignment_order=args.assignment_order,
        smooth=args.smooth,
        photo=args.photo,
    )
    progress = _Progress(args.max_steps, args.quiet or jax.process_index() != 0, args.interrupts)
    several = args.starts > 1 or args.devices != 1
    if several and (several_frames or args.smooth):
        raise RtjaxError("--starts and --devices fit one frame without --smooth: give one target")
    scenes = [deck.frames[k].scene for k in chosen]
    # what can be refused is refused before the line that says the first step waits;
    # the fit is given what was read (targets, the mask's weights), not the files again
    images = [fitting.load_target(t, assignment_order=args.assignment_order) for t in targets]
    mask = args.mask
    for scene, image in zip(scenes, images):
        match_size(scene, image)
        mask = None if mask is None else prepare_mask(mask, *image.shape[:2])
    options = dataclasses.replace(options, mask=mask)
    fitting.Selection(frame.scene, args.free, args.spheres)
    progress.start(args.cache)
    height, width = images[0].shape[:2]
    try:
        with args.interrupts.deferring(), _out_of_memory(f"fitting at {width}×{height} pixels: "):
            if several:
                multi = fitting.fit_multistart(frame.scene, images[0], args.free, starts=args.starts, seed=args.seed,
                                               spread=args.spread, devices=args.devices, spheres=args.spheres,
                                               options=options, callback=progress)
                result = multi.best
            else:
                result = fitting.fit(scenes if several_frames else frame.scene, images if several_frames else images[0],
                                     args.free, spheres=args.spheres, options=options, callback=progress)
    finally:
        progress.close()
    if jax.process_index() != 0:  # several hosts: the first one writes and reports
        return 0 if result.ok else 1
    fitted = fitting.fitted_scenes(scenes, result.selection, result.y) if several_frames else None
    print(table_text(result))  # first: should the outputs fail to be written, the fitted values are on screen
    if several:
        print(summary_line(multi))
    with _writing(outdir, "the fit's outputs", "the fitted values are printed above"):
        paths = save_outputs(result, outdir, stem, args.deck, ", ".join(targets), image_name=f"{stem}.sunimg", frames=fitted)
        if several:
            add_to_report(paths["report"], multi)
    print("wrote " + ", ".join(paths[k] for k in ("deck", "image", "report", "plot")))
    return 0 if result.ok else 1


def _check_output_folder(folder: str, what: str) -> None:
    """Refuse, before a fit or a benchmark starts, an output folder that cannot be made or
    written (they run for minutes; `what` they write must not be lost to a mistyped
    `-o`). Creates nothing: the outputs make the folder when they are written."""
    path = os.path.abspath(folder)
    while not os.path.lexists(path) and os.path.dirname(path) != path:
        path = os.path.dirname(path)
    if not os.path.isdir(path):
        raise RtjaxError(f"{folder}: cannot write {what} there: {path} is not a folder")
    if not os.access(path, os.W_OK | os.X_OK):
        raise RtjaxError(f"{folder}: cannot write {what} there: {path} is not writable")


@contextlib.contextmanager
def _out_of_memory(what: str = "") -> Iterator[None]:
    """Running out of memory (Python's MemoryError, or XLA's allocator: a RuntimeError
    saying RESOURCE_EXHAUSTED) becomes one line, `what` then "out of memory (XLA's
    words)": too large a job for the machine is the input's size, not a bug."""
    try:
        yield
    except MemoryError:
        raise RtjaxError(f"{what}out of memory") from None
    except RuntimeError as e:
        if "RESOURCE_EXHAUSTED" not in str(e):
            raise
        raise RtjaxError(f"{what}out of memory ({_one_line(e)[:200]})") from None


@contextlib.contextmanager
def _writing(folder: str, what: str, shown: str) -> Iterator[None]:
    """An OSError while writing `what` into `folder` becomes one line naming the file and
    saying where the results are (`shown`: they were printed before the write)."""
    try:
        yield
    except OSError as e:
        raise RtjaxError(f"{e.filename or folder}: cannot write {what}: {e.strerror or e} ({shown})") from None


def cmd_bench(args) -> int:
    """`rtjax bench`: the speed/accuracy table, derivative costs and plots of a deck."""
    import jax

    jax.config.update("jax_enable_x64", True)  # the reference renders in float64
    from .bench import main_bench
    from .deck import load_deck

    deck = load_deck(args.deck)  # a bad deck is one line before anything is measured
    if not deck.frames:
        raise DeckError(deck.path, None, "the deck has no rend line: nothing to measure")
    _check_output_folder(args.outdir, "the benchmark's outputs")
    with _writing(args.outdir, "the benchmark's outputs", "its table is printed above"), _out_of_memory("rtjax bench: "):
        main_bench(args.deck, quick=args.quick, scale=args.scale, outdir=args.outdir)
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr (no usage block), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {_one_line(message)}\n")


def _one_line(text: str) -> str:
    return " ".join(str(text).split("\n")).replace("\r", " ")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rtjax", description="A differentiable JAX ray tracer for sphere scene decks.")
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render every `rend` of a deck", description="Render every `rend` line of DECK.")
    r.add_argument("deck", help="the deck file (.dat)")
    r.add_argument("-o", "--outdir", default=".", help="folder for the `rend` files (default: the current folder)")
    r.add_argument("--depth", type=_depth, default=None, help="reflection/refraction depth (default: 10 with mirrors or glass, else 0)")
    r.add_argument("--spp", type=_positive_int, default=1, help="K for K×K samples per pixel (default 1)")
    r.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="arithmetic precision (default float32)")
    r.add_argument("--edges", type=_edge_width, default=0.0, metavar="WIDTH",
                   help="silhouette-aware (antialiased, edge-differentiable) mode with this edge width in pixels (default 0: off)")
    r.add_argument("--subdivide", type=_halvings, nargs="?", const=1, default=None, metavar="N",
                   help="with --edges: trace the pixels an edge may cross as 2^N x 2^N sub-boxes "
                        "(N = 1 without a value: 2x2; 2: 4x4; 3, 4: 4x4, then 2x2 or 4x4 in the sub-boxes an edge may cross; "
                        f"0: none; default: {SMALL_IMAGE_SUBDIVIDE} in images "
                        f"of at most {EDGE_CHUNK_MIN} pixels, else 0; see docs/EDGES.md)")
    r.add_argument("--png", action="store_true", help="also write a PNG preview beside each Sun raster file")
    r.add_argument("--assignment-order", action="store_true",
                   help="write Sun raster pixels R,G,B as the assignment's code did (standard viewers swap red and blue)")
    r.add_argument("--allow-any-path", action="store_true", help="allow `rend` paths that are absolute or leave OUTDIR")
    r.add_argument("--allow-large", action="store_true", help=f"allow images beyond {MAX_SIDE} pixels a side")
    r.add_argument("--devices", type=_devices, default=1, metavar="N|all",
                   help="shard each call's pixels (or frames) over N local devices, or all of them (default 1)")
    r.add_argument("--batch", type=_positive_int, default=None, metavar="N",
                   help="frames sharing a structure render N at a time in one batched call; the time printed per "
                        "frame is its call's time divided among its frames (default: as many as fit 2^21 samples "
                        "per device; 1: frame by frame)")
    r.add_argument("--batch-mode", choices=("auto", "vmap", "map"), default="auto",
                   help="a batched call's frames: vmap (all at once), map (one after another inside the call), "
                        "auto (default: map on a CPU, vmap on a GPU)")
    r.add_argument("--distributed", action="store_true",
                   help="join a multi-host run first (jax.distributed.initialize, configured by the environment); "
                        "every process renders, the first writes")
    r.set_defaults(run=cmd_render)

    f = sub.add_parser("fit", help="fit a deck's parameters to a target image",
                       description="Fit the free parameters of DECK's scene so that it renders like TARGET.")
    f.add_argument("deck", help="the deck whose scene is the starting point")
    f.add_argument("target", nargs="+", help="the target image: Sun raster (either byte order) or anything OpenImageIO "
                   "reads; several: one per frame (--frames; default: the deck's frames in order), fitted together")
    f.add_argument("--free", default="centers", help="parameter families to fit, e.g. centers,colors,ke (default centers)")
    f.add_argument("--spheres", type=_int_list, default=None, help="restrict per-sphere families to these spheres, e.g. 0,2,5")
    f.add_argument("--solver", choices=("lm", "gn", "dogleg", "bfgs"), default="lm", help="solver (default lm: Levenberg-Marquardt)")
    f.add_argument("-o", "--output", default=None, help="the fitted deck (default DECK_fitted.dat); image, report and plot go beside it")
    f.add_argument("--max-steps", type=_positive_int, default=30, help="iterations in all (default 30)")
    f.add_argument("--levels", type=_int_list, default=None, help="coarse-to-fine: a count of levels halving the width, or widths such as 50,100,400 (default: an eighth, a quarter, full)")
    f.add_argument("--edges", type=_float_list, default=None, help="edge width per level in pixels, e.g. 2,1,1 (default 1)")
    f.add_argument("--polish", type=float, default=1.0,
                   help="edge width in pixels of the full-size level (default 1; 0: no special full-size level)")
    f.add_argument("--exact-polish", action=argparse.BooleanOptionalAction, default=True,
                   help="match the full-size level at pixel centres, as rtjax render makes targets (default); "
                        "--no-exact-polish: a last box-filtered level --polish wide (then use e.g. 0.02), for antialiased targets")
    f.add_argument("--loss", choices=("l2", "huber", "cauchy"), default="cauchy", help="residual loss (default cauchy: robust)")
    f.add_argument("--loss-scale", type=_positive_float, default=10.0, help="robust loss scale in levels (default 10)")
    f.add_argument("--nuisance", default="", help="also fit a camera model for a photo-like target: gain,gamma,blur,chroma,order, or camera (all five: response, Gaussian blur in pixels, JPEG chroma blur, blur before/after the response)")
    f.add_argument("--photo", action="store_true",
                   help="the target is a photo (another renderer, a camera): fit a camera model and the scene's appearance "
                        "(colours, ambient, background, lights, an illumination field) with the geometry, and judge the "
                        "result (exit 1 with the cause where a parameter ran away, the residual explains nothing, or a "
                        "centre is undetermined); not with --nuisance")
    f.add_argument("--mask", default=None, help="an image whose dark pixels are ignored")
    f.add_argument("--frame", type=int, default=0, help="which rend frame of the deck to fit (default 0)")
    f.add_argument("--smooth", type=float, default=0.0, metavar="WEIGHT",
                   help="with --free textures: a smoothness prior on the texels, each neighbour pair's difference "
                        "weighing as WEIGHT pixels' (default 0: none; fills texels no view sees)")
    f.add_argument("--frames", type=_int_list, default=None,
                   help="the rend frames the targets show, e.g. 0,2,3 (default: one target, --frame; several, 0,1,...)")
    f.add_argument("--assignment-order", action="store_true", help="the target is a Sun raster file in the assignment's R,G,B order")
    f.add_argument("--quiet", action="store_true", help="no per-iteration progress")
    f.add_argument("--starts", type=_positive_int, default=1, metavar="K",
                   help="multi-start: K starts (the deck's and K-1 perturbed) solved in parallel, the best kept (default 1)")
    f.add_argument("--seed", type=int, default=0, help="seed of the multi-start perturbations (default 0)")
    f.add_argument("--spread", type=float, default=0.5,
                   help="multi-start perturbation scale in solver units (median radii for centres, logits for colours; default 0.5)")
    f.add_argument("--devices", type=_devices, default=1, metavar="N|all",
                   help="shard the starts over N local devices, or all of them (default 1: vmapped on one)")
    f.add_argument("--distributed", action="store_true", help="join a multi-host run first (jax.distributed.initialize)")
    f.set_defaults(run=cmd_fit)

    b = sub.add_parser("bench", help="measure speed against accuracy of each knob on a deck",
                       description="Measure each knob (dtype, depth, samples per pixel, edge width, image scale) on DECK's "
                                   "first frame against a float64 reference render; time derivatives and the NumPy reference; "
                                   "print a table, write bench_<deck>.json and a Pareto plot bench_<deck>.png.")
    b.add_argument("deck", help="the deck file (.dat); its first frame is measured")
    b.add_argument("--quick", action="store_true", help="smaller reference (8×8 samples), fewer settings, derivatives at ¼ size")
    b.add_argument("--scale", action="store_true",
                   help="also time random scenes of 8…1000 spheres, the deck at several widths, and gradient memory against depth")
    b.add_argument("-o", "--outdir", default=".", help="folder for the JSON and PNG files (default: the current folder)")
    b.set_defaults(run=cmd_bench)
    return parser


class Interrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP, raised like Ctrl-C so that temporary files are cleaned up."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


class Interrupts:
    """SIGINT, SIGTERM and SIGHUP while a command runs, raised as `Interrupted` (their
    default would kill the process on the spot, leaving a temporary file behind
    mid-write).

    Within `deferring()` (JAX computations) a signal is noted when it arrives and raised
    at the block's end or at a `check` inside it (a fit's iteration): raised at once, it
    could land in a callback from JAX's compiled code, which reports it as a traceback.
    What it waits for is the computation under way, which compiled code would not leave
    earlier anyway. Elsewhere (writing files) it is raised at once."""

    def __init__(self):
        self.deferred = False
        self.pending: int | None = None

    def _handler(self, signum, frame):
        if not self.deferred:
            raise Interrupted(signum)
        self.pending = signum

    def check(self) -> None:
        """Raise `Interrupted` for a signal noted since the command began."""
        if self.pending is not None:
            raise Interrupted(self.pending)

    @contextlib.contextmanager
    def deferring(self) -> Iterator[None]:
        """Signals within the block are raised at its end (or at a `check`)."""
        self.deferred = True
        try:
            yield
        finally:
            self.deferred = False
        self.check()

    @contextlib.contextmanager
    def installed(self) -> Iterator["Interrupts"]:
        """The handlers in place for the block (main thread only), the previous ones after."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        names = [n for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)]
        previous = {n: signal.signal(getattr(signal, n), self._handler) for n in names}
        try:
            yield self
        finally:
            for n, old in previous.items():
                signal.signal(getattr(signal, n), signal.SIG_DFL if old is None else old)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    with Interrupts().installed() as interrupts:
        args.interrupts = interrupts
        try:
            tune_cpu()  # before anything (a deck's arrays included) starts JAX
            _start_distributed(args)
            args.cache = use_compilation_cache()  # the folder, or None: what `rtjax fit` tells the user
            return args.run(args)
        except RtjaxError as e:
            print(_one_line(e), file=sys.stderr)
            return 2
        except KeyboardInterrupt as e:
            print("interrupted: no partial file was written", file=sys.stderr)
            return 128 + int(getattr(e, "signum", signal.SIGINT))


if __name__ == "__main__":
    sys.exit(main())
