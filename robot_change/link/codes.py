"""The wire format's numbers: protocol versions and size limits, the codes of message types,
reasons, states and causes, and the whitelist of parameters the base may read or set.

Part of :mod:`robot_change.link.protocol`, which re-exports every name; docs/protocol.md is the
specification.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import Enum, IntEnum

from robot_change import validate

#: The highest protocol version this end speaks, and the lowest (docs/protocol.md 7.5).
VERSION = 5
MIN_VERSION = 1
MAX_PAYLOAD = 240
HEADER = struct.Struct("<BBHB")
HEADER_SIZE = HEADER.size  # 5
CRC_SIZE = 2
MIN_BODY = HEADER_SIZE + CRC_SIZE  # 7
MAX_BODY = MIN_BODY + MAX_PAYLOAD  # 247
#: Longest COBS-encoded body (without the 0x00 delimiter): one overhead byte below 254 bytes.
MAX_ENCODED = MAX_BODY + 1  # 248
#: Urgent frames (PAUSE, RESUME, HELLO) are written this many times in a row, and so are their ACKs.
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
