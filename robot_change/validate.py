"""Every check of one value: the fields of the parameter dataclasses (CloudParams,
ChangeParams, ...), the configuration's keys, the protocol's message fields, and the rule of a
station name (the protocol and the store both hold names to it).

One wording for every error: ``Owner.name=value: must be ...``, a
:class:`robot_change.errors.BadValue` (an InputError) that names the owner, the field, the value
given and what is allowed; the configuration (ConfigError) and the protocol (MessageError,
with its NAK reason) re-word it from those attributes, so every value anywhere is checked here.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from enum import IntEnum
from typing import Any

import numpy as np

from robot_change.errors import BadValue

#: Longest station name, characters.
MAX_STATION = 32
#: Longest robot id (the fleet's topic level naming a robot), characters.
MAX_ROBOT_ID = 64


def _name_rule(max_chars: int) -> str:
    return (f"1..{max_chars} ASCII letters, digits, '_' or '-', starting with a letter or "
            "digit (a name, never a path)")


#: What a station name is, for error messages.
STATION_RULE = f"a station name is {_name_rule(MAX_STATION)}"


def _is_name(value: Any, max_chars: int) -> bool:
    return (isinstance(value, str) and len(value) <= max_chars
            and re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", value) is not None)


def is_station(value: Any) -> bool:
    """Is ``value`` a valid station name (:data:`STATION_RULE`)?"""
    return _is_name(value, MAX_STATION)


def _is_whole(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)))


def number(owner: str, name: str, value: Any, low: float, high: float, *,
           low_open: bool = False, high_open: bool = False, unit: str = "") -> float:
    """A finite real number with ``low <= value <= high`` (``low < value`` when
    ``low_open``, ``value < high`` when ``high_open``); booleans are refused.  Returns it as
    a float."""
    if math.isinf(high):
        allowed = f"a number with {name} {'>' if low_open else '>='} {low}{unit}"
    else:
        allowed = (f"a number with {low} {'<' if low_open else '<='} {name} "
                   f"{'<' if high_open else '<='} {high}{unit}")
    if not _is_real(value) or not math.isfinite(float(value)):
        raise BadValue(owner, name, value, allowed, wrong_type=True)
    as_float = float(value)
    if not ((as_float > low if low_open else as_float >= low)
            and (as_float < high if high_open else as_float <= high)):
        raise BadValue(owner, name, value, allowed)
    return as_float


def positive(owner: str, name: str, value: Any, high: float = math.inf, *, unit: str = ""
             ) -> float:
    """A finite number with ``0 < value <= high``."""
    return number(owner, name, value, 0.0, high, low_open=True, unit=unit)


def whole(owner: str, name: str, value: Any, low: int, high: int, *, unit: str = "") -> int:
    """A whole number (not a bool, not a float) in ``low..high``."""
    allowed = f"a whole number in {low}..{high}{unit}"
    if not _is_whole(value):
        raise BadValue(owner, name, value, allowed, wrong_type=True)
    if not low <= value <= high:
        raise BadValue(owner, name, value, allowed)
    return int(value)


def flag(owner: str, name: str, value: Any, *, zero_one: bool = False) -> bool:
    """True or False, nothing else (not a string; 0 and 1 only when ``zero_one``, as the wire
    carries them)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if zero_one and _is_whole(value) and value in (0, 1):
        return bool(value)
    raise BadValue(owner, name, value, "true or false", wrong_type=True)


def choice(owner: str, name: str, value: Any, choices: Iterable[Any]) -> Any:
    """One of ``choices`` (strings are shown quoted, numbers bare)."""
    options = tuple(choices)
    a_bool_for_a_number = isinstance(value, bool) and not any(isinstance(o, bool) for o in options)
    if a_bool_for_a_number or value not in options:  # (True == 1)
        raise BadValue(owner, name, value, "one of " + ", ".join(
            repr(option) if isinstance(option, str) else str(option) for option in options))
    return value


def member(owner: str, name: str, value: Any, enum: type[IntEnum]) -> IntEnum:
    """A member of the integer enumeration ``enum``, or its value."""
    try:
        return enum(value)
    except (ValueError, TypeError):
        allowed = ", ".join(f"{m.value} {m.name}" for m in enum)
        raise BadValue(owner, name, value, f"a {enum.__name__} ({allowed})",
                       wrong_type=True) from None


