"""Bytes <-> messages: the table of message classes by type code, COBS framing, the CRC,
encode and decode of one frame, the streaming :class:`FrameDecoder`, the PARTs that carry one
frame body (version 3), and :func:`describe`, the readable form of a message.

Part of :mod:`robot_change.link.protocol`, which re-exports every public name.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass, fields
from enum import IntEnum

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
from robot_change.link.codes import (
    CRC_SIZE,
    HEADER,
    HEADER_SIZE,
    MAX_BODY,
    MAX_ENCODED,
    MAX_PAYLOAD,
    MIN_BODY,
    MIN_VERSION,
    PARAM_BY_ID,
    PART_DATA,
    VERSION,
    DecodeReason,
    MsgType,
    NakReason,
)
from robot_change.link.messages import Ack, Hello, Message, Nak, _int
from robot_change.link.module_messages import (
    Captured,
    ChangeReport,
    CheckResult,
    Clear,
    Fault,
    Heartbeat,
    ParamValue,
    Part,
    Pause,
    Status,
)

# ---------------------------------------------------------------------------------------------
# message classes by type code


MESSAGE_CLASSES: tuple[type[Message], ...] = (
    Hello, Ack, Nak, Heartbeat, Pause, ChangeReport, Clear, Fault, Status, ParamValue, Captured,
    CheckResult, BaseHeartbeat, StatusQuery, CaptureReference, Check, Watch, Stop, Arm, Disarm,
    Resume, SetParam, GetParam, Part, Need,
)
CLASS_BY_TYPE: dict[int, type[Message]] = {cls.TYPE: cls for cls in MESSAGE_CLASSES}
CLASS_BY_NAME: dict[str, type[Message]] = {cls.TYPE.name: cls for cls in MESSAGE_CLASSES}


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
    """Inverse of :func:`cobs_encode`; raises MessageError (a ValueError) on a zero byte or a
    truncated block."""
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
# carried bodies (version 3)


def split_body(body: bytes) -> list[Part]:
    """The PARTs that carry ``body`` (a whole frame body, header and CRC included)."""
    if not MIN_BODY <= len(body) <= MAX_BODY:
        raise MessageError(f"a carried body is {MIN_BODY}..{MAX_BODY} bytes, got {len(body)}")
    chunks = [body[i:i + PART_DATA] for i in range(0, len(body), PART_DATA)]
    return [Part(i, len(chunks), chunk) for i, chunk in enumerate(chunks)]


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
