"""Wire format between the module and the base controller, sans-IO: bytes <-> messages.

No ports, no threads, no clocks: :func:`encode` turns a message into the bytes of one frame and
:class:`FrameDecoder` turns any stream of bytes into frames and counted decode errors.  The
session (sequence numbers, acks, retries, heartbeats) lives in :mod:`robot_change.link.session`.

A frame on the wire is ``COBS(body) 0x00``; the body is::

    version u8 | type u8 | seq u16 LE | flags u8 | payload (0..240 bytes) | CRC-16 u16 BE

with CRC-16/CCITT-FALSE (``binascii.crc_hqx(data, 0xFFFF)``) over everything before it.  Every
multi-byte field of a payload is little-endian.  docs/protocol.md is the specification; its hex
examples are checked by the tests against this module.

The format is built in layers, one job each; every public name is re-exported here, so import
from this module: :mod:`~robot_change.link.codes` (versions, limits, codes, the parameter
whitelist), :mod:`~robot_change.link.messages` (the Message base, field checks, HELLO, ACK,
NAK), :mod:`~robot_change.link.module_messages` and :mod:`~robot_change.link.base_messages`
(what each end sends), :mod:`~robot_change.link.codec` (framing, encode/decode, PARTs,
:func:`describe`).
"""

from __future__ import annotations

from robot_change.errors import MessageError
from robot_change.link.base_messages import (
    Arm,
    BaseHeartbeat,
    CaptureReference,
    Check,
    Disarm,
    GetParam,
    Need,
    Resume,
    SetParam,
    StatusQuery,
    Stop,
    Watch,
)
from robot_change.link.codec import (
    CLASS_BY_NAME,
    CLASS_BY_TYPE,
    FROZEN_TYPES,
    MESSAGE_CLASSES,
    DecodeError,
    Frame,
    FrameDecoder,
    cobs_decode,
    cobs_encode,
    crc16,
    decode,
    decode_body,
    describe,
    encode,
    encode_body,
    split_body,
)
from robot_change.link.codes import (
    CRC_SIZE,
    FLAG_RETRY,
    FLAG_URGENT,
    HEADER,
    HEADER_SIZE,
    MAX_BODY,
    MAX_ENCODED,
    MAX_PARTS,
    MAX_PAYLOAD,
    MAX_STATION,
    MIN_BODY,
    MIN_VERSION,
    PARAM_BY_ID,
    PARAM_BY_NAME,
    PARAMS,
    PART_DATA,
    REGIONS_PER_PART,
    URGENT_COPIES,
    V1_FAULT_CODE,
    V1_PAUSE_CAUSE,
    VERSION,
    WEAK_BITS,
    CheckOutcome,
    DecodeReason,
    FaultCode,
    ModuleState,
    Motion,
    MsgType,
    NakReason,
    Param,
    PauseCause,
    RegionKind,
    Role,
)
from robot_change.link.messages import (
    Ack,
    Hello,
    Message,
    Nak,
    may_send,
)
from robot_change.link.module_messages import (
    AssembledReport,
    Captured,
    ChangeReport,
    CheckResult,
    Clear,
    Fault,
    Heartbeat,
    ParamValue,
    Part,
    Pause,
    Region,
    ReportAssembler,
    Status,
    split_change_report,
)

__all__ = [
    # codes
    "CRC_SIZE", "FLAG_RETRY", "FLAG_URGENT", "HEADER", "HEADER_SIZE", "MAX_BODY", "MAX_ENCODED",
    "MAX_PARTS", "MAX_PAYLOAD", "MAX_STATION", "MIN_BODY", "MIN_VERSION", "PARAMS", "PARAM_BY_ID",
    "PARAM_BY_NAME", "PART_DATA", "REGIONS_PER_PART", "URGENT_COPIES", "V1_FAULT_CODE",
    "V1_PAUSE_CAUSE", "VERSION", "WEAK_BITS", "CheckOutcome", "DecodeReason", "FaultCode",
    "ModuleState", "Motion", "MsgType", "NakReason", "Param", "PauseCause", "RegionKind", "Role",
    # messages
    "Ack", "Hello", "Message", "Nak", "may_send", "MessageError",
    # module_messages
    "AssembledReport", "Captured", "ChangeReport", "CheckResult", "Clear", "Fault", "Heartbeat",
    "ParamValue", "Part", "Pause", "Region", "ReportAssembler", "Status", "split_change_report",
    # base_messages
    "Arm", "BaseHeartbeat", "CaptureReference", "Check", "Disarm", "GetParam", "Need", "Resume",
    "SetParam", "StatusQuery", "Stop", "Watch",
    # codec
    "CLASS_BY_NAME", "CLASS_BY_TYPE", "FROZEN_TYPES", "MESSAGE_CLASSES", "DecodeError", "Frame",
    "FrameDecoder", "cobs_decode", "cobs_encode", "crc16", "decode", "decode_body", "describe",
    "encode", "encode_body", "split_body",
]
