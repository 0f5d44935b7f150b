"""rtjax: a differentiable, jit-compiled JAX Whitted ray tracer for sphere scene decks."""

import os as _os


def _tune_xla_cpu() -> None:
    """Turn off XLA's new CPU fusion emitters unless the user chose: on this renderer
    they measured about 2× slower to run and 1.5× slower to compile (forward and
    derivatives, see README "Speed"). XLA reads the flag when JAX first starts its
    backend, so it takes effect if rtjax is imported before any JAX computation ran.
    Set RTJAX_KEEP_XLA_FLAGS=1 to leave XLA_FLAGS alone."""
    flags = _os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags and not _os.environ.get("RTJAX_KEEP_XLA_FLAGS"):
        _os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_use_fusion_emitters=false").strip()


_tune_xla_cpu()

from .deck import Deck as Deck, Frame as Frame, format_deck as format_deck, load_deck as load_deck, parse_deck as parse_deck, save_deck as save_deck
from .atomic import atomic_path as atomic_path, atomic_write as atomic_write
from .camera import image_height as image_height
from .errors import DeckError as DeckError, ImageError as ImageError, RtjaxError as RtjaxError
from .images import load_image as load_image, save_image as save_image, to_uint8 as to_uint8
from .render import EdgeSamples as EdgeSamples, render as render, render_samples as render_samples
from .batch import (device_mesh as device_mesh, init_distributed as init_distributed, render_batch as render_batch,
                    render_frames as render_frames, render_sharded as render_sharded, stack_params as stack_params)
from .scene import DEFAULT_DEPTH as DEFAULT_DEPTH, Params as Params, Scene as Scene, Structure as Structure

__version__ = "0.1.0"
