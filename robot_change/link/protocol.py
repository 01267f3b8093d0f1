"""Wire format between the module and the base controller, sans-IO: bytes <-> messages.

No ports, no threads, no clocks: :func:`encode` turns a message into the bytes of one frame and
:class:`FrameDecoder` turns any stream of bytes into frames and counted decode errors.  The
session (sequence numbers, acks, retries, heartbeats) lives in :mod:`robot_change.link.session`.

A frame on the wire is ``COBS(body) 0x00``; the body is::

    version u8 | type u8 | seq u16 LE | flags u8 | payload (0..240 bytes) | CRC-16 u16 BE

with CRC-16/CCITT-FALSE (``binascii.crc_hqx(data, 0xFFFF)``) over everything before it.  Every
multi-byte field of a payload is little-endian.  docs/protocol.md is the specification; its hex
examples are checked by the tests against this module.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, fields
from enum import Enum, IntEnum
from typing import Any, Callable, ClassVar, Iterable

from robot_change import validate
from robot_change.errors import BadValue, MessageError

#: The highest protocol version this end speaks, and the lowest (docs/protocol.md 7.5).
VERSION = 4
MIN_VERSION = 1
MAX_PAYLOAD = 240
HEADER = struct.Struct("<BBHB")
HEADER_SIZE = HEADER.size  # 5
CRC_SIZE = 2
MIN_BODY = HEADER_SIZE + CRC_SIZE  # 7
MAX_BODY = MIN_BODY + MAX_PAYLOAD  # 247
#: Longest COBS-encoded body (without the 0x00 delimiter): one overhead byte below 254 bytes.
MAX_ENCODED = MAX_BODY + 1  # 248
#: Urgent frames (PAUSE, RESUME) are written this many times in a row, and so are their ACKs.
URGENT_COPIES = 8
FLAG_URGENT = 0x01
FLAG_RETRY = 0x02
#: Longest station name, in bytes.
MAX_STATION = validate.MAX_STATION
#: Regions per CHANGE_REPORT part (fits any station name within the payload limit).
REGIONS_PER_PART = 11
#: Version 3: bytes of a carried body per PART frame (docs/protocol.md 7.11); a PART frame is
#: then 19 bytes on the wire, short enough to get through 10 % byte corruption often.
PART_DATA = 8
#: PARTs of one carried body at most: ceil(MAX_BODY / PART_DATA).
MAX_PARTS = -(-MAX_BODY // PART_DATA)  # 31


# ---------------------------------------------------------------------------------------------
# codes


class MsgType(IntEnum):
    """Message type codes: 0x01.. both directions, 0x10.. module -> base, 0x40.. base -> module."""

    HELLO = 0x01
    ACK = 0x02
    NAK = 0x03
    HEARTBEAT = 0x10
    PAUSE = 0x11
    CHANGE_REPORT = 0x12
    CLEAR = 0x13
    FAULT = 0x14
    STATUS = 0x15
    PARAM_VALUE = 0x16
    CAPTURED = 0x17
    CHECK_RESULT = 0x18
    PART = 0x19
    BASE_HEARTBEAT = 0x40
    STATUS_QUERY = 0x41
    CAPTURE_REFERENCE = 0x42
    CHECK = 0x43
    WATCH = 0x44
    STOP = 0x45
    ARM = 0x46
    DISARM = 0x47
    RESUME = 0x48
    SET_PARAM = 0x49
    GET_PARAM = 0x4A
    NEED = 0x4B


class Role(IntEnum):
    """Who is speaking: the change-detection module or the base controller."""

    MODULE = 1
    BASE = 2


class NakReason(IntEnum):
    """Why a frame with a valid CRC was refused."""

    UNKNOWN_TYPE = 1
    BAD_PAYLOAD = 2
    BAD_VERSION = 3
    UNKNOWN_PARAM = 4
    OUT_OF_RANGE = 5
    WRONG_DIRECTION = 6
    BUSY = 7  # version 3: the module's queue for this kind of command is full; try later


class DecodeReason(str, Enum):
    """Why a stretch of bytes between two delimiters did not become a message."""

    BAD_COBS = "bad_cobs"
    BAD_CRC = "bad_crc"
    TOO_LONG = "too_long"
    TOO_SHORT = "too_short"
    BAD_VERSION = "bad_version"
    UNKNOWN_TYPE = "unknown_type"
    BAD_PAYLOAD = "bad_payload"


class ModuleState(IntEnum):
    """What the module is doing (HEARTBEAT, STATUS)."""

    BOOTING = 0
    IDLE = 1
    CAPTURING = 2
    CHECKING = 3
    WATCHING = 4
    PAUSED = 5
    FAULT = 6


class PauseCause(IntEnum):
    """Why the module asks the base to pause."""

    CHANGE_CHECK = 1
    CHANGE_WATCH = 2
    CAMERA_LOST = 3
    INTERNAL_ERROR = 4
    NOT_AT_STATION = 5  # version 2: the robot was moved off the station it watches


class FaultCode(IntEnum):
    """What went wrong (FAULT); CLEARED says every fault is over."""

    CLEARED = 0
    CAMERA_LOST = 1
    REFERENCE_MISSING = 2
    INTERNAL_ERROR = 3
    STORAGE_ERROR = 4
    COMMAND_REFUSED = 5
    NOT_AT_STATION = 6  # version 2
    STALLED = 7  # version 2: a part of the module made no progress; the module restarts


#: Codes a version-1 peer does not know, and the version-1 code sent in their place.
V1_PAUSE_CAUSE = {PauseCause.NOT_AT_STATION: PauseCause.CAMERA_LOST}
V1_FAULT_CODE = {FaultCode.NOT_AT_STATION: FaultCode.COMMAND_REFUSED,
                 FaultCode.STALLED: FaultCode.INTERNAL_ERROR}


class CheckOutcome(IntEnum):
    """What a check found (CHECK_RESULT, version 2)."""

    NO_CHANGE = 0
    CHANGED = 1
    NOT_AT_STATION = 2


#: CHECK_RESULT ``weak`` bits: directions of the offset the views leave unconstrained (base
#: frame: x forward, y left, z up; roll, pitch, yaw about them).
WEAK_BITS = {"x": 0x01, "y": 0x02, "z": 0x04, "roll": 0x08, "pitch": 0x10, "yaw": 0x20}


class RegionKind(IntEnum):
    """A changed region holds something new (APPEARED) or misses something (DISAPPEARED)."""

    APPEARED = 1
    DISAPPEARED = 2


class Motion(IntEnum):
    """The base's own state, in its heartbeat."""

    UNKNOWN = 0
    MOVING = 1
    PARKED = 2
    PAUSED = 3


