"""rtjax: a differentiable, jit-compiled JAX Whitted ray tracer for sphere scene decks."""

from .deck import Deck as Deck, Frame as Frame, format_deck as format_deck, load_deck as load_deck, parse_deck as parse_deck, save_deck as save_deck
from .camera import image_height as image_height
from .errors import DeckError as DeckError, ImageError as ImageError, RtjaxError as RtjaxError
from .images import load_image as load_image, save_image as save_image, to_uint8 as to_uint8
from .render import render as render
from .scene import DEFAULT_DEPTH as DEFAULT_DEPTH, Params as Params, Scene as Scene, Structure as Structure

__version__ = "0.1.0"
