"""The base of every message layout: the :class:`Message` class, the payload shapes several
messages share, the field checks (every bad value a MessageError naming the field, the value
and what is allowed), and the three messages both ends send: HELLO, ACK, NAK.

Part of :mod:`robot_change.link.protocol`, which re-exports every public name.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

from robot_change import validate
from robot_change.errors import BadValue, MessageError
from robot_change.link.codes import (
    MIN_VERSION,
    PARAM_BY_ID,
    PARAMS,
    VERSION,
    MsgType,
    NakReason,
    Param,
    Role,
)

# ---------------------------------------------------------------------------------------------
# field validation (every error is a MessageError naming the field, the value and what is allowed)


def _checked(reason: NakReason, check: Callable[..., Any], owner: str, name: str, value: object,
             *args: Any, **kwargs: Any) -> Any:
    """``check`` (robot_change.validate) as a MessageError: a value of the wrong kind is a bad
    payload, one out of its range is ``reason``."""
    try:
        return check(owner, name, value, *args, **kwargs)
    except BadValue as exc:
        raise MessageError(str(exc), NakReason.BAD_PAYLOAD if exc.wrong_type else reason) from None


def _enum(owner: str, name: str, value: object, enum: type[IntEnum]) -> IntEnum:
    return _checked(NakReason.BAD_PAYLOAD, validate.member, owner, name, value, enum)


def _int(owner: str, name: str, value: object, lo: int, hi: int,
         reason: NakReason = NakReason.OUT_OF_RANGE) -> int:
    return _checked(reason, validate.whole, owner, name, value, lo, hi)


def _bool(owner: str, name: str, value: object) -> bool:
    return _checked(NakReason.BAD_PAYLOAD, validate.flag, owner, name, value, zero_one=True)


def _station(owner: str, value: object, empty_ok: bool = False) -> str:
    if empty_ok and value == "":
        return ""
    return _checked(NakReason.BAD_PAYLOAD, validate.station, owner, "station", value)


def _text(owner: str, name: str, value: object, limit: int) -> str:
    return _checked(NakReason.BAD_PAYLOAD, validate.text, owner, name, value, max_bytes=limit)


def _set(obj: object, name: str, value: object) -> None:
    object.__setattr__(obj, name, value)


def _exact(cls: type, payload: bytes, size: int) -> None:
    if len(payload) != size:
        raise MessageError(f"{cls.TYPE.name} payload is {len(payload)} bytes, must be {size}",
                           NakReason.BAD_PAYLOAD)


def _read_str(owner: str, payload: bytes, offset: int) -> tuple[str, int]:
    """Read a str8 (u8 length, then UTF-8 bytes) at ``offset``; return (text, next offset)."""
    if offset >= len(payload):
        raise MessageError(f"{owner} payload ends before its string length byte",
                           NakReason.BAD_PAYLOAD)
    n = payload[offset]
    end = offset + 1 + n
    if end > len(payload):
        raise MessageError(f"{owner} string of {n} bytes runs past the end of the payload",
                           NakReason.BAD_PAYLOAD)
    try:
        return payload[offset + 1:end].decode("utf-8"), end
    except UnicodeDecodeError:
        raise MessageError(f"{owner} string is not valid UTF-8", NakReason.BAD_PAYLOAD) from None


def _str8(text: str) -> bytes:
    raw = text.encode("utf-8")
    return bytes((len(raw),)) + raw


# ---------------------------------------------------------------------------------------------
# the base classes


class Message:
    """Base of every message.  Subclasses are frozen dataclasses validated on construction."""

    __slots__ = ()
    TYPE: ClassVar[MsgType]
    #: Sent with a sequence number, acknowledged, retried.  False: HEARTBEATs, ACK, NAK.
    SEQUENCED: ClassVar[bool] = True
    #: Written URGENT_COPIES times per try, with FLAG_URGENT; its ACK likewise.
    URGENT: ClassVar[bool] = False
    #: Who may send it; None: both.
    SENDER: ClassVar[Role | None] = None
    #: The first protocol version in which both ends may send it (PART, NEED: 5); None: never.
    BOTH_WAYS_SINCE: ClassVar[int | None] = None
    #: The first protocol version that has it.
    SINCE: ClassVar[int] = 1

    def pack(self) -> bytes:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    def since(self) -> int:
        """The first protocol version this message, as it stands, exists in (its type's, or
        later where it carries a later version's fields)."""
        return self.SINCE

    @classmethod
    def unpack(cls, payload: bytes) -> Message:  # pragma: no cover
        raise NotImplementedError


class _Empty(Message):
    """A message without payload."""

    __slots__ = ()

    def pack(self) -> bytes:
        return b""

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, 0)
        return cls()


