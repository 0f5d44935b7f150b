"""Image files by extension: Sun raster through our codec, everything else through OpenImageIO.

Images in memory are (H, W, 3) RGB in 0..255: float32 when loaded (textures), uint8
when saved (renders; DECK.md §3 "clamp to [0, 255] and round to the nearest integer").
Every write is atomic, and every failure is an ImageError naming the file.
"""

from __future__ import annotations

import os

import numpy as np

from rtjax.atomic import atomic_path
from rtjax.errors import ImageError, writing
from rtjax.sunraster import SUN_MAGIC, is_sunraster_path, read_sunraster, write_sunraster

__all__ = ["FLOAT_EXTENSIONS", "check_writable", "load_image", "load_image_uint8", "save_image", "to_uint8"]

# Formats whose pixels are floats: written as value/255 so a round trip keeps the levels.
FLOAT_EXTENSIONS = (".exr", ".hdr", ".rgbe", ".pfm")


def to_uint8(image: object) -> np.ndarray:
    """(H, W, 3) values in 0..255 (numpy or JAX, any dtype) → uint8, clamped and rounded.

    Rounding is half up, floor(x + 0.5), so 0.5 → 1 and 254.5 → 255. uint8 input
    passes through unchanged. Non-finite values and other shapes are an ImageError.
    """
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ImageError(f"image has shape {arr.shape}; expected (height, width, 3)")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise ImageError(f"image has dtype {arr.dtype}; expected numbers")
    values = arr.astype(np.float64)
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        raise ImageError(f"image has {bad} non-finite values")
    return np.floor(np.clip(values, 0.0, 255.0) + 0.5).astype(np.uint8)


def check_writable(path: str | os.PathLike) -> None:
    """Raise ImageError now if no writer handles `path`'s extension (before any rendering)."""
    name = os.fspath(path)
    if is_sunraster_path(name):
        return
    import OpenImageIO as oiio

    if oiio.ImageOutput.create(name) is None:
        raise ImageError(f"{name}: no image format for this extension ({_oiio_message(oiio.geterror())})")


def save_image(path: str | os.PathLike, image: object, *, assignment_order: bool = False) -> None:
    """Write `image` (see to_uint8) to `path`, the format chosen by the extension.

    Sun raster extensions use our codec (`assignment_order` as in sunraster); any other
    goes to OpenImageIO (PNG, TIFF, JPEG, EXR, ...). Float formats (EXR, HDR) get
    value/255. The file is either complete or untouched, never half-written.
    """
    name = os.fspath(path)
    pixels = to_uint8(image)
    if is_sunraster_path(name):
        write_sunraster(name, pixels, assignment_order=assignment_order)
        return
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(name)
    if out is None:
        raise ImageError(f"{name}: cannot write: {_oiio_message(oiio.geterror())}")
    height, width = pixels.shape[:2]
    if name.lower().endswith(FLOAT_EXTENSIONS):
        spec, data = oiio.ImageSpec(width, height, 3, "float"), pixels.astype(np.float32) / np.float32(255)
    else:
        spec, data = oiio.ImageSpec(width, height, 3, "uint8"), pixels
    with writing(name, ImageError), atomic_path(name) as tmp:
        try:
            if not out.open(tmp, spec):
                raise ImageError(f"{name}: cannot write: {_oiio_message(out.geterror())}")
            if not out.write_image(data):
                raise ImageError(f"{name}: cannot write: {_oiio_message(out.geterror())}")
        finally:
            closed = out.close()
        if not closed:
            raise ImageError(f"{name}: cannot write: {_oiio_message(out.geterror())}")


def load_image(path: str | os.PathLike, *, assignment_order: bool = False) -> np.ndarray:
    """Read an image as (H, W, 3) float32 RGB in 0..255.

    Sun raster (by extension or by its magic number) uses our codec; anything else
    OpenImageIO: 8-bit as is, 16-bit / 257, float formats × 255 (clamped to 0..255).
    Greyscale is expanded to three channels; alpha and extra channels are dropped
    (colours as stored, not premultiplied by alpha).
    """
    return _load(path, assignment_order).astype(np.float32)


def load_image_uint8(path: str | os.PathLike, *, assignment_order: bool = False) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 RGB (float formats rounded as in to_uint8)."""
    return to_uint8(_load(path, assignment_order))


def _load(path: str | os.PathLike, assignment_order: bool) -> np.ndarray:
    """(H, W, 3) uint8 for 8-bit files, float32 in 0..255 for deeper ones."""
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            head = f.read(4)
    except (OSError, ValueError) as e:  # ValueError: a name with a NUL byte
        raise ImageError(f"{name}: cannot read: {getattr(e, 'strerror', None) or e}") from e
    if is_sunraster_path(name) or head == SUN_MAGIC.to_bytes(4, "big"):
        return read_sunraster(name, assignment_order=assignment_order)
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # colours as stored, not premultiplied by alpha
    inp = oiio.ImageInput.open(name, config)
    if inp is None:
        raise ImageError(f"{name}: cannot read: {_oiio_message(oiio.geterror())}")
    try:
        spec = inp.spec()
        base = spec.format.basetype
        kind = "uint8" if base == oiio.UINT8 else "uint16" if base == oiio.UINT16 else "float"
        pixels = inp.read_image(0, 0, 0, spec.nchannels, kind)
        if pixels is None:
            raise ImageError(f"{name}: cannot read: {_oiio_message(inp.geterror())}")
    finally:
        inp.close()
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if pixels.ndim != 3 or pixels.shape[0] < 1 or pixels.shape[1] < 1:
        raise ImageError(f"{name}: cannot read: unexpected pixel array shape {pixels.shape}")
    pixels = pixels[:, :, :3] if pixels.shape[2] >= 3 else np.repeat(pixels[:, :, :1], 3, axis=2)
    if kind == "uint8":
        return np.ascontiguousarray(pixels)
    values = pixels.astype(np.float32) / np.float32(257) if kind == "uint16" else pixels.astype(np.float32) * np.float32(255)
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        raise ImageError(f"{name}: image has {bad} non-finite values")
    return np.clip(values, 0, 255)


def _oiio_message(message: str) -> str:
    """OpenImageIO's (possibly multi-line) error text as one line."""
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    return "; ".join(lines) or "OpenImageIO gave no reason"
