"""rtjax: a differentiable, jit-compiled JAX Whitted ray tracer for sphere scene decks.

Call `rtjax.tune_cpu()` before any JAX computation for the faster CPU code generator
(`rtjax.xla`); the `rtjax` command does.
"""

from .atomic import atomic_path as atomic_path, atomic_write as atomic_write
from .batch import (device_mesh as device_mesh, init_distributed as init_distributed, render_batch as render_batch,
                    render_frames as render_frames, render_sharded as render_sharded, stack_params as stack_params)
from .camera import image_height as image_height
from .deck import Deck as Deck, Frame as Frame, format_deck as format_deck, load_deck as load_deck, parse_deck as parse_deck, save_deck as save_deck
from .edges import EdgeSamples as EdgeSamples
from .errors import DeckError as DeckError, ImageError as ImageError, RtjaxError as RtjaxError
from .images import load_image as load_image, save_image as save_image, to_uint8 as to_uint8
from .render import edge_samples as edge_samples, render as render, render_samples as render_samples
from .scene import DEFAULT_DEPTH as DEFAULT_DEPTH, Params as Params, Scene as Scene, Structure as Structure
from .xla import tune_cpu as tune_cpu, use_compilation_cache as use_compilation_cache

__version__ = "0.1.0"
