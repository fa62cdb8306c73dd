"""Progress of long numeric work: an optional callback ``progress(fraction, message)``.

Numeric code never prints: it reports through this callback (the CLI draws a bar, the file bridge
writes ``PROGRESS`` lines, Fiji its status bar) and logs through :mod:`logging`.
"""
from __future__ import annotations

from typing import Callable, Optional

#: A progress callback: fraction in [0, 1] and a short message.
Progress = Optional[Callable[[float, str], None]]


def report(progress: Progress, fraction: float, message: str) -> None:
    """Call ``progress`` if given."""
    if progress is not None:
        progress(float(min(max(fraction, 0.0), 1.0)), message)


def sub_progress(progress: Progress, start: float, stop: float) -> Progress:
    """A progress callback for a sub-step that covers ``[start, stop]`` of ``progress``."""
    if progress is None:
        return None
    return lambda fraction, message: progress(start + (stop - start) * fraction, message)