@dataclass(frozen=True)
class Param:
    """One entry of the SET_PARAM / GET_PARAM whitelist: a bounded integer, never a path."""

    id: int
    name: str
    minimum: int
    maximum: int
    default: int
    unit: str
    meaning: str


#: The only parameters the base may read or set.  Ids are never reused.
PARAMS: tuple[Param, ...] = (
    Param(1, "watch_m", 1, 10, 3, "checks", "WATCH pauses when a change is seen in M ..."),
    Param(2, "watch_n", 1, 10, 5, "checks", "... of the last N checks (M <= N)"),
    Param(3, "check_interval_ms", 100, 10_000, 500, "ms", "time between two WATCH checks"),
    Param(4, "min_region_points", 10, 100_000, 12, "points", "smaller changed regions are ignored"),
    Param(5, "pause_on_change", 0, 1, 1, "bool", "1: a change raises PAUSE; 0: report only"),
    Param(6, "fuse_frames", 1, 30, 5, "frames", "depth frames fused per capture or check"),
    Param(7, "min_region_extent_mm", 10, 5_000, 10, "mm", "smaller changed regions are ignored"),
    Param(8, "max_depth_mm", 500, 10_000, 5_000, "mm", "depth beyond this is not used"),
)
PARAM_BY_ID = {p.id: p for p in PARAMS}
PARAM_BY_NAME = {p.name: p for p in PARAMS}


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
# messages


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
    #: The first protocol version that has it.
    SINCE: ClassVar[int] = 1

    def pack(self) -> bytes:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    def since(self) -> int:
        """The first protocol version this message, as it stands, exists in (its type's, or
        later where it carries a later version's fields)."""
        return self.SINCE

    @classmethod
    def unpack(cls, payload: bytes) -> "Message":  # pragma: no cover
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
        _int(o, "boot_id", self.boot_id, 0, 0xFFFF_FFFF)
        _text(o, "software", self.software, 32)
        _int(o, "proto_min", self.proto_min, 1, 255)
        _int(o, "proto_max", self.proto_max, self.proto_min, 255)

    def pack(self) -> bytes:
        return _HELLO.pack(self.proto_min, self.proto_max, self.role, self.boot_id) + _str8(self.software)

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


_HEARTBEAT = struct.Struct("<BBHI")
_PAUSED, _ARMED, _FAULT = 0x01, 0x02, 0x04


def _state_flags(paused: bool, armed: bool, fault: bool) -> int:
    return (_PAUSED if paused else 0) | (_ARMED if armed else 0) | (_FAULT if fault else 0)