def text(owner: str, name: str, value: Any, *, max_bytes: int | None = None,
         non_empty: bool = False, no_nul: bool = False) -> str:
    """A string encodable as UTF-8; at most ``max_bytes`` bytes of UTF-8 when given; not blank
    when ``non_empty``; without NUL characters when ``no_nul`` (a path, a device name)."""
    allowed = "a non-empty string" if non_empty else "a string"
    if not isinstance(value, str) or (no_nul and "\0" in value):
        raise BadValue(owner, name, value, allowed, wrong_type=True)
    if non_empty and not value.strip():
        raise BadValue(owner, name, value, allowed)
    try:
        size = len(value.encode("utf-8"))
    except UnicodeEncodeError:
        raise BadValue(owner, name, value, "a string of valid UTF-8", wrong_type=True) from None
    if max_bytes is not None and size > max_bytes:
        raise BadValue(owner, name, value, f"at most {max_bytes} bytes of UTF-8 (it has {size})")
    return value


def station(owner: str, name: str, value: Any) -> str:
    """A station name (:data:`STATION_RULE`)."""
    return plain_name(owner, name, value, MAX_STATION)


def plain_name(owner: str, name: str, value: Any, max_chars: int) -> str:
    """A name that is safe as a file name and as one MQTT topic level: 1..``max_chars`` ASCII
    letters, digits, '_' or '-', starting with a letter or digit (stations, robot ids)."""
    if not _is_name(value, max_chars):
        raise BadValue(owner, name, value, _name_rule(max_chars),
                       wrong_type=not isinstance(value, str))
    return value


#: Longest MQTT topic prefix, bytes of UTF-8 (a topic may have 65535; ours add ~100).
MAX_TOPIC_PREFIX = 200


def topic_prefix(owner: str, name: str, value: Any) -> str:
    """The first levels of an MQTT topic: levels joined by '/', none empty, no wildcard ('+',
    '#'), no control character, at most :data:`MAX_TOPIC_PREFIX` bytes of UTF-8."""
    allowed = ("MQTT topic levels joined by '/' (e.g. \"robot-change\" or \"site-a/robots\"): "
               f"none empty, no '+' or '#', no control characters, at most "
               f"{MAX_TOPIC_PREFIX} bytes")
    text(owner, name, value, non_empty=True)
    if (len(value.encode("utf-8")) > MAX_TOPIC_PREFIX or any(c in value for c in "+#")
            or any(ord(c) < 32 or ord(c) == 127 for c in value)
            or "" in value.split("/") or value.startswith("$")):
        raise BadValue(owner, name, value, allowed)
    return value


#: The schemes of a broker URL and their default ports.
BROKER_SCHEMES = {"mqtt": 1883, "mqtts": 8883}


def broker_url(owner: str, name: str, value: Any) -> tuple[str, str, int]:
    """An MQTT broker URL, ``mqtt://HOST[:PORT]`` (TCP, port 1883) or ``mqtts://HOST[:PORT]``
    (TLS, port 8883), with no path, query or user name (credentials are keys of their own).
    Returns (scheme, host, port)."""
    allowed = ("a broker URL mqtt://HOST[:PORT] (plain TCP, port 1883) or mqtts://HOST[:PORT] "
               "(TLS, port 8883), without a path or credentials")
    text(owner, name, value, non_empty=True, no_nul=True)
    match = re.fullmatch(r"(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://(?P<host>\[[0-9A-Fa-f:.]+\]|"
                         r"[A-Za-z0-9._-]+)(?::(?P<port>[0-9]{1,5}))?/?", value.strip())
    if match is None or match["scheme"].lower() not in BROKER_SCHEMES:
        raise BadValue(owner, name, value, allowed)
    scheme = match["scheme"].lower()
    port = int(match["port"]) if match["port"] else BROKER_SCHEMES[scheme]
    if not 1 <= port <= 65535:
        raise BadValue(owner, name, value, allowed + "; the port in 1..65535")
    return scheme, match["host"].strip("[]"), port
