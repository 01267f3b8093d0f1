"""JSON text every parser reads: NaN and the infinities, which Python's ``json`` writes as bare
``NaN`` / ``Infinity`` (not JSON: JavaScript's ``JSON.parse``, jq and strict readers refuse
them), are written as ``null`` (not defined: an EMD with nothing to move, a limit beyond the
range).  Every report, message and ``--json`` line the module writes goes through
:func:`dumps`."""

from __future__ import annotations

import json
import math
from typing import Any

__all__ = ["dumps", "finite"]


def finite(value: Any) -> Any:
    """``value`` (dicts, lists and tuples of JSON values) with every float that is NaN or
    infinite replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    return value


def dumps(value: Any, **options: Any) -> str:
    """:func:`json.dumps` of :func:`finite` ``value`` (``options`` as json.dumps takes them);
    raises ValueError rather than write a non-finite number."""
    return json.dumps(finite(value), allow_nan=False, **options)