class _StationMsg(Message):
    """A message whose payload is one station name (str8)."""

    __slots__ = ()

    def __post_init__(self) -> None:
        _set(self, "station", _station(self.TYPE.name, self.station))

    def pack(self) -> bytes:
        return _str8(self.station)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        station, end = _read_str(cls.TYPE.name, payload, 0)
        _exact(cls, payload, end)
        return cls(station)


_PARAM = struct.Struct("<Bi")


def _param(owner: str, param: object) -> Param:
    if isinstance(param, bool) or not isinstance(param, int) or param not in PARAM_BY_ID:
        known = ", ".join(f"{p.id} {p.name}" for p in PARAMS)
        raise MessageError(f"{owner}.param = {param!r}: unknown parameter (known: {known})",
                           NakReason.UNKNOWN_PARAM)
    return PARAM_BY_ID[param]


class _ParamValueMsg(Message):
    """param u8 + value i32, with the value checked against the whitelist's bounds."""

    __slots__ = ()

    def __post_init__(self) -> None:
        o = self.TYPE.name
        p = _param(o, self.param)
        _int(f"{o}({p.name})", "value", self.value, p.minimum, p.maximum)

    def pack(self) -> bytes:
        return _PARAM.pack(self.param, self.value)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, _PARAM.size)
        return cls(*_PARAM.unpack(payload))


# ---------------------------------------------------------------------------------------------
# both ways: the session's own messages


_HELLO = struct.Struct("<BBBI")


@dataclass(frozen=True, slots=True)
class Hello(Message):
    """Both ways, first on a link and as a probe: versions spoken, role, boot id, software."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO
    role: Role
    boot_id: int
    software: str = ""
    proto_min: int = MIN_VERSION
    proto_max: int = VERSION

    def __post_init__(self) -> None:
        o = "HELLO"
        _set(self, "role", _enum(o, "role", self.role, Role))
        # a bad field of a HELLO is a bad payload (OUT_OF_RANGE is SET_PARAM's: 7.3)
        _int(o, "boot_id", self.boot_id, 0, 0xFFFF_FFFF, NakReason.BAD_PAYLOAD)
        _text(o, "software", self.software, 32)
        _int(o, "proto_min", self.proto_min, 1, 255, NakReason.BAD_PAYLOAD)
        _int(o, "proto_max", self.proto_max, self.proto_min, 255, NakReason.BAD_PAYLOAD)

    def pack(self) -> bytes:
        return (_HELLO.pack(self.proto_min, self.proto_max, self.role, self.boot_id)
                + _str8(self.software))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if len(payload) < _HELLO.size:
            _exact(cls, payload, _HELLO.size + 1)
        lo, hi, role, boot = _HELLO.unpack_from(payload)
        software, end = _read_str("HELLO", payload, _HELLO.size)
        _exact(cls, payload, end)
        return cls(role, boot, software, lo, hi)


@dataclass(frozen=True, slots=True)
class Ack(_Empty):
    """Both ways: the frame whose seq is in this frame's header arrived intact and was accepted."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    SEQUENCED: ClassVar[bool] = False


@dataclass(frozen=True, slots=True)
class Nak(Message):
    """Both ways: the frame whose seq is in this header was refused; says why and its type."""

    TYPE: ClassVar[MsgType] = MsgType.NAK
    SEQUENCED: ClassVar[bool] = False
    reason: NakReason
    refused_type: int

    def __post_init__(self) -> None:
        _set(self, "reason", _enum("NAK", "reason", self.reason, NakReason))
        _set(self, "refused_type",
             int(_int("NAK", "refused_type", self.refused_type, 0, 255, NakReason.BAD_PAYLOAD)))

    def pack(self) -> bytes:
        return bytes((self.reason, self.refused_type))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, 2)
        return cls(payload[0], payload[1])


def may_send(role: Role, cls: type[Message], version: int = VERSION) -> bool:
    """True when ``role`` is allowed to send messages of class ``cls`` in a frame of
    protocol ``version``."""
    return (cls.SENDER is None or cls.SENDER == role
            or (cls.BOTH_WAYS_SINCE is not None and version >= cls.BOTH_WAYS_SINCE))