@dataclass(frozen=True, slots=True)
class Heartbeat(Message):
    """Module -> base, ~10 Hz: state, the pause latch (repeated until RESUME), fps, last frame."""

    TYPE: ClassVar[MsgType] = MsgType.HEARTBEAT
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.MODULE
    state: ModuleState
    paused: bool = False
    armed: bool = False
    fault: bool = False
    fps_x10: int = 0
    frame_index: int = 0

    def __post_init__(self) -> None:
        o = "HEARTBEAT"
        _set(self, "state", _enum(o, "state", self.state, ModuleState))
        _set(self, "paused", _bool(o, "paused", self.paused))
        _set(self, "armed", _bool(o, "armed", self.armed))
        _set(self, "fault", _bool(o, "fault", self.fault))
        _int(o, "fps_x10", self.fps_x10, 0, 0xFFFF)
        _int(o, "frame_index", self.frame_index, 0, 0xFFFF_FFFF)

    def pack(self) -> bytes:
        return _HEARTBEAT.pack(self.state, _state_flags(self.paused, self.armed, self.fault),
                               self.fps_x10, self.frame_index)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, _HEARTBEAT.size)
        state, flags, fps, frame = _HEARTBEAT.unpack(payload)
        return cls(state, bool(flags & _PAUSED), bool(flags & _ARMED), bool(flags & _FAULT), fps, frame)


@dataclass(frozen=True, slots=True)
class Pause(Message):
    """Module -> base, urgent: stop now.  Only RESUME from the base lifts the latch."""

    TYPE: ClassVar[MsgType] = MsgType.PAUSE
    URGENT: ClassVar[bool] = True
    SENDER: ClassVar[Role | None] = Role.MODULE
    cause: PauseCause

    def __post_init__(self) -> None:
        _set(self, "cause", _enum("PAUSE", "cause", self.cause, PauseCause))

    def pack(self) -> bytes:
        return bytes((self.cause,))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        _exact(cls, payload, 1)
        return cls(payload[0])


_REGION = struct.Struct("<B3h3HI")


@dataclass(frozen=True, slots=True)
class Region:
    """One changed region: kind, centroid and extent (camera optical frame, mm), point count."""

    kind: RegionKind
    centroid_mm: tuple[int, int, int]
    extent_mm: tuple[int, int, int]
    points: int

    def __post_init__(self) -> None:
        o = "Region"
        _set(self, "kind", _enum(o, "kind", self.kind, RegionKind))
        for name, lo, hi in (("centroid_mm", -32768, 32767), ("extent_mm", 0, 65535)):
            value = getattr(self, name)
            if not isinstance(value, (tuple, list)) or len(value) != 3:
                raise MessageError(f"{o}.{name} = {value!r}: must be 3 integers (x, y, z)",
                                   NakReason.BAD_PAYLOAD)
            _set(self, name, tuple(_int(o, name, v, lo, hi) for v in value))
        _int(o, "points", self.points, 0, 0xFFFF_FFFF)

    def pack(self) -> bytes:
        return _REGION.pack(self.kind, *self.centroid_mm, *self.extent_mm, self.points)

    @classmethod
    def unpack_many(cls, data: bytes) -> tuple["Region", ...]:
        """Regions packed back to back.  struct already bounds every number; only kind is checked."""
        out = []
        new, put, kinds = object.__new__, object.__setattr__, _REGION_KINDS
        for v in _REGION.iter_unpack(data):
            kind = kinds.get(v[0])
            if kind is None:
                _enum("Region", "kind", v[0], RegionKind)
            region = new(cls)
            put(region, "kind", kind)
            put(region, "centroid_mm", v[1:4])
            put(region, "extent_mm", v[4:7])
            put(region, "points", v[7])
            out.append(region)
        return tuple(out)


_REGION_KINDS = {kind.value: kind for kind in RegionKind}


_REPORT = struct.Struct("<HBB")


@dataclass(frozen=True, slots=True)
class ChangeReport(Message):
    """Module -> base: part ``part`` of ``parts`` of report ``report_id`` for ``station``.

    Use :func:`split_change_report` to make the parts and :class:`ReportAssembler` to join them.
    A report with no region says "checked: no change".
    """

    TYPE: ClassVar[MsgType] = MsgType.CHANGE_REPORT
    SENDER: ClassVar[Role | None] = Role.MODULE
    report_id: int
    part: int
    parts: int
    station: str
    regions: tuple[Region, ...] = ()

    def __post_init__(self) -> None:
        o = "CHANGE_REPORT"
        _int(o, "report_id", self.report_id, 0, 0xFFFF)
        _int(o, "parts", self.parts, 1, 255)
        _int(o, "part", self.part, 0, self.parts - 1)
        _set(self, "station", _station(o, self.station))
        regions = tuple(self.regions)
        if len(regions) > REGIONS_PER_PART:
            raise MessageError(f"{o}: {len(regions)} regions in one part, at most "
                               f"{REGIONS_PER_PART}: use split_change_report()", NakReason.BAD_PAYLOAD)
        if not all(type(r) is Region for r in regions):
            raise MessageError(f"{o}.regions must hold Region objects", NakReason.BAD_PAYLOAD)
        _set(self, "regions", regions)

    def pack(self) -> bytes:
        return b"".join((_REPORT.pack(self.report_id, self.part, self.parts), _str8(self.station),
                         bytes((len(self.regions),)), *(r.pack() for r in self.regions)))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if len(payload) < _REPORT.size:
            _exact(cls, payload, _REPORT.size + 2)
        report_id, part, parts = _REPORT.unpack_from(payload)
        station, off = _read_str("CHANGE_REPORT", payload, _REPORT.size)
        if off >= len(payload):
            _exact(cls, payload, off + 1)
        count = payload[off]
        _exact(cls, payload, off + 1 + count * _REGION.size)
        if not part < parts:
            raise MessageError(f"CHANGE_REPORT part {part} of {parts}: want 0 <= part < parts "
                               "and parts 1..255", NakReason.BAD_PAYLOAD)
        if count > REGIONS_PER_PART:
            raise MessageError(f"CHANGE_REPORT with {count} regions in one part, at most "
                               f"{REGIONS_PER_PART}", NakReason.BAD_PAYLOAD)
        report = object.__new__(cls)  # struct bounded the numbers; check the rest, skip the rest
        for name, value in (("report_id", report_id), ("part", part), ("parts", parts),
                            ("station", _station("CHANGE_REPORT", station)),
                            ("regions", Region.unpack_many(payload[off + 1:]))):
            _set(report, name, value)
        return report


