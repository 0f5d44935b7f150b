"""Errors that the command line reports as one clean line (never a traceback)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator


def shown(token: str) -> str:
    """A token as it reads in a one-line message: as is if printable, else escaped."""
    return token if token.isprintable() else repr(token)[1:-1]


class RtjaxError(Exception):
    """Base class: bad input a user can fix (a deck, an image file, an option)."""


class DeckError(RtjaxError):
    """A deck that does not parse or breaks a rule; the message reads `file:line: ...`."""

    def __init__(self, file: str, line: int | None, message: str):
        self.file = file
        self.line = line
        self.detail = message
        where = f"{file}:{line}" if line is not None else f"{file}"
        super().__init__(f"{where}: {message}")


class ImageError(RtjaxError):
    """An image file that cannot be read or written (truncated, bad header, unknown format)."""


@contextlib.contextmanager
def writing(path: str | os.PathLike, error: type[RtjaxError] = RtjaxError) -> Iterator[None]:
    """An OSError while writing `path` becomes one `error` naming it: what the commands
    print as a line, not a traceback naming a temporary file."""
    try:
        yield
    except OSError as e:
        raise error(f"{os.fspath(path)}: cannot write: {e.strerror or e}") from e
