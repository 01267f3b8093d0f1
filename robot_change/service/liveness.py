"""Is every part the base relies on making real progress?  (the watchdog's question)

A thread that is alive is not a thread that works: a detector stuck in a kernel, a check stuck
on the control thread or a camera read that never returns leave every thread alive while
nothing is watched.  :class:`Progress` keeps, per part, when it last made progress, and the
units of work in flight (a WATCH check, a CHECK, a capture) with when each began.  A part is
*stalled* when it has not made progress, or a unit of work has not ended, within ``bound_s``
(half of systemd's ``WatchdogSec``: docs/deployment.md).

    progress = Progress(5.0)
    progress.beat("link")                        # every turn of a loop
    token = progress.begin("detector", "WATCH office: frame 812")
    ...
    progress.end(token)
    progress.stalled()                           # "" or what stalled, for how long

Thread-safe; the clock is ``time.monotonic`` (injectable for tests).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable

from robot_change import validate

__all__ = ["Progress"]


class Progress:
    """Progress stamps of named parts and the units of work in flight.

    ``bound_s``: the longest a part may go without progress, and a unit of work may take.
    ``bounds``: per-part exceptions (e.g. the camera: its read timeout and a margin).
    """

    def __init__(self, bound_s: float, bounds: dict[str, float] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.bound_s = validate.positive("Progress", "bound_s", bound_s, unit=" seconds")
        self._bounds = dict(bounds or {})
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: dict[str, float] = {}
        self._work: dict[int, tuple[str, str, float, float | None]] = {}
        self._ids = itertools.count(1)

    def bound(self, part: str) -> float:
        """Seconds ``part`` may go without progress."""
        return self._bounds.get(part, self.bound_s)

    def set_bound(self, part: str, seconds: float) -> None:
        """``part`` may go ``seconds`` without progress (e.g. the WATCH checks: the check
        interval plus the bound)."""
        with self._lock:
            self._bounds[part] = float(seconds)

    def beat(self, part: str) -> None:
        """``part`` made progress now (and is watched from now on)."""
        now = self._clock()
        with self._lock:
            self._seen[part] = now

    def watches(self, part: str) -> bool:
        """Is ``part`` watched (has it beaten since it was last forgotten)?"""
        with self._lock:
            return part in self._seen

    def forget(self, part: str) -> None:
        """Stop watching ``part`` (it has nothing to do, e.g. a watch that ended)."""
        with self._lock:
            self._seen.pop(part, None)

    def begin(self, part: str, what: str, bound_s: float | None = None) -> int:
        """A unit of work of ``part`` starts; it must :meth:`end` within ``bound_s`` (default:
        the part's bound).  Returns its token."""
        now = self._clock()
        with self._lock:
            token = next(self._ids)
            self._work[token] = (part, what, now, bound_s)
            return token

    def end(self, token: int) -> None:
        """The unit of work ``token`` is over (done, failed or cancelled): progress of its
        part, if the part is watched (a part of units of work alone is not required to beat)."""
        now = self._clock()
        with self._lock:
            entry = self._work.pop(token, None)
            if entry is not None and entry[0] in self._seen:
                self._seen[entry[0]] = now

    def stalled(self) -> str:
        """What stalled, for how long ("" when every part is making progress): the unit of
        work in flight longest past its bound if any, else the part silent longest past its
        (a part with work in flight is judged by its work)."""
        now = self._clock()
        with self._lock:
            work = [(now - t0 - (bound if bound is not None else
                                 self._bounds.get(part, self.bound_s)),
                     f"{part}: {what} has not finished after {now - t0:.1f} s")
                    for part, what, t0, bound in self._work.values()]
            busy = {part for part, _what, _t0, _bound in self._work.values()}
            silent = [(now - seen - self._bounds.get(part, self.bound_s),
                       f"{part}: no progress for {now - seen:.1f} s")
                      for part, seen in self._seen.items() if part not in busy]
        for entries in (work, silent):
            over = [entry for entry in entries if entry[0] > 0]
            if over:
                return max(over)[1]
        return ""