@dataclass(frozen=True, slots=True)
class Clear(_StationMsg):
    """Module -> base: the scene at ``station`` matches its reference (no change, or gone again)."""

    TYPE: ClassVar[MsgType] = MsgType.CLEAR
    SENDER: ClassVar[Role | None] = Role.MODULE
    station: str


_CHECK_RESULT = struct.Struct("<BH3h3hHHB")


@dataclass(frozen=True, slots=True)
class CheckResult(Message):
    """Module -> base (version 2): what a check of ``station`` found and where the robot stands.

    ``outcome``: :class:`CheckOutcome`.  ``report_id``: the CHANGE_REPORT that follows (0: none).
    ``offset_mm`` (dx, dy, dz) and ``rotation_cdeg`` (roll, pitch, yaw, centi-degrees): the
    robot's pose now relative to its pose when the reference was captured, in the base frame
    of that station pose (x forward, y left, z up; REP 103).  ``fitness_permille``: registered
    overlap 0..1000; ``unobserved_permille``: points the other epoch could not see;
    ``weak``: :data:`WEAK_BITS` of unconstrained directions.
    """

    TYPE: ClassVar[MsgType] = MsgType.CHECK_RESULT
    SENDER: ClassVar[Role | None] = Role.MODULE
    SINCE: ClassVar[int] = 2
    station: str
    outcome: CheckOutcome
    report_id: int = 0
    offset_mm: tuple[int, int, int] = (0, 0, 0)
    rotation_cdeg: tuple[int, int, int] = (0, 0, 0)
    fitness_permille: int = 0
    unobserved_permille: int = 0
    weak: int = 0

    def __post_init__(self) -> None:
        o = "CHECK_RESULT"
        _set(self, "station", _station(o, self.station))
        _set(self, "outcome", _enum(o, "outcome", self.outcome, CheckOutcome))
        _int(o, "report_id", self.report_id, 0, 0xFFFF)
        for name in ("offset_mm", "rotation_cdeg"):
            value = getattr(self, name)
            if not isinstance(value, (tuple, list)) or len(value) != 3:
                raise MessageError(f"{o}.{name} = {value!r}: must be 3 integers",
                                   NakReason.BAD_PAYLOAD)
            _set(self, name, tuple(_int(o, name, v, -32768, 32767) for v in value))
        _int(o, "fitness_permille", self.fitness_permille, 0, 1000)
        _int(o, "unobserved_permille", self.unobserved_permille, 0, 1000)
        _int(o, "weak", self.weak, 0, 0x3F)

    def pack(self) -> bytes:
        return _CHECK_RESULT.pack(self.outcome, self.report_id, *self.offset_mm,
                                  *self.rotation_cdeg, self.fitness_permille,
                                  self.unobserved_permille, self.weak) + _str8(self.station)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if len(payload) < _CHECK_RESULT.size:
            _exact(cls, payload, _CHECK_RESULT.size + 2)
        v = _CHECK_RESULT.unpack_from(payload)
        station, end = _read_str("CHECK_RESULT", payload, _CHECK_RESULT.size)
        _exact(cls, payload, end)
        return cls(station, v[0], v[1], v[2:5], v[5:8], v[8], v[9], v[10])


@dataclass(frozen=True, slots=True)
class Fault(Message):
    """Module -> base: something is wrong (or, code CLEARED, no longer); text says what to do."""

    TYPE: ClassVar[MsgType] = MsgType.FAULT
    SENDER: ClassVar[Role | None] = Role.MODULE
    code: FaultCode
    text: str = ""

    def __post_init__(self) -> None:
        _set(self, "code", _enum("FAULT", "code", self.code, FaultCode))
        _text("FAULT", "text", self.text, 200)

    def pack(self) -> bytes:
        return bytes((self.code,)) + _str8(self.text)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if not payload:
            _exact(cls, payload, 2)
        text, end = _read_str("FAULT", payload, 1)
        _exact(cls, payload, end)
        return cls(payload[0], text)


