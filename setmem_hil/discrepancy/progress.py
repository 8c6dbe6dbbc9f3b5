"""What the discrepancy workflow starts next, for a display: ``progress(text)`` (on real data the
workflow takes minutes, each bound-inflation and interval trial an identification)."""

from __future__ import annotations

from typing import Callable

__all__ = ["Progress", "say"]

Progress = Callable[[str], None]
"""``progress(text)``: what the workflow starts next (a display's line)."""


def say(progress: Progress | None, text: str) -> None:
    """``progress(text)``, or nothing without a display."""
    if progress is not None:
        progress(text)
