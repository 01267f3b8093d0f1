"""Checks for the frozen parameter dataclasses (CloudParams, ChangeParams, ...), and the rule
of a station name (the protocol and the store both hold names to it).

One wording for every error: ``Owner.name=value: must be ...``, an :class:`InputError` that
names the field, the value given and what is allowed.
"""

from __future__ import annotations

import math
import re
from typing import Any, Iterable

import numpy as np

from robot_change.errors import InputError

#: Longest station name, characters.
MAX_STATION = 32
_STATION = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,%d}\Z" % (MAX_STATION - 1))
#: What a station name is, for error messages.
STATION_RULE = (f"a station name is 1..{MAX_STATION} ASCII letters, digits, '_' or '-', "
                "starting with a letter or digit (a name, never a path)")


def is_station(value: Any) -> bool:
    """Is ``value`` a valid station name (:data:`STATION_RULE`)?"""
    return isinstance(value, str) and _STATION.match(value) is not None


def number(owner: str, name: str, value: Any, low: float, high: float, *,
           low_open: bool = False, unit: str = "") -> float:
    """A finite real number with ``low <= value <= high`` (``low < value`` when
    ``low_open``); booleans are refused.  Returns it as a float."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if ok:
        as_float = float(value)
        ok = math.isfinite(as_float) and (as_float > low if low_open else as_float >= low)
        ok = ok and as_float <= high
    if not ok:
        relation = "<" if low_open else "<="
        raise InputError(f"{owner}.{name}={value!r}: must be a number with {low} {relation} "
                         f"{name} <= {high}{unit}")
    return float(value)


def whole(owner: str, name: str, value: Any, low: int, high: int) -> int:
    """A whole number (not a bool, not a float) in ``low..high``."""
    if (isinstance(value, bool) or not isinstance(value, (int, np.integer))
            or not low <= value <= high):
        raise InputError(f"{owner}.{name}={value!r}: must be a whole number in {low}..{high}")
    return int(value)


def flag(owner: str, name: str, value: Any) -> bool:
    """True or False, nothing else (not 0/1, not a string)."""
    if not isinstance(value, bool):
        raise InputError(f"{owner}.{name}={value!r}: must be True or False")
    return value


def choice(owner: str, name: str, value: Any, choices: Iterable[str]) -> str:
    """One of ``choices``."""
    options = tuple(choices)
    if value not in options:
        raise InputError(f"{owner}.{name}={value!r}: must be one of "
                         + ", ".join(repr(option) for option in options))
    return value