_STATUS = struct.Struct("<BBHIII")


@dataclass(frozen=True, slots=True)
class Status(Message):
    """Module -> base, the answer to STATUS_QUERY."""

    TYPE: ClassVar[MsgType] = MsgType.STATUS
    SENDER: ClassVar[Role | None] = Role.MODULE
    state: ModuleState
    paused: bool = False
    armed: bool = False
    fault: bool = False
    fps_x10: int = 0
    frame_index: int = 0
    frames_dropped: int = 0
    uptime_s: int = 0
    station: str = ""

    def __post_init__(self) -> None:
        o = "STATUS"
        _set(self, "state", _enum(o, "state", self.state, ModuleState))
        for name in ("paused", "armed", "fault"):
            _set(self, name, _bool(o, name, getattr(self, name)))
        _int(o, "fps_x10", self.fps_x10, 0, 0xFFFF)
        for name in ("frame_index", "frames_dropped", "uptime_s"):
            _int(o, name, getattr(self, name), 0, 0xFFFF_FFFF)
        _set(self, "station", _station(o, self.station, empty_ok=True))

    def pack(self) -> bytes:
        return _STATUS.pack(self.state, _state_flags(self.paused, self.armed, self.fault),
                            self.fps_x10, self.frame_index, self.frames_dropped,
                            self.uptime_s) + _str8(self.station)

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if len(payload) < _STATUS.size:
            _exact(cls, payload, _STATUS.size + 1)
        state, flags, fps, frame, dropped, uptime = _STATUS.unpack_from(payload)
        station, end = _read_str("STATUS", payload, _STATUS.size)
        _exact(cls, payload, end)
        return cls(state, bool(flags & _PAUSED), bool(flags & _ARMED), bool(flags & _FAULT),
                   fps, frame, dropped, uptime, station)


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


@dataclass(frozen=True, slots=True)
class ParamValue(_ParamValueMsg):
    """Module -> base: the current value of a parameter (answers GET_PARAM and SET_PARAM)."""

    TYPE: ClassVar[MsgType] = MsgType.PARAM_VALUE
    SENDER: ClassVar[Role | None] = Role.MODULE
    param: int
    value: int


@dataclass(frozen=True, slots=True)
class Captured(Message):
    """Module -> base: the reference of ``station`` is built and stored (answers
    CAPTURE_REFERENCE).  Version 4 adds what the station can see: ``smallest_change_mm``, the
    edge of the smallest box a check reports at the view's median depth (0: nothing can be
    told, no reading within the camera's range), and ``noise``, the camera's noise profile the
    reference keeps; both None before version 4 (a module leaves them out for an older base)."""

    TYPE: ClassVar[MsgType] = MsgType.CAPTURED
    SENDER: ClassVar[Role | None] = Role.MODULE
    station: str
    smallest_change_mm: int | None = None
    noise: str | None = None

    def __post_init__(self) -> None:
        _set(self, "station", _station("CAPTURED", self.station))
        if (self.smallest_change_mm is None) != (self.noise is None):
            raise MessageError("CAPTURED: smallest_change_mm and noise come together (version "
                               "4) or not at all", NakReason.BAD_PAYLOAD)
        if self.noise is not None:
            _set(self, "smallest_change_mm", _int("CAPTURED", "smallest_change_mm",
                                                  self.smallest_change_mm, 0, 0xFFFF))
            _text("CAPTURED", "noise", self.noise, 64)

    def since(self) -> int:
        return 1 if self.noise is None else 4

    def pack(self) -> bytes:
        if self.noise is None:
            return _str8(self.station)
        return (_str8(self.station) + _CAPTURED.pack(self.smallest_change_mm)
                + _str8(self.noise))

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        station, end = _read_str("CAPTURED", payload, 0)
        if end == len(payload):
            return cls(station)
        if end + _CAPTURED.size > len(payload):
            _exact(cls, payload, end + _CAPTURED.size + 1)
        (smallest,) = _CAPTURED.unpack_from(payload, end)
        noise, end = _read_str("CAPTURED", payload, end + _CAPTURED.size)
        _exact(cls, payload, end)
        return cls(station, smallest, noise)


