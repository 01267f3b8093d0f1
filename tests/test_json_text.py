"""Every JSON the module writes is read by strict parsers: no bare NaN or Infinity."""

from __future__ import annotations

import json
import math

import pytest
from conftest import strict_loads

from robot_change.json_text import dumps, finite


def test_non_finite_numbers_are_written_as_null_wherever_they_stand():
    value = {"emd_after": [math.nan], "limit": (math.inf, -math.inf, 1.5),
             "nested": [{"x": math.nan, "ok": 2, "name": "NaN"}], "flag": True, "none": None}
    text = dumps(value, indent=1)
    assert strict_loads(text) == {"emd_after": [None], "limit": [None, None, 1.5],
                                  "nested": [{"x": None, "ok": 2, "name": "NaN"}],
                                  "flag": True, "none": None}
    assert finite(3) == 3 and finite("inf") == "inf"
    with pytest.raises(ValueError, match="not JSON"):
        strict_loads(json.dumps([math.nan]))  # what json.dumps alone writes
    with pytest.raises(TypeError):
        dumps({"a": object()})  # anything else json refuses is still refused


def test_the_fleet_and_foxglove_messages_go_through_it():
    """The MQTT messages and the check's JSON topics in Foxglove are written the same way."""
    from robot_change.fleet.messages import encode

    assert strict_loads(encode({"limit_mm": math.inf, "ok": 1}).decode()) == {
        "limit_mm": None, "ok": 1}
