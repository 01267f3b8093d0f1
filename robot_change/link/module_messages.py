"""The messages the module sends to the base (type codes 0x10..): HEARTBEAT, PAUSE,
CHANGE_REPORT and its regions, CLEAR, CHECK_RESULT, FAULT, STATUS, PARAM_VALUE, CAPTURED and
PART; and the splitting and joining of a change report too long for one frame.

Part of :mod:`robot_change.link.protocol`, which re-exports every public name.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar

from robot_change.errors import MessageError
from robot_change.link.codes import (
    MAX_PARTS,
    PART_DATA,
    REGIONS_PER_PART,
    CheckOutcome,
    FaultCode,
    ModuleState,
    MsgType,
    NakReason,
    PauseCause,
    RegionKind,
    Role,
)
from robot_change.link.messages import (
    Message,
    _bool,
    _enum,
    _exact,
    _int,
    _ParamValueMsg,
    _read_str,
    _set,
    _station,
    _StationMsg,
    _str8,
    _text,
)

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
        return cls(state, bool(flags & _PAUSED), bool(flags & _ARMED), bool(flags & _FAULT),
                   fps, frame)


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
    def unpack_many(cls, data: bytes) -> tuple[Region, ...]:
        """Regions packed back to back.  struct already bounds every number; only kind is
        checked."""
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
                               f"{REGIONS_PER_PART}: use split_change_report()",
                               NakReason.BAD_PAYLOAD)
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
class Part(Message):
    """Module -> base (version 3; both ways from version 5): part ``index`` of ``count`` of
    the body of a sequenced message, whose seq is this frame's header seq (docs/protocol.md
    7.11).  Not acknowledged itself: the carried message is, once the peer has joined every
    part."""

    TYPE: ClassVar[MsgType] = MsgType.PART
    SEQUENCED: ClassVar[bool] = False
    SENDER: ClassVar[Role | None] = Role.MODULE
    BOTH_WAYS_SINCE: ClassVar[int | None] = 5
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


# ---------------------------------------------------------------------------------------------
# long change reports


@dataclass(frozen=True, slots=True)
class AssembledReport:
    """A whole change report, joined from its parts."""

    report_id: int
    station: str
    regions: tuple[Region, ...]


def split_change_report(report_id: int, station: str,
                        regions: Iterable[Region]) -> list[ChangeReport]:
    """The CHANGE_REPORT parts of one report (one part with no region when nothing changed)."""
    regions = tuple(regions)
    chunks = [regions[i:i + REGIONS_PER_PART]
              for i in range(0, len(regions), REGIONS_PER_PART)] or [()]
    if len(chunks) > 255:
        raise MessageError(f"a report of {len(regions)} regions needs {len(chunks)} parts, at most "
                           f"255 ({255 * REGIONS_PER_PART} regions): send the largest regions only")
    return [ChangeReport(report_id, i, len(chunks), station, chunk)
            for i, chunk in enumerate(chunks)]


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
