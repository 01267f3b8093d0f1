"""robot_change.validate: the one check of a value, and how config and protocol re-word it."""

from __future__ import annotations

import enum
import math

import numpy as np
import pytest

from robot_change import validate
from robot_change.errors import BadValue, ConfigError, InputError, MessageError
from robot_change.link import protocol
from robot_change.service.config import config_from_dict


class Colour(enum.IntEnum):
    RED = 1
    BLUE = 2


@pytest.mark.parametrize("call, kept", [
    (lambda: validate.number("O", "x", 2, 0.0, 5.0), 2.0),
    (lambda: validate.number("O", "x", np.float32(0.5), 0.0, 1.0), 0.5),
    (lambda: validate.positive("O", "x", 1e-9), 1e-9),
    (lambda: validate.whole("O", "n", np.int64(7), 0, 9), 7),
    (lambda: validate.flag("O", "f", np.bool_(True)), True),
    (lambda: validate.flag("O", "f", 0, zero_one=True), False),
    (lambda: validate.choice("O", "c", "b", ("a", "b")), "b"),
    (lambda: validate.choice("O", "c", 19200, (9600, 19200)), 19200),
    (lambda: validate.member("O", "m", 2, Colour), Colour.BLUE),
    (lambda: validate.text("O", "t", "é", max_bytes=2), "é"),
    (lambda: validate.station("O", "s", "dock_1"), "dock_1"),
])
def test_a_good_value_comes_back_as_its_kind(call, kept) -> None:
    got = call()
    assert got == kept and type(got) is type(kept)


@pytest.mark.parametrize("call, wrong_type, allowed", [
    (lambda: validate.number("O", "x", "1", 0.0, 5.0), True, "a number with 0.0 <= x <= 5.0"),
    (lambda: validate.number("O", "x", True, 0.0, 5.0), True, "a number"),
    (lambda: validate.number("O", "x", math.nan, 0.0, 5.0), True, "a number"),
    (lambda: validate.number("O", "x", 6, 0.0, 5.0, unit=" m"), False, "x <= 5.0 m"),
    (lambda: validate.positive("O", "x", 0.0), False, "a number with x > 0.0"),
    (lambda: validate.whole("O", "n", 2.0, 0, 9), True, "a whole number in 0..9"),
    (lambda: validate.whole("O", "n", True, 0, 9), True, "a whole number in 0..9"),
    (lambda: validate.whole("O", "n", 10, 0, 9), False, "a whole number in 0..9"),
    (lambda: validate.flag("O", "f", 1), True, "true or false"),
    (lambda: validate.flag("O", "f", 2, zero_one=True), True, "true or false"),
    (lambda: validate.flag("O", "f", "yes"), True, "true or false"),
    (lambda: validate.choice("O", "c", "z", ("a", "b")), False, "one of 'a', 'b'"),
    (lambda: validate.choice("O", "c", True, (1, 2)), False, "one of 1, 2"),
    (lambda: validate.member("O", "m", 3, Colour), True, "a Colour (1 RED, 2 BLUE)"),
    (lambda: validate.text("O", "t", 5), True, "a string"),
    (lambda: validate.text("O", "t", "éé", max_bytes=3), False, "at most 3 bytes"),
    (lambda: validate.text("O", "t", "  ", non_empty=True), False, "a non-empty string"),
    (lambda: validate.text("O", "t", "a\0b", no_nul=True), True, "a string"),
    (lambda: validate.text("O", "t", "\udc80"), True, "valid UTF-8"),
    (lambda: validate.station("O", "s", "../etc"), False, "never a path"),
    (lambda: validate.station("O", "s", 5), True, "never a path"),
])
def test_a_bad_value_names_owner_field_value_and_what_is_allowed(call, wrong_type,
                                                                 allowed) -> None:
    with pytest.raises(BadValue) as info:
        call()
    exc = info.value
    assert isinstance(exc, InputError) and isinstance(exc, ValueError)
    assert exc.owner == "O" and exc.wrong_type is wrong_type
    assert allowed in exc.allowed
    assert str(exc).startswith(f"O.{exc.name}={exc.value!r}: must be ")


def test_the_configuration_words_a_bad_value_as_toml_with_the_same_allowed_text() -> None:
    with pytest.raises(ConfigError, match=r"watch\.watch_m = 11: must be a whole number in "
                                          r"1\.\.10"):
        config_from_dict({"watch": {"watch_m": 11}}, "x.toml")
    with pytest.raises(ConfigError, match=r"cloud\.remove_plane = 1: must be true or false"):
        config_from_dict({"cloud": {"remove_plane": 1}}, "x.toml")


def test_the_protocol_naks_a_wrong_kind_as_bad_payload_and_a_wrong_range_as_out_of_range(
        ) -> None:
    with pytest.raises(MessageError) as kind:
        protocol.SetParam(1, "3")
    with pytest.raises(MessageError) as out:
        protocol.SetParam(1, 11)
    assert kind.value.reason == protocol.NakReason.BAD_PAYLOAD
    assert out.value.reason == protocol.NakReason.OUT_OF_RANGE
    assert "SET_PARAM(watch_m).value=11: must be a whole number in 1..10" in str(out.value)
