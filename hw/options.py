"""What every depth backend reads the same way: the options of a URI (``?rate=30&loop=1``) and
delivery paced at a rate, as a camera delivers frames.

    loop = flag("images", "loop", "1")                      # True; "" (a bare ?loop) too
    rate = positive("images", "rate", "30", "frames per second")
    pacer = Pacer(30.0); pacer.wait(timeout, "images:dir")  # before handing out a frame
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hw.errors import FrameTimeout, UriError

__all__ = ["Pacer", "flag", "positive"]

_TRUE = {"1", "true", "yes", "on", ""}
_FALSE = {"0", "false", "no", "off"}


def flag(backend: str, name: str, value: Any) -> bool:
    """An on/off option: a bool, 0 / 1, or 1/0, true/false, yes/no, on/off (any case); a bare
    ``?name`` (empty string) is on.  :class:`UriError` otherwise."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
        return value.strip().lower() in _TRUE
    raise UriError(f"{backend} option {name}={value!r}: expected 1 or 0 (true/false, yes/no)")


def positive(backend: str, name: str, value: Any, meaning: str) -> float:
    """A finite number > 0 (a string of one too); :class:`UriError` naming ``meaning``
    otherwise."""
    try:
        number = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        number = math.nan
    if not (math.isfinite(number) and number > 0):
        raise UriError(f"{backend} option {name}={value!r}: expected a number > 0 ({meaning})")
    return number


class Pacer:
    """Hands out frames no faster than ``rate`` per second (None: as fast as asked).  A late
    reader gets the next frame at once, not a burst of the ones it missed."""

    def __init__(self, rate: float | None) -> None:
        self.rate = rate
        self._due: float | None = None

    def reset(self) -> None:
        """The next frame is due at once (a source opened again)."""
        self._due = None

    def wait(self, timeout: float | None, what: str) -> None:
        """Sleep until the next frame is due; when that is more than ``timeout`` s away, sleep
        ``timeout`` and raise :class:`FrameTimeout` (``what`` names the source)."""
        if self.rate is None:
            return
        now = time.monotonic()
        due = now if self._due is None else self._due
        wait = due - now
        if wait > 0:
            if timeout is not None and wait > timeout:
                time.sleep(max(float(timeout), 0.0))
                raise FrameTimeout(f"{what}: no frame within {timeout} s; the source is paced "
                                   f"at {self.rate:g} fps (lower the rate option or raise the "
                                   "read timeout)")
            time.sleep(wait)
        self._due = max(due, now) + 1.0 / self.rate