_CAPTURED = struct.Struct("<H")


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
    """Base -> module: compare now with ``station``'s reference once; CHANGE_REPORT (+PAUSE) or CLEAR."""

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
class Part(Message):
    """Module -> base (version 3): part ``index`` of ``count`` of the body of a sequenced
    message, whose seq is this frame's header seq (docs/protocol.md 7.11).  Not acknowledged
    itself: the carried message is, once the base has joined every part."""

    TYPE: ClassVar[MsgType] = MsgType.PART
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.MODULE
    SINCE: ClassVar[int] = 3
    index: int
    count: int
    data: bytes

    def __post_init__(self) -> None:
        _int("PART", "count", self.count, 1, MAX_PARTS, NakReason.BAD_PAYLOAD)
        _int("PART", "index", self.index, 0, self.count - 1, NakReason.BAD_PAYLOAD)
        if not isinstance(self.data, (bytes, bytearray)) or not 1 <= len(self.data) <= PART_DATA:
            raise MessageError(f"PART.data must be 1..{PART_DATA} bytes", NakReason.BAD_PAYLOAD)
        _set(self, "data", bytes(self.data))

    def pack(self) -> bytes:
        return bytes((self.index, self.count)) + self.data

    @classmethod
    def unpack(cls, payload: bytes) -> Message:
        if not 3 <= len(payload) <= 2 + PART_DATA:
            raise MessageError(f"PART payload is {len(payload)} bytes, must be 3..{2 + PART_DATA}",
                               NakReason.BAD_PAYLOAD)
        return cls(payload[0], payload[1], payload[2:])


