"""Fitting's errors: bad input a user can fix, reported like the renderer's (one line, exit 2)."""

from __future__ import annotations

import rtjax


class FitError(rtjax.RtjaxError):
    """A fit that cannot start: unknown family or solver, target of the wrong aspect, …"""
