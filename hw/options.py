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

from hw.depth import Intrinsics
from hw.errors import FrameError, FrameTimeout, UriError

__all__ = ["LapClock", "Pacer", "flag", "intrinsics_option", "positive"]

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


def intrinsics_option(backend: str, value: Any) -> Intrinsics | str | None:
    """An ``intrinsics`` option: an :class:`Intrinsics`, ``"fx,fy,cx,cy"`` text (checked to be
    four finite numbers, kept as text: the image size comes later) or None (also for "").
    :class:`UriError` otherwise."""
    if value is None or isinstance(value, Intrinsics):
        return value
    if isinstance(value, str):
        if not value.strip():
            return None
        try:
            Intrinsics.parse(value, 100_000, 100_000)  # the numbers alone: any image size
        except FrameError:
            raise UriError(f"{backend} option intrinsics={value!r}: expected four numbers "
                           "'fx,fy,cx,cy' in pixels, e.g. '525,525,319.5,239.5'") from None
        return value
    raise UriError(f"{backend} option intrinsics={value!r}: expected an Intrinsics or "
                   "'fx,fy,cx,cy' text")


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


class LapClock:
    """The timestamps of a looped recording: each lap after the first is shifted by the first
    lap's span and one frame period, so time keeps increasing.  ``lap`` counts laps,
    ``lap_frames`` the frames of this one."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Back to the first lap (a source opened again)."""
        self.lap = self.lap_frames = self._first_lap_frames = 0
        self._first = self._last = 0

    def next_lap(self) -> None:
        """The recording starts again."""
        if self.lap == 0:
            self._first_lap_frames = self.lap_frames
        self.lap += 1
        self.lap_frames = 0

    def stamp(self, recorded_us: int) -> int:
        """A frame recorded at ``recorded_us`` -> its timestamp in this lap, µs."""
        if self.lap == 0:
            if self.lap_frames == 0:
                self._first = recorded_us
            self._last = recorded_us
        self.lap_frames += 1
        if self.lap == 0:
            return recorded_us
        span = self._last - self._first
        frames = self._first_lap_frames
        period = span // (frames - 1) if frames > 1 else 1_000_000 // 30
        return recorded_us + self.lap * (span + max(period, 1))