@dataclass(frozen=True, slots=True)
class Need(Message):
    """Base -> module (version 3): of the message whose seq is this frame's header seq, the
    parts ``missing`` have not arrived yet (a bitmap on the wire, bit i of byte i // 8 for
    part i, least significant bit first; the last byte non-zero)."""

    TYPE: ClassVar[MsgType] = MsgType.NEED
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.BASE
    SINCE: ClassVar[int] = 3
    missing: tuple[int, ...]

    def __post_init__(self) -> None:
        missing = tuple(sorted(set(self.missing))) if isinstance(self.missing, (tuple, list, set, frozenset)) else None
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
                               f"0x{payload[-1] if payload else 0:02X}: want 1..{-(-MAX_PARTS // 8)} "
                               "bytes, the last non-zero", NakReason.BAD_PAYLOAD)
        missing = tuple(i for i in range(8 * len(payload)) if payload[i // 8] >> (i % 8) & 1)
        return cls(missing)


def split_body(body: bytes) -> list[Part]:
    """The PARTs that carry ``body`` (a whole frame body, header and CRC included)."""
    if not MIN_BODY <= len(body) <= MAX_BODY:
        raise MessageError(f"a carried body is {MIN_BODY}..{MAX_BODY} bytes, got {len(body)}")
    chunks = [body[i:i + PART_DATA] for i in range(0, len(body), PART_DATA)]
    return [Part(i, len(chunks), chunk) for i, chunk in enumerate(chunks)]


MESSAGE_CLASSES: tuple[type[Message], ...] = (
    Hello, Ack, Nak, Heartbeat, Pause, ChangeReport, Clear, Fault, Status, ParamValue, Captured,
    CheckResult, BaseHeartbeat, StatusQuery, CaptureReference, Check, Watch, Stop, Arm, Disarm, Resume,
    SetParam, GetParam, Part, Need,
)
CLASS_BY_TYPE: dict[int, type[Message]] = {cls.TYPE: cls for cls in MESSAGE_CLASSES}
CLASS_BY_NAME: dict[str, type[Message]] = {cls.TYPE.name: cls for cls in MESSAGE_CLASSES}


def may_send(role: Role, cls: type[Message]) -> bool:
    """True when ``role`` is allowed to send messages of class ``cls``."""
    return cls.SENDER is None or cls.SENDER == role


# ---------------------------------------------------------------------------------------------
# framing


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: ``data`` without any 0x00 byte (no delimiter added)."""
    out = bytearray()
    chunks = bytes(data).split(b"\x00")
    last = len(chunks) - 1
    for i, block in enumerate(chunks):
        full = False
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
            full = True
        if block or not (full and i == last):  # a final 0xFF block needs no empty block after it
            out.append(len(block) + 1)
            out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises MessageError (a ValueError) on a zero byte or a truncated block."""
    if 0 in data:
        return _cobs_decode_long(data)  # raises, naming the offset
    n = len(data)
    chunks: list[bytes] = []
    append = chunks.append
    i = 0
    while i < n:  # fast path: blocks shorter than 254 bytes, each followed by an implied zero
        code = data[i]
        if code == 0xFF:
            return _cobs_decode_long(data)
        append(data[i + 1:i + code])
        i += code
    if i != n:
        return _cobs_decode_long(data)  # raises: the last block runs past the end
    return b"\x00".join(chunks)


def _cobs_decode_long(data: bytes) -> bytes:
    """cobs_decode for data with 254-byte blocks (never a frame of this protocol)."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise MessageError(f"zero byte inside a COBS frame at offset {i}")
        end = i + code
        if end > n:
            raise MessageError(f"COBS block at offset {i} wants {code - 1} bytes, {n - i - 1} left")
        out += data[i + 1:end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame: the message and the header fields that belong to the session."""

    message: Message
    seq: int = 0
    flags: int = 0
    version: int = VERSION


#: Messages whose layout is frozen across versions: read whatever version byte they carry.
FROZEN_TYPES = frozenset((MsgType.HELLO, MsgType.ACK, MsgType.NAK))


@dataclass(frozen=True, slots=True)
class DecodeError:
    """A stretch of bytes between delimiters that is not a message, and why.

    ``seq`` and ``msg_type`` are known (and ``nak`` set) only when the CRC was good, i.e. when the
    receiver can answer with a NAK.
    """

    reason: DecodeReason
    detail: str
    seq: int | None = None
    msg_type: int | None = None
    nak: NakReason | None = None


def encode_body(message: Message, seq: int = 0, flags: int = 0, version: int = VERSION) -> bytes:
    """The body of a frame (header, payload, CRC), before COBS: what the CRC covers.
    ``version``: the header's version byte (the session's; HELLO goes out as MIN_VERSION)."""
    if not isinstance(message, Message):
        raise MessageError(f"encode() wants a protocol message, got {type(message).__name__}")
    _int("frame", "seq", seq, 0, 0xFFFF, NakReason.BAD_PAYLOAD)
    _int("frame", "flags", flags, 0, 0xFF, NakReason.BAD_PAYLOAD)
    _int("frame", "version", version, MIN_VERSION, VERSION, NakReason.BAD_PAYLOAD)
    if message.since() > version:
        raise MessageError(f"{describe(message)} exists from protocol version "
                           f"{message.since()}; this session speaks {version}")
    payload = message.pack()
    if len(payload) > MAX_PAYLOAD:
        raise MessageError(f"{message.TYPE.name} payload is {len(payload)} bytes, at most "
                           f"{MAX_PAYLOAD} allowed")
    body = HEADER.pack(version, message.TYPE, seq, flags) + payload
    return body + crc16(body).to_bytes(2, "big")


def encode(message: Message, seq: int = 0, flags: int = 0, version: int = VERSION) -> bytes:
    """The bytes of one frame on the wire: COBS(body) followed by the 0x00 delimiter."""
    return cobs_encode(encode_body(message, seq, flags, version)) + b"\x00"


def decode_body(body: bytes) -> Frame | DecodeError:
    """Decode one frame body (COBS already removed): header, CRC, payload."""
    if len(body) < MIN_BODY:
        return DecodeError(DecodeReason.TOO_SHORT, f"{len(body)}-byte body, at least {MIN_BODY}")
    if binascii.crc_hqx(body, 0xFFFF):  # the CRC over data + big-endian CRC leaves 0
        return DecodeError(DecodeReason.BAD_CRC, f"CRC mismatch over {len(body)} bytes")
    version, mtype, seq, flags = HEADER.unpack_from(body)
    if not MIN_VERSION <= version <= VERSION and not (version and mtype in FROZEN_TYPES):
        return DecodeError(DecodeReason.BAD_VERSION, f"protocol version {version}, this end speaks "
                           f"{MIN_VERSION}..{VERSION}", seq, mtype, NakReason.BAD_VERSION)
    cls = CLASS_BY_TYPE.get(mtype)
    if cls is None or cls.SINCE > version:
        return DecodeError(DecodeReason.UNKNOWN_TYPE, f"unknown message type 0x{mtype:02X} "
                           f"in protocol version {version}", seq, mtype, NakReason.UNKNOWN_TYPE)
    try:
        message = cls.unpack(body[HEADER_SIZE:-CRC_SIZE])
    except MessageError as exc:
        return DecodeError(DecodeReason.BAD_PAYLOAD, str(exc), seq, mtype, NakReason(exc.reason))
    if message.since() > version:  # a later version's fields in an older frame
        return DecodeError(DecodeReason.BAD_PAYLOAD, f"{cls.TYPE.name} with the fields of "
                           f"protocol version {message.since()} in a version-{version} frame",
                           seq, mtype, NakReason.BAD_PAYLOAD)
    return Frame(message, seq, flags, version)


def decode(frame: bytes) -> Frame | DecodeError:
    """Decode the bytes of exactly one frame (with or without its trailing 0x00)."""
    if frame.endswith(b"\x00"):
        frame = frame[:-1]
    if b"\x00" in frame:
        return DecodeError(DecodeReason.BAD_COBS, "0x00 inside a frame: more than one frame given")
    if len(frame) > MAX_ENCODED:
        return DecodeError(DecodeReason.TOO_LONG, f"{len(frame)} bytes between delimiters, "
                           f"at most {MAX_ENCODED}")
    try:
        body = cobs_decode(frame)
    except ValueError as exc:
        return DecodeError(DecodeReason.BAD_COBS, str(exc))
    return decode_body(body)


class FrameDecoder:
    """Bytes in, frames and decode errors out; resynchronises on the next 0x00 after garbage.

    ``counts`` holds, per :class:`DecodeReason`, how many bad frames were seen; ``frames`` how many
    good ones.  Empty frames (0x00 0x00) are ignored: a sender may write a lone 0x00 to flush.
    Memory is bounded: at most MAX_ENCODED bytes are kept between calls.
    """

    def __init__(self) -> None:
        self._buf = b""
        self._skipping = False
        self.frames = 0
        self.counts: dict[DecodeReason, int] = {reason: 0 for reason in DecodeReason}

    @property
    def errors(self) -> int:
        """Bad frames seen so far, all reasons together."""
        return sum(self.counts.values())

    def reset(self) -> None:
        """Drop a partial frame (e.g. after the port was reopened)."""
        self._buf = b""
        self._skipping = False

    def feed(self, data: bytes) -> list[Frame | DecodeError]:
        """Consume ``data``; return every frame it completed, in order, good or bad."""
        parts = (self._buf + bytes(data)).split(b"\x00")
        self._buf = parts.pop()
        out: list[Frame | DecodeError] = []
        for part in parts:
            if self._skipping:  # the tail of an oversized frame already counted
                self._skipping = False
                continue
            if part:
                out.append(decode(part))
        if len(self._buf) > MAX_ENCODED:
            if not self._skipping:
                out.append(DecodeError(DecodeReason.TOO_LONG, f"more than {MAX_ENCODED} bytes "
                                       "without a delimiter; skipping to the next 0x00"))
                self._skipping = True
            self._buf = b""
        for item in out:
            if type(item) is Frame:
                self.frames += 1
            else:
                self.counts[item.reason] += 1
        return out


# ---------------------------------------------------------------------------------------------
# long change reports


@dataclass(frozen=True, slots=True)
class AssembledReport:
    """A whole change report, joined from its parts."""

    report_id: int
    station: str
    regions: tuple[Region, ...]


def split_change_report(report_id: int, station: str, regions: Iterable[Region]) -> list[ChangeReport]:
    """The CHANGE_REPORT parts of one report (one part with no region when nothing changed)."""
    regions = tuple(regions)
    chunks = [regions[i:i + REGIONS_PER_PART] for i in range(0, len(regions), REGIONS_PER_PART)] or [()]
    if len(chunks) > 255:
        raise MessageError(f"a report of {len(regions)} regions needs {len(chunks)} parts, at most "
                           f"255 ({255 * REGIONS_PER_PART} regions): send the largest regions only")
    return [ChangeReport(report_id, i, len(chunks), station, chunk) for i, chunk in enumerate(chunks)]


class ReportAssembler:
    """Joins CHANGE_REPORT parts (any order, duplicates ignored) into :class:`AssembledReport`.

    At most ``max_pending`` incomplete reports are kept; the oldest is dropped beyond that.
    """

    def __init__(self, max_pending: int = 4) -> None:
        self.max_pending = max_pending
        self._pending: dict[int, dict[int, ChangeReport]] = {}
        self.dropped = 0

    def add(self, part: ChangeReport) -> AssembledReport | None:
        """Add a part; return the whole report when this part completes it."""
        got = self._pending.get(part.report_id)
        if got:
            first = next(iter(got.values()))
            if (first.parts, first.station) != (part.parts, part.station):
                self.dropped += 1  # the id was reused for another report: start again
                got = None
        if got is None:
            self._pending.pop(part.report_id, None)
            got = self._pending[part.report_id] = {}
            while len(self._pending) > self.max_pending:
                del self._pending[next(iter(self._pending))]
                self.dropped += 1
        got[part.part] = part
        if len(got) < part.parts:
            return None
        del self._pending[part.report_id]
        regions = tuple(r for i in range(part.parts) for r in got[i].regions)
        return AssembledReport(part.report_id, part.station, regions)


# ---------------------------------------------------------------------------------------------
# readable form


def describe(message: Message) -> str:
    """One line for people: ``PAUSE cause=CHANGE_CHECK``."""
    parts = [message.TYPE.name]
    for f in fields(message):  # type: ignore[arg-type]
        value = getattr(message, f.name)
        if value is None:  # a field of a later version, left out
            continue
        if isinstance(value, IntEnum):
            value = value.name
        elif f.name == "param" and value in PARAM_BY_ID:
            value = PARAM_BY_ID[value].name
        elif f.name == "refused_type":
            value = MsgType(value).name if value in CLASS_BY_TYPE else f"0x{value:02X}"
        elif f.name == "boot_id":
            value = f"0x{value:08X}"
        elif f.name == "regions":
            value = len(value)
        elif isinstance(value, bytes):
            value = value.hex()
        elif f.name == "missing":
            value = ",".join(map(str, value))
        elif isinstance(value, str):
            value = repr(value) if (not value or " " in value) else value
        parts.append(f"{f.name}={value}")
    return " ".join(parts)
