"""Two parts of a check at once: the second on a short-lived thread of its own, the first on
the caller's (``ChangeParams.threads``).  The kernels release the GIL (``nogil=True``), so the
two parts run on two cores; the Python between them does not.  No pool is kept: a thread is
started per call (about 0.1 ms), so the numeric layers hold no global state.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TypeVar

__all__ = [
    "both",
]

A = TypeVar("A")
B = TypeVar("B")


def both(first: Callable[[], A], second: Callable[[], B], threads: int) -> tuple[A, B]:
    """``(first(), second())``; with ``threads`` > 1 ``second`` runs on another thread while
    ``first`` runs on this one.  An exception of either is raised here once both have ended
    (``first``'s when both raise), with its own traceback."""
    if threads <= 1:
        return first(), second()
    box: dict[str, object] = {}

    def run_second() -> None:
        try:
            box["value"] = second()
        except BaseException as exc:  # handed to the caller below
            box["error"] = exc

    helper = threading.Thread(target=run_second, name="robot_change-check", daemon=True)
    helper.start()
    try:
        a = first()
    finally:
        helper.join()
    if "error" in box:
        raise box["error"]
    return a, box["value"]
