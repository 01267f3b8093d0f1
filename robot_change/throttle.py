"""Log lines that would repeat (a broker that stays down, a queue that stays full) at most once
per period, saying how many were held back.

    throttled = Throttled(logging.getLogger(__name__), every=10.0)
    throttled("busy", logging.WARNING, "%s refused: busy", name)
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

__all__ = ["Throttled"]


class Throttled:
    """``self(key, level, fmt, *args)`` logs to ``log`` unless the same ``key`` was logged less
    than ``every`` seconds ago; the next line that passes says how many were held.  Thread-safe."""

    def __init__(self, log: logging.Logger, every: float = 10.0) -> None:
        self.log = log
        self.every = every
        self._last: dict[str, float] = {}
        self._held: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def __call__(self, key: str, level: int, fmt: str, *args: Any) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.every:
                self._held[key] += 1
                return
            held, self._held[key] = self._held[key], 0
            self._last[key] = now
        self.log.log(level, fmt + (f" ({held} more like it in the last {now - last:.0f} s)"
                                   if held and last is not None else ""), *args)

    def forget(self, key: str) -> None:
        """The condition ended: the next line with ``key`` is logged at once."""
        with self._lock:
            self._last.pop(key, None)
            self._held.pop(key, None)
