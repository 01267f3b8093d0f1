"""Matroska as the Azure Kinect recorder writes it (``k4arecorder``, the SDK's ``k4arecord``;
Orbbec's Femto cameras record the same through their K4A wrapper): read from the file as it is
walked, so an hour of recording is never held in memory.

The file is an EBML document: an ``EBML`` header, then a ``Segment`` holding ``Info`` (the
timecode scale), ``Tracks`` (one ``TrackEntry`` a track: number, name ``COLOR`` / ``DEPTH`` /
``IR`` / ``IMU``, codec, picture size), ``Tags`` (``K4A_DEPTH_MODE``,
``K4A_DEVICE_SERIAL_NUMBER``, ...), ``Attachments`` (the factory calibration,
``calibration.json``) and ``Cluster`` s (a ``Timecode`` and ``SimpleBlock`` s or ``BlockGroup``
/ ``Block`` s, each naming its track).  The DEPTH track's codec is ``V_MS/VFW/FOURCC`` with the
four-character code ``b16g``: 16-bit **big-endian** grey, millimetres, 0 = no reading.

Every element is an id (a variable-length integer keeping its marker bit, 1-4 bytes) and a size
(one without it, 1-8 bytes; all value bits set = unknown size, allowed for the Segment and
Clusters of a recording written as a stream: such an element ends where an element that cannot
be its child begins, or at the end of its parent).

A missing file, one that is not such a recording (truncated, another format, no DEPTH track, a
depth block of the wrong size) raises :class:`hw.errors.DepthFileError` naming the file.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hw.errors import DepthFileError

__all__ = ["DepthBlock", "MkvFile", "MkvTrack"]

# EBML / Matroska element ids (with their marker bits, as written in the file)
EBML = 0x1A45DFA3
DOC_TYPE = 0x4282
SEGMENT = 0x18538067
SEEK_HEAD = 0x114D9B74
INFO = 0x1549A966
TIMECODE_SCALE = 0x2AD7B1
TRACKS = 0x1654AE6B
TRACK_ENTRY = 0xAE
TRACK_NUMBER = 0xD7
TRACK_NAME = 0x536E
CODEC_ID = 0x86
CODEC_PRIVATE = 0x63A2
VIDEO = 0xE0
PIXEL_WIDTH = 0xB0
PIXEL_HEIGHT = 0xBA
CLUSTER = 0x1F43B675
CLUSTER_TIMECODE = 0xE7
SIMPLE_BLOCK = 0xA3
BLOCK_GROUP = 0xA0
BLOCK = 0xA1
CUES = 0x1C53BB6B
ATTACHMENTS = 0x1941A469
ATTACHED_FILE = 0x61A7
FILE_NAME = 0x466E
FILE_DATA = 0x465C
CHAPTERS = 0x1043A770
TAGS = 0x1254C367
TAG = 0x7373
SIMPLE_TAG = 0x67C8
TAG_NAME = 0x45A3
TAG_STRING = 0x4487

#: The Segment's children: an unknown-size Cluster ends where one of these begins.
_SEGMENT_CHILDREN = frozenset((SEEK_HEAD, INFO, TRACKS, CLUSTER, CUES, ATTACHMENTS, CHAPTERS,
                               TAGS))
#: Top-level elements: an unknown-size Segment ends where one of these begins.
_TOP_LEVEL = frozenset((EBML, SEGMENT))
#: The largest attachment or codec field read into memory (a calibration is ~3 kB), bytes.
_SMALL = 1 << 20


@dataclasses.dataclass(frozen=True)
class MkvTrack:
    """One ``TrackEntry``: its ``number``, ``name`` ("DEPTH", ...), ``codec`` id, the
    four-character code of a ``V_MS/VFW/FOURCC`` track (``fourcc``, else ""), and the picture
    size (``width``, ``height``; 0 for a track without video settings)."""

    number: int
    name: str
    codec: str
    fourcc: str
    width: int
    height: int


@dataclasses.dataclass(frozen=True)
class DepthBlock:
    """Where one frame of a track lies: ``timestamp_us`` (its time in the recording, µs),
    ``offset`` and ``size`` of its bytes in the file."""

    timestamp_us: int
    offset: int
    size: int


@dataclasses.dataclass(frozen=True)
class _Element:
    id: int
    start: int       # offset of the id
    data: int        # offset of the payload
    end: int | None  # offset after the payload; None: unknown size


class MkvFile:
    """An open recording: :meth:`tracks`, :meth:`tags`, :meth:`attachment`, :meth:`blocks`
    (walked from the file as they are asked for) and :meth:`frame` (one block's picture).
    Opening reads the EBML header and checks it is a Matroska document.  Use it in a ``with``
    block, or :meth:`close` it."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.name = str(path)
        try:
            self._file: BinaryIO = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        except FileNotFoundError:
            raise DepthFileError(f"{path}: no such recording") from None
        except IsADirectoryError:
            raise DepthFileError(f"{path}: a folder, not an Azure Kinect recording (.mkv)") \
                from None
        except OSError as exc:
            raise DepthFileError(f"{path}: cannot be opened: {exc.strerror}") from exc
        try:
            self.size = self.path.stat().st_size
            self._segment = self._find_segment()
            self._scale_ns = self._timecode_scale_ns()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> MkvFile:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file.  Safe to repeat."""
        self._file.close()

    def fail(self, what: str) -> DepthFileError:
        return DepthFileError(f"{self.name}: not a readable Azure Kinect recording (Matroska): "
                              f"{what}")

    # the bytes ---------------------------------------------------------------------------
    def read_at(self, pos: int, size: int) -> bytes:
        """``size`` bytes at ``pos`` (fewer at the end of the file)."""
        self._file.seek(pos)
        return self._file.read(size)

    def _vint(self, pos: int, limit: int, keep_marker: bool, what: str
              ) -> tuple[int, int, bool]:
        """(value, length, all value bits set) of the variable-length integer at ``pos``."""
        if pos >= limit:
            raise self.fail(f"{what} at byte {pos} runs past the end (file truncated?)")
        head = self.read_at(pos, min(8, limit - pos))
        first = head[0] if head else 0
        if not head:
            raise self.fail(f"{what} at byte {pos} runs past the end (file truncated?)")
        if first == 0:
            raise self.fail(f"{what} at byte {pos} has no length marker (a corrupt file)")
        length = 9 - first.bit_length()
        if length > (4 if keep_marker else 8):
            raise self.fail(f"{what} at byte {pos} is {length} bytes long (at most "
                            f"{4 if keep_marker else 8})")
        if length > len(head):
            raise self.fail(f"{what} at byte {pos} runs past the end (file truncated?)")
        value = int.from_bytes(head[:length], "big")
        marker = 1 << (7 * length)
        ones = (value ^ marker) == marker - 1
        return (value if keep_marker else value ^ marker), length, ones

    def _element(self, pos: int, limit: int) -> _Element:
        eid, n_id, _ = self._vint(pos, limit, True, "element id")
        size, n_size, unknown = self._vint(pos + n_id, limit, False,
                                           f"size of element 0x{eid:X}")
        data = pos + n_id + n_size
        if unknown:
            if eid not in (SEGMENT, CLUSTER):
                raise self.fail(f"element 0x{eid:X} at byte {pos} has an unknown size (only "
                                "the Segment and Clusters may)")
            return _Element(eid, pos, data, None)
        if data + size > limit:
            raise self.fail(f"element 0x{eid:X} at byte {pos} claims {size} bytes, only "
                            f"{limit - data} are left (file truncated?)")
        return _Element(eid, pos, data, data + size)

    def _children(self, parent: _Element, limit: int | None = None) -> Iterator[_Element]:
        """The child elements of a master element (one of unknown size ends where an element
        that cannot be its child begins, or at ``limit``, the end of its parent)."""
        stop_ids = _TOP_LEVEL if parent.id == SEGMENT else \
            (_SEGMENT_CHILDREN | _TOP_LEVEL) if parent.id == CLUSTER else frozenset()
        bound = (self.size if limit is None else limit) if parent.end is None else parent.end
        pos = parent.data
        while pos < bound:
            if parent.end is None:
                eid, _, _ = self._vint(pos, bound, True, "element id")
                if eid in stop_ids:
                    return
            el = self._element(pos, bound)
            yield el
            pos = el.end if el.end is not None else self._end_of(el, bound)

    def _end_of(self, el: _Element, limit: int) -> int:
        """Where an unknown-size element ends (walking its children)."""
        pos = el.data
        for child in self._children(el, limit):
            pos = child.end if child.end is not None else self._end_of(child, limit)
        return pos

    def _payload(self, el: _Element) -> bytes:
        assert el.end is not None
        if el.end - el.data > _SMALL:
            raise self.fail(f"element 0x{el.id:X} at byte {el.start} holds "
                            f"{el.end - el.data} bytes, more than a field may")
        return self.read_at(el.data, el.end - el.data)

    def _uint(self, el: _Element) -> int:
        return int.from_bytes(self._payload(el), "big")

    def _text(self, el: _Element) -> str:
        return self._payload(el).rstrip(b"\0").decode("utf-8", "replace")

    # the document ------------------------------------------------------------------------
    def _find_segment(self) -> _Element:
        """The Segment after the EBML header (checked to be a Matroska document)."""
        if self.size < 4 or int.from_bytes(self.read_at(0, 4), "big") != EBML:
            raise self.fail("no EBML header (another format)")
        header = self._element(0, self.size)
        doc_type = next((self._text(c) for c in self._children(header) if c.id == DOC_TYPE),
                        "")
        if doc_type not in ("matroska", "webm"):
            raise self.fail(f"EBML document of type {doc_type!r}, not matroska")
        pos = header.end
        assert pos is not None
        while pos < self.size:
            el = self._element(pos, self.size)
            if el.id == SEGMENT:
                return el
            if el.end is None:
                break
            pos = el.end
        raise self.fail("no Segment after the EBML header")

    def _before_clusters(self, wanted: int) -> Iterator[_Element]:
        """The Segment's ``wanted`` children that stand before its first Cluster (where
        ``k4arecord`` writes Info, Tracks, Tags and Attachments)."""
        for el in self._children(self._segment):
            if el.id == CLUSTER:
                return
            if el.id == wanted:
                yield el

    def _timecode_scale_ns(self) -> int:
        for info in self._before_clusters(INFO):
            for c in self._children(info):
                if c.id == TIMECODE_SCALE:
                    return self._uint(c)
        return 1_000_000  # Matroska's default: milliseconds

    def tracks(self) -> list[MkvTrack]:
        """The recording's tracks, in file order."""
        for el in self._before_clusters(TRACKS):
            return [self._track(entry) for entry in self._children(el)
                    if entry.id == TRACK_ENTRY]
        raise self.fail("no Tracks element before the first Cluster")

    def _track(self, entry: _Element) -> MkvTrack:
        fields = {"number": 0, "name": "", "codec": "", "fourcc": "", "width": 0, "height": 0}
        for c in self._children(entry):
            if c.id == TRACK_NUMBER:
                fields["number"] = self._uint(c)
            elif c.id == TRACK_NAME:
                fields["name"] = self._text(c)
            elif c.id == CODEC_ID:
                fields["codec"] = self._text(c)
            elif c.id == CODEC_PRIVATE:
                # V_MS/VFW/FOURCC: a BITMAPINFOHEADER, biCompression at bytes 16-19
                private = self._payload(c)
                if len(private) >= 20:
                    fields["fourcc"] = private[16:20].decode("latin-1")
            elif c.id == VIDEO:
                for v in self._children(c):
                    if v.id == PIXEL_WIDTH:
                        fields["width"] = self._uint(v)
                    elif v.id == PIXEL_HEIGHT:
                        fields["height"] = self._uint(v)
        return MkvTrack(**fields)

    def tags(self) -> dict[str, str]:
        """The simple tags (``K4A_DEPTH_MODE`` -> ``NFOV_UNBINNED``, ...), first of a name."""
        out: dict[str, str] = {}
        for tags in self._before_clusters(TAGS):
            for tag in (t for t in self._children(tags) if t.id == TAG):
                for simple in (c for c in self._children(tag) if c.id == SIMPLE_TAG):
                    name = value = None
                    for c in self._children(simple):
                        if c.id == TAG_NAME:
                            name = self._text(c)
                        elif c.id == TAG_STRING:
                            value = self._text(c)
                    if name and value is not None:
                        out.setdefault(name, value)
        return out

    def attachment(self, file_name: str) -> bytes | None:
        """The bytes of the attached file ``file_name`` (``calibration.json``), or None."""
        for attachments in self._before_clusters(ATTACHMENTS):
            for attached in self._children(attachments):
                if attached.id != ATTACHED_FILE:
                    continue
                fields = {c.id: c for c in self._children(attached)}
                if FILE_NAME in fields and self._text(fields[FILE_NAME]) == file_name \
                        and FILE_DATA in fields:
                    return self._payload(fields[FILE_DATA])
        return None

    def blocks(self, track: MkvTrack) -> Iterator[DepthBlock]:
        """Every frame of ``track``, in file order, found as the Clusters are walked (laced
        blocks raise: k4arecord's video tracks are never laced)."""
        for cluster in self._children(self._segment):
            if cluster.id != CLUSTER:
                continue
            base = 0
            for el in self._children(cluster, self._segment.end or self.size):
                if el.id == CLUSTER_TIMECODE:
                    base = self._uint(el)
                elif el.id == SIMPLE_BLOCK:
                    block = self._block(el, base, track.number)
                    if block is not None:
                        yield block
                elif el.id == BLOCK_GROUP:
                    for c in self._children(el):
                        block = self._block(c, base, track.number) if c.id == BLOCK else None
                        if block is not None:
                            yield block

    def _block(self, el: _Element, base: int, number: int) -> DepthBlock | None:
        """The frame in a SimpleBlock / Block when it is track ``number``'s."""
        assert el.end is not None
        track, n, _ = self._vint(el.data, el.end, False, "block track number")
        if track != number:
            return None
        head = el.data + n
        if head + 3 > el.end:
            raise self.fail(f"block at byte {el.start} is shorter than its header")
        raw = self.read_at(head, 3)
        (relative,) = struct.unpack(">h", raw[:2])
        if raw[2] & 0x06:
            raise self.fail(f"block at byte {el.start} (track {track}) is laced; a recording "
                            "holds one frame a block")
        return DepthBlock((base + relative) * self._scale_ns // 1000, head + 3,
                          el.end - head - 3)

    def frame(self, block: DepthBlock, track: MkvTrack) -> np.ndarray:
        """(H, W) uint16 of a ``b16g`` block (big-endian in the file)."""
        expected = 2 * track.width * track.height
        if block.size != expected:
            raise self.fail(f"a {track.name} block holds {block.size} bytes, a {track.width} "
                            f"x {track.height} 16-bit frame is {expected}")
        data = self.read_at(block.offset, block.size)
        if len(data) != expected:
            raise self.fail(f"a {track.name} block at byte {block.offset} is cut short (file "
                            "truncated?)")
        return np.frombuffer(data, ">u2").reshape(track.height, track.width).astype(np.uint16)
