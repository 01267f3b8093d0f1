"""One exponential back-off for everything that reconnects (camera, reader, serial port).

    wait = Backoff(0.5, 10.0)
    delay = wait.next()      # 0.5, then 1, 2, 4, 8, 10, 10, ...
    wait.reset()             # after success: the next failure waits the first delay again
"""

from __future__ import annotations

from hw.errors import ArgumentError

__all__ = ["Backoff"]


class Backoff:
    """Delays that double from ``first`` to at most ``cap`` seconds.  ``current`` is the delay
    the next :meth:`next` returns.  Not thread-safe: one owner."""

    def __init__(self, first: float, cap: float) -> None:
        if not 0 < first <= cap:
            raise ArgumentError(f"Backoff({first!r}, {cap!r}): needs 0 < first <= cap (seconds)")
        self.first, self.cap = float(first), float(cap)
        self.current = self.first

    def next(self) -> float:
        """The delay to wait now (seconds); the one after it doubles, up to the cap."""
        delay = self.current
        self.current = min(self.current * 2.0, self.cap)
        return delay

    def reset(self) -> None:
        """Start again from the first delay."""
        self.current = self.first

    def __repr__(self) -> str:
        return f"Backoff({self.first:g}, {self.cap:g}; next {self.current:g} s)"
