"""The messages the base sends to the module (type codes 0x40..): BASE_HEARTBEAT, the commands
(STATUS_QUERY, CAPTURE_REFERENCE, CHECK, WATCH, STOP, ARM, DISARM, RESUME, SET_PARAM,
GET_PARAM) and NEED.

Part of :mod:`robot_change.link.protocol`, which re-exports every public name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from robot_change.errors import MessageError
from robot_change.link.codes import MAX_PARTS, Motion, MsgType, NakReason, Role
from robot_change.link.messages import (
    Message,
    _Empty,
    _enum,
    _exact,
    _param,
    _ParamValueMsg,
    _set,
    _StationMsg,
)


@dataclass(frozen=True, slots=True)
class BaseHeartbeat(Message):
    """Base -> module, >= 5 Hz: the base's motion state (WATCH runs only while parked)."""

    TYPE: ClassVar[MsgType] = MsgType.BASE_HEARTBEAT
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.BASE
    motion: Motion = Motion.UNKNOWN

    def __post_init__(self) -> None:
        _set(self, "motion", _enum("BASE_HEARTBEAT", "motion", self.motion, Motion))

    def pack(self) -> bytes:
        return bytes((self.motion,))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, 1)
        return cls(payload[0])


@dataclass(frozen=True, slots=True)
class StatusQuery(_Empty):
    """Base -> module: answer with STATUS."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS_QUERY
    SENDER: ClassVar[Role | None] = Role.BASE


@dataclass(frozen=True, slots=True)
class CaptureReference(_StationMsg):
    """Base -> module: build and store the reference of ``station`` (the robot is parked there)."""

    TYPE: ClassVar[MsgType] = MsgType.CAPTURE_REFERENCE
    SENDER: ClassVar[Role | None] = Role.BASE
    station: str


@dataclass(frozen=True, slots=True)
class Check(_StationMsg):
    """Base -> module: compare now with ``station``'s reference once; CHANGE_REPORT (+PAUSE)
    or CLEAR."""

    TYPE: ClassVar[MsgType] = MsgType.CHECK
    SENDER: ClassVar[Role | None] = Role.BASE
    station: str


@dataclass(frozen=True, slots=True)
class Watch(_StationMsg):
    """Base -> module: check ``station`` continuously; PAUSE when a change persists M of N."""

    TYPE: ClassVar[MsgType] = MsgType.WATCH
    SENDER: ClassVar[Role | None] = Role.BASE
    station: str


@dataclass(frozen=True, slots=True)
class Stop(_Empty):
    """Base -> module: stop capturing or watching, back to IDLE (the pause latch stays)."""

    TYPE: ClassVar[MsgType] = MsgType.STOP
    SENDER: ClassVar[Role | None] = Role.BASE


@dataclass(frozen=True, slots=True)
class Arm(_Empty):
    """Base -> module: a detected change raises PAUSE."""

    TYPE: ClassVar[MsgType] = MsgType.ARM
    SENDER: ClassVar[Role | None] = Role.BASE


@dataclass(frozen=True, slots=True)
class Disarm(_Empty):
    """Base -> module: changes are reported but raise no PAUSE."""

    TYPE: ClassVar[MsgType] = MsgType.DISARM
    SENDER: ClassVar[Role | None] = Role.BASE


@dataclass(frozen=True, slots=True)
class Resume(_Empty):
    """Base -> module, urgent: clear the pause latch."""

    TYPE: ClassVar[MsgType] = MsgType.RESUME
    URGENT: ClassVar[bool] = True
    SENDER: ClassVar[Role | None] = Role.BASE


@dataclass(frozen=True, slots=True)
class SetParam(_ParamValueMsg):
    """Base -> module: set a whitelisted parameter; the module answers PARAM_VALUE."""

    TYPE: ClassVar[MsgType] = MsgType.SET_PARAM
    SENDER: ClassVar[Role | None] = Role.BASE
    param: int
    value: int


@dataclass(frozen=True, slots=True)
class GetParam(Message):
    """Base -> module: read a whitelisted parameter; the module answers PARAM_VALUE."""

    TYPE: ClassVar[MsgType] = MsgType.GET_PARAM
    SENDER: ClassVar[Role | None] = Role.BASE
    param: int

    def __post_init__(self) -> None:
        _param("GET_PARAM", self.param)

    def pack(self) -> bytes:
        return bytes((self.param,))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, 1)
        return cls(payload[0])


@dataclass(frozen=True, slots=True)
class Need(Message):
    """Base -> module (version 3; both ways from version 5): of the message whose seq is this
    frame's header seq, the parts ``missing`` have not arrived yet (a bitmap on the wire, bit i
    of byte i // 8 for part i, least significant bit first; the last byte non-zero)."""

    TYPE: ClassVar[MsgType] = MsgType.NEED
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.BASE
    BOTH_WAYS_SINCE: ClassVar[int | None] = 5
    SINCE: ClassVar[int] = 3
    missing: tuple[int, ...]

    def __post_init__(self) -> None:
        missing = (tuple(sorted(set(self.missing)))
                   if isinstance(self.missing, (tuple, list, set, frozenset)) else None)
        if not missing or not all(isinstance(i, int) and not isinstance(i, bool)
                                  and 0 <= i < MAX_PARTS for i in missing):
            raise MessageError(f"NEED.missing = {self.missing!r}: give 1..{MAX_PARTS} part "
                               f"indices 0..{MAX_PARTS - 1}", NakReason.BAD_PAYLOAD)
        _set(self, "missing", missing)

    def pack(self) -> bytes:
        bitmap = bytearray(self.missing[-1] // 8 + 1)
        for i in self.missing:
            bitmap[i // 8] |= 1 << (i % 8)
        return bytes(bitmap)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if not 1 <= len(payload) <= -(-MAX_PARTS // 8) or not payload[-1]:
            raise MessageError(f"NEED payload is {len(payload)} bytes ending in "
                               f"0x{payload[-1] if payload else 0:02X}: "
                               f"want 1..{-(-MAX_PARTS // 8)} "
                               "bytes, the last non-zero", NakReason.BAD_PAYLOAD)
        missing = tuple(i for i in range(8 * len(payload)) if payload[i // 8] >> (i % 8) & 1)
        return cls(missing)
