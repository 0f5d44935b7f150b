"""Errors that the command line reports as one clean line (never a traceback)."""

from __future__ import annotations


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
