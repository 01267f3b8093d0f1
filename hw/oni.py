"""Writing and checking OpenNI ``.oni`` recordings without a camera or the native library.

An ``.oni`` file (format version 1.0.1.0, what OpenNI2's own recorder writes) is a 24-byte file
header followed by records.  Every record starts with a 28-byte header::

    magic "NIR\\0" | record type u32 | node id u32 | fields size u32 (incl. this header)
    | payload size u32 | undo position u64            (little endian, packed)

A depth recording made here holds one depth node (id 1)::

    NodeAdded        name "Depth", type depth, codec, frame count, min/max timestamp,
                     position of the seek table (patched when the file is finished)
    properties       xnMapOutputMode (W, H, fps), xnCropping (off), oniPixelFormat (1 mm),
                     xnFOV (from the intrinsics), xnDeviceMaxDepth, ...
    NodeStateReady
    NodeDataBegin    frame count, max timestamp
    NewData x N      timestamp (us), frame id (1..N), the frame (raw or compressed)
    SeekTable        (N + 1) x (timestamp u64, configuration id u32, record position u64)
    End

OpenNI2's player needs ``xnCropping``: without it it silently drops every frame.  Three codecs:
``"none"`` (raw little-endian uint16, 614 KB per VGA frame), ``"16z"`` (OpenNI's lossless
``16zP`` depth coding: differences between neighbouring pixels in nibbles, runs of equal pixels
collapsed; values up to 32767 mm) and ``"16zt"`` (OpenNI's ``16zT``: the frame's distinct
values in a table, then ``16zP`` over table indices; any uint16 value, at most 32768 distinct
values per frame).  Kinect depth is quantised, so neighbouring pixels are mostly 0 or 1 table
step apart and ``16zt`` is the smallest: 156 KB vs 374 KB (16z) per VGA Kinect-noise frame.

:func:`read_oni_header` checks a file's structure (cheaply, by walking the record headers) so a
missing, truncated or foreign file gives :class:`hw.errors.DepthFileError` before the native
player sees it.  :func:`read_oni_frames` decodes a recording's depth frames (all three codecs)
without the native library -- for fixtures and tests; cameras and players go through
``hw.openni2``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from pathlib import Path
from typing import BinaryIO, Callable, Iterable

import numpy as np
from numba import njit

from hw.atomic import AtomicFile
from hw.depth import DepthFrame, Intrinsics
from hw.errors import DepthFileError, FrameError

# --- container constants (OpenNI2 Source/Drivers/OniFile/DataRecords.h) ---------------------
_FILE_HEADER = struct.Struct("<4sBBHIQI")  # magic, version (major, minor, maint, build), max ts, max node id
_RECORD_HEADER = struct.Struct("<IIIIIQ")  # magic, type, node id, fields size, payload size, undo pos
_SEEK_ENTRY = struct.Struct("<QIQ")  # timestamp, configuration id, record position
FILE_MAGIC = b"NI10"
RECORD_MAGIC = 0x0052494E  # "NIR\0"
FORMAT_VERSION = (1, 0, 1, 0)
OLDEST_VERSION = (1, 0, 0, 4)
FIRST_64BIT_VERSION = (1, 0, 1, 0)

REC_NODE_ADDED_1_0_0_4 = 0x02
REC_INT_PROPERTY = 0x03
REC_REAL_PROPERTY = 0x04
REC_STRING_PROPERTY = 0x05
REC_GENERAL_PROPERTY = 0x06
REC_NODE_REMOVED = 0x07
REC_NODE_DATA_BEGIN = 0x08
REC_NODE_STATE_READY = 0x09
REC_NEW_DATA = 0x0A
REC_END = 0x0B
REC_NODE_ADDED_1_0_0_5 = 0x0C
REC_NODE_ADDED = 0x0D
REC_SEEK_TABLE = 0x0E
_KNOWN_RECORDS = {
    REC_NODE_ADDED_1_0_0_4, REC_INT_PROPERTY, REC_REAL_PROPERTY, REC_STRING_PROPERTY,
    REC_GENERAL_PROPERTY, REC_NODE_REMOVED, REC_NODE_DATA_BEGIN, REC_NODE_STATE_READY,
    REC_NEW_DATA, REC_END, REC_NODE_ADDED_1_0_0_5, REC_NODE_ADDED, REC_SEEK_TABLE,
}

NODE_TYPE_DEPTH = 2
ONI_PIXEL_FORMAT_DEPTH_1_MM = 100
XN_PIXEL_FORMAT_GRAYSCALE_16_BIT = 4
DEPTH_NODE_ID = 1
#: The player's record buffer: 1600 x 1200 x 3 bytes of frame data.
PLAYER_MAX_FRAME_BYTES = 1600 * 1200 * 3

#: codec name -> the four-character id stored in the NodeAdded record
CODECS: dict[str, bytes] = {"none": b"NONE", "16z": b"16zP", "16zt": b"16zT"}
_CODEC_NAMES = {value: key for key, value in CODECS.items()}
#: Largest depth value (mm) the 16z codec can store.
MAX_16Z_VALUE = 0x7FFF
#: Most distinct depth values one 16zt frame can hold (its indices are 16z-coded, so < 0x8000).
MAX_16ZT_VALUES = MAX_16Z_VALUE + 1


# --- 16z depth coding ---------------------------------------------------------------------------
def encode_16z(depth: np.ndarray) -> bytes:
    """OpenNI's lossless ``16zP`` coding of a depth image.

    ``depth``: (H, W) or flat uint16, values 0..32767 (mm).  Returns the payload bytes the
    OniFile player decodes back to exactly ``depth``.  Layout: the first pixel as little-endian
    uint16, then tokens over the differences ``d = previous - current``: a byte
    ``(d1 + 6) << 4 | (d2 + 6)`` for two differences in -6..6; low nibble ``0xD`` for a single
    one; low nibble ``0xF`` or a whole ``0xFF`` byte introduces a larger step, ``d + 192`` (one
    byte, |d| <= 63) or the new value big-endian (two bytes, < 0x8000); ``0xE0 + n`` repeats
    the previous pixel 2n times.  Pixels are paired in order so that the whole encoding is a
    few vectorised passes (about 10 ms for VGA).
    """
    values = np.ascontiguousarray(depth, dtype=np.uint16).ravel()
    if values.size == 0:
        return b""
    top = int(values.max())
    if top > MAX_16Z_VALUE:
        raise FrameError(
            f"depth value {top} mm does not fit the 16z codec (at most {MAX_16Z_VALUE} mm); "
            "clip the image or write it with codec='none'"
        )
    first = struct.pack("<H", int(values[0]))
    v = values.astype(np.int32)
    diffs = v[:-1] - v[1:]
    news = v[1:]
    count = diffs.size
    n_pairs = count // 2
    parts = [first]
    if n_pairs:
        parts.append(_encode_pairs(diffs[: 2 * n_pairs].reshape(-1, 2), news[: 2 * n_pairs].reshape(-1, 2)))
    if count % 2:
        d, new = int(diffs[-1]), int(news[-1])
        if abs(d) <= 6:
            parts.append(bytes([((d + 6) << 4) | 0x0D]))
        elif abs(d) <= 63:
            parts.append(bytes([0xFF, d + 192]))
        else:
            parts.append(bytes([0xFF, new >> 8, new & 0xFF]))
    return b"".join(parts)


def encode_16zt(depth: np.ndarray) -> bytes:
    """OpenNI's lossless ``16zT`` coding ("16z with embedded table") of a depth image.

    ``depth``: (H, W) or flat uint16 (mm, any value 0..65535) with at most
    :data:`MAX_16ZT_VALUES` distinct values.  Layout (little-endian): the table length ``n``
    (uint16), the ``n`` distinct values in increasing order (uint16 each), then the
    :func:`encode_16z` stream of the image of table indices (first index as uint16, then
    tokens).  A VGA Kinect frame has a few hundred distinct values, so the table costs ~1 KB and
    neighbouring indices differ by 0 or 1 where raw millimetres jump by a quantisation step.
    Raises :class:`FrameError` for more distinct values than the index stream can address.
    """
    values = np.ascontiguousarray(depth, dtype=np.uint16).ravel()
    if values.size == 0:
        return b""
    present = np.zeros(0x10000, dtype=bool)
    present[values] = True
    table = np.flatnonzero(present).astype("<u2")
    if table.size > MAX_16ZT_VALUES:
        raise FrameError(
            f"the frame has {table.size} distinct depth values; the 16zt codec holds at most "
            f"{MAX_16ZT_VALUES} per frame (real depth has a few thousand at most): write it "
            "with codec='16z' (values <= 32767 mm) or codec='none'"
        )
    lookup = (np.cumsum(present) - 1).astype(np.uint16)  # value -> its index in the table
    return struct.pack("<H", table.size) + table.tobytes() + encode_16z(lookup[values])


def _encode_pairs(d: np.ndarray, new: np.ndarray) -> bytes:
    """Tokens for pairs of differences ``d`` (P, 2) int32 with new values ``new`` (P, 2)."""
    small = np.abs(d) <= 6
    medium = ~small & (np.abs(d) <= 63)
    big = ~small & ~medium
    a_s, b_s = small[:, 0], small[:, 1]
    out = np.zeros((d.shape[0], 7), dtype=np.uint8)
    use = np.zeros((d.shape[0], 7), dtype=bool)

    def token(col: int, first_slot: int, rows: np.ndarray) -> None:
        # a large step's token: d + 192 (1 byte) or the new value big-endian (2 bytes)
        m = rows & medium[:, col]
        out[m, first_slot] = (d[m, col] + 192).astype(np.uint8)
        use[m, first_slot] = True
        g = rows & big[:, col]
        out[g, first_slot] = (new[g, col] >> 8).astype(np.uint8)
        out[g, first_slot + 1] = (new[g, col] & 0xFF).astype(np.uint8)
        use[g, first_slot] = use[g, first_slot + 1] = True

    # small, small: one byte
    ss = a_s & b_s
    out[ss, 0] = (((d[ss, 0] + 6) << 4) | (d[ss, 1] + 6)).astype(np.uint8)
    use[ss, 0] = True
    # small, large: (a + 6) << 4 | 0xF, then b's token
    sl = a_s & ~b_s
    out[sl, 0] = (((d[sl, 0] + 6) << 4) | 0x0F).astype(np.uint8)
    use[sl, 0] = True
    token(1, 1, sl)
    # large first: 0xFF + a's token, then b as a single small (low nibble 0xD) or 0xFF + token
    la = ~a_s
    out[la, 0] = 0xFF
    use[la, 0] = True
    token(0, 1, la)
    width_a = np.where(medium[:, 0], 1, 2)  # bytes of a's token
    ls = la & b_s
    rows = np.nonzero(ls)[0]
    out[rows, 1 + width_a[rows]] = (((d[rows, 1] + 6) << 4) | 0x0D).astype(np.uint8)
    use[rows, 1 + width_a[rows]] = True
    ll = la & ~b_s
    for w in (1, 2):  # where b's token starts depends on the width of a's
        rows_w = ll & (width_a == w)
        out[rows_w, 1 + w] = 0xFF
        use[rows_w, 1 + w] = True
        token(1, 2 + w, rows_w)

    # runs of (0, 0) pairs collapse to 0xE0 + n (n <= 15 pairs)
    zero = ss & (d[:, 0] == 0) & (d[:, 1] == 0)
    if zero.any():
        idx = np.arange(zero.size)
        starts = zero & ~np.concatenate(([False], zero[:-1]))
        ends = zero & ~np.concatenate((zero[1:], [False]))
        run_start = np.maximum.accumulate(np.where(starts, idx, 0))
        pos = idx - run_start
        emit = zero & ((pos % 15 == 14) | ends)
        use[zero, 0] = False
        out[emit, 0] = (0xE0 + pos[emit] % 15 + 1).astype(np.uint8)
        use[emit, 0] = True
    return out[use].tobytes()


# --- the writer -------------------------------------------------------------------------------
class OniWriter:
    """Write depth frames to an OpenNI2 ``.oni`` recording, atomically.

    ``OniWriter(path, width, height, fps=30, codec="none", intrinsics=None)`` -- frames are
    (height, width) uint16 depth in millimetres; ``codec`` is ``"none"`` (raw), ``"16z"``
    (lossless, values <= 32767 mm) or ``"16zt"`` (lossless, the smallest on quantised depth,
    <= 32768 distinct values per frame); ``intrinsics`` (default
    :meth:`Intrinsics.openni_default`) are stored as the stream's field of view.  The file
    appears at ``path`` only when the writer is closed without an error (temp file, fsync,
    rename)::

        with OniWriter("scene.oni", 640, 480, codec="16z") as writer:
            for depth in frames:
                writer.write(depth)            # timestamps 0, 33333, 66667, ... us
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        width: int,
        height: int,
        fps: int = 30,
        codec: str = "none",
        intrinsics: Intrinsics | None = None,
    ) -> None:
        self.path = Path(path)
        whole = isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
        if not (whole and 0 < width <= 1600 and 0 < height <= 1200):
            raise FrameError(
                f"an .oni depth stream of {width}x{height} pixels is not supported: OpenNI2's "
                "player takes at most 1600x1200"
            )
        if not isinstance(fps, (int, np.integer)) or not 0 < fps <= 1000:
            raise FrameError(f"fps={fps!r}: expected a whole number of frames per second in 1..1000")
        if codec not in CODECS:
            raise FrameError(f"codec {codec!r}: choose one of {sorted(CODECS)}")
        if intrinsics is None:
            intrinsics = Intrinsics.openni_default(int(width), int(height))
        elif (intrinsics.width, intrinsics.height) != (width, height):
            raise FrameError(
                f"intrinsics are for {intrinsics.width}x{intrinsics.height} but the recording is "
                f"{width}x{height}; pass Intrinsics.scaled({width}, {height})"
            )
        self.width, self.height, self.fps, self.codec = int(width), int(height), int(fps), codec
        self.intrinsics = intrinsics
        self.frames = 0
        self._index: list[tuple[int, int]] = []  # (timestamp, record position) per frame
        self._last_timestamp: int | None = None
        self._first_timestamp = 0
        self._last_data_pos = 0
        self._file: BinaryIO | None = None
        self._target: AtomicFile | None = None
        self._node_added_pos = 0
        self._data_begin_pos = 0
        self._closed = False
        self._open()

    # context manager ------------------------------------------------------------------------
    def __enter__(self) -> "OniWriter":
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # public ---------------------------------------------------------------------------------
    def write(self, depth: np.ndarray, timestamp_us: int | None = None) -> int:
        """Append one frame: ``depth`` (H, W) uint16 mm; ``timestamp_us`` defaults to
        ``frame number / fps`` seconds.  Timestamps must not decrease.  Returns the frame id
        (1, 2, ...)."""
        if self._file is None:
            raise FrameError(f"{self.path}: the writer is closed")
        shape = (self.height, self.width)
        if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.shape != shape:
            described = (f"{depth.dtype} array of shape {depth.shape}" if isinstance(depth, np.ndarray)
                         else type(depth).__name__)
            raise FrameError(
                f"expected a ({self.height}, {self.width}) uint16 depth image in mm for "
                f"{self.path.name}, got a {described}"
            )
        if timestamp_us is None:
            timestamp_us = round(self.frames * 1_000_000 / self.fps)
        timestamp_us = int(timestamp_us)
        if timestamp_us < 0 or (self._last_timestamp is not None and timestamp_us < self._last_timestamp):
            raise FrameError(
                f"timestamp {timestamp_us} us after {self._last_timestamp} us: timestamps of a "
                "recording must be >= 0 and must not decrease"
            )
        if self.codec == "16z":
            payload = encode_16z(depth)
        elif self.codec == "16zt":
            payload = encode_16zt(depth)
        else:
            payload = np.ascontiguousarray(depth).astype("<u2", copy=False).tobytes()
        frame_id = self.frames + 1
        pos = self._file.tell()
        fields = struct.pack("<QI", timestamp_us, frame_id)
        self._write_record(REC_NEW_DATA, fields, payload, undo=self._last_data_pos)
        self._last_data_pos = pos
        self._index.append((timestamp_us, pos))
        if self._last_timestamp is None:
            self._first_timestamp = timestamp_us
        self._last_timestamp = timestamp_us
        self.frames = frame_id
        return frame_id

    @property
    def size(self) -> int:
        """Bytes written so far (0 once closed or aborted)."""
        return self._file.tell() if self._file is not None else 0

    def close(self) -> Path:
        """Finish the file (seek table, end record, patched header) and move it into place.
        Raises :class:`FrameError` if no frame was written (the player rejects empty files)."""
        if self._closed:
            return self.path
        if self._file is None:
            raise FrameError(f"{self.path}: the writer was aborted")
        if self.frames == 0:
            self.abort()
            raise FrameError(f"{self.path}: no frames were written; an .oni file needs at least one")
        f = self._file
        max_ts = int(self._last_timestamp or 0)
        seek_pos = f.tell()
        table = [_SEEK_ENTRY.pack(0, 0, 0)] + [_SEEK_ENTRY.pack(ts, 0, pos) for ts, pos in self._index]
        self._write_record(REC_SEEK_TABLE, b"", b"".join(table))
        self._write_record(REC_END, b"", b"")
        end = f.tell()
        # patch what is only known now: header, NodeAdded and NodeDataBegin
        f.seek(0)
        f.write(_FILE_HEADER.pack(FILE_MAGIC, *FORMAT_VERSION, max_ts, DEPTH_NODE_ID))
        f.seek(self._node_added_pos)
        self._write_record(REC_NODE_ADDED, self._node_added_fields(self.frames, self._first_timestamp,
                                                                   max_ts, seek_pos), b"")
        f.seek(self._data_begin_pos)
        self._write_record(REC_NODE_DATA_BEGIN, struct.pack("<IQ", self.frames, max_ts), b"")
        f.seek(end)
        assert self._target is not None
        self._file = None
        self._target.commit()
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop the unfinished file (nothing appears at ``path``)."""
        self._file = None
        if self._target is not None and not self._closed:
            self._target.discard()

    # internals ------------------------------------------------------------------------------
    def _open(self) -> None:
        parent = self.path.parent
        if not parent.is_dir():
            raise DepthFileError(f"cannot write {self.path}: the folder {parent} does not exist")
        try:
            self._target = AtomicFile(self.path)
        except OSError as exc:
            raise DepthFileError(f"cannot write {self.path}: {exc.strerror}") from exc
        self._file = self._target.file
        f = self._file
        f.write(_FILE_HEADER.pack(FILE_MAGIC, *FORMAT_VERSION, 0, DEPTH_NODE_ID))
        self._node_added_pos = f.tell()
        self._write_record(REC_NODE_ADDED, self._node_added_fields(0, 0, 0, 0), b"")
        w, h, fps = self.width, self.height, self.fps
        hfov = 2.0 * math.atan((w / 2.0) / self.intrinsics.fx)
        vfov = 2.0 * math.atan((h / 2.0) / self.intrinsics.fy)
        props: list[tuple[int, str, bytes]] = [
            (REC_INT_PROPERTY, "oniRequiredFrameSize", struct.pack("<Q", w * h * 2)),
            (REC_INT_PROPERTY, "xnIsGenerating", struct.pack("<Q", 1)),
            (REC_INT_PROPERTY, "xnDeviceMaxDepth", struct.pack("<Q", 10000)),
            (REC_INT_PROPERTY, "xnSupportedMapOutputModesCount", struct.pack("<Q", 1)),
            (REC_GENERAL_PROPERTY, "xnSupportedMapOutputModes", struct.pack("<III", w, h, fps)),
            (REC_GENERAL_PROPERTY, "xnMapOutputMode", struct.pack("<III", w, h, fps)),
            (REC_GENERAL_PROPERTY, "xnSupportedPixelFormats", struct.pack("<I", 1 << 3)),
            (REC_INT_PROPERTY, "xnPixelFormat", struct.pack("<Q", XN_PIXEL_FORMAT_GRAYSCALE_16_BIT)),
            (REC_INT_PROPERTY, "oniPixelFormat", struct.pack("<Q", ONI_PIXEL_FORMAT_DEPTH_1_MM)),
            (REC_GENERAL_PROPERTY, "xnFOV", struct.pack("<dd", hfov, vfov)),
            (REC_INT_PROPERTY, "Cropping", struct.pack("<Q", 1)),
            # XnCropping: enabled (32-bit bool), x offset, y offset, width, height (uint16)
            (REC_GENERAL_PROPERTY, "xnCropping", struct.pack("<iHHHH", 0, 0, 0, w, h)),
            (REC_INT_PROPERTY, "Mirror", struct.pack("<Q", 1)),
            (REC_INT_PROPERTY, "xnMirror", struct.pack("<Q", 0)),
        ]
        for kind, name, data in props:
            fields = _string_field(name) + struct.pack("<I", len(data)) + data
            self._write_record(kind, fields, b"")
        self._write_record(REC_NODE_STATE_READY, b"", b"")
        self._data_begin_pos = f.tell()
        self._write_record(REC_NODE_DATA_BEGIN, struct.pack("<IQ", 0, 0), b"")

    def _node_added_fields(self, frames: int, min_ts: int, max_ts: int, seek_pos: int) -> bytes:
        return (_string_field("Depth") + struct.pack("<i", NODE_TYPE_DEPTH) + CODECS[self.codec]
                + struct.pack("<IQQQ", frames, min_ts, max_ts, seek_pos))

    def _write_record(self, kind: int, fields: bytes, payload: bytes, undo: int = 0) -> None:
        assert self._file is not None
        header = _RECORD_HEADER.pack(RECORD_MAGIC, kind, DEPTH_NODE_ID if kind != REC_END else 0,
                                     _RECORD_HEADER.size + len(fields), len(payload), undo)
        self._file.write(header + fields)
        if payload:
            self._file.write(payload)


def _string_field(text: str) -> bytes:
    raw = text.encode("ascii") + b"\0"
    return struct.pack("<I", len(raw)) + raw



def write_oni(
    path: str | os.PathLike[str],
    frames: Iterable[np.ndarray | DepthFrame],
    fps: int = 30,
    codec: str = "none",
    intrinsics: Intrinsics | None = None,
    on_frame: Callable[[int, int], None] | None = None,
) -> int:
    """Write depth images ((H, W) uint16 mm arrays, or :class:`DepthFrame` objects whose
    timestamps and intrinsics are kept) to ``path`` atomically.  Returns the number of frames.
    ``on_frame(frames, bytes)`` is called after each frame with the count so far and the size
    of the file so far."""
    writer: OniWriter | None = None
    try:
        for item in frames:
            if isinstance(item, DepthFrame):
                depth, stamp, own = item.depth, item.timestamp_us, item.intrinsics
            else:
                depth, stamp, own = item, None, intrinsics
            if writer is None:
                if not isinstance(depth, np.ndarray) or depth.ndim != 2:
                    raise FrameError("write_oni expects (H, W) uint16 depth images or DepthFrames")
                writer = OniWriter(path, depth.shape[1], depth.shape[0], fps=fps, codec=codec,
                                   intrinsics=intrinsics or own)
                first_stamp = stamp
            if stamp is not None and first_stamp is not None:
                stamp -= first_stamp
            writer.write(depth, stamp)
            if on_frame is not None:
                on_frame(writer.frames, writer.size)
        if writer is None:
            raise FrameError(f"{path}: no frames to write; an .oni file needs at least one")
        writer.close()
        return writer.frames
    except BaseException:
        if writer is not None:
            writer.abort()
        raise


# --- checking a file --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class OniInfo:
    """What :func:`read_oni_header` found in a recording's depth stream.

    ``width``/``height`` pixels, ``fps``, ``codec`` (the four-character id, e.g. ``"NONE"``,
    ``"16zP"``, ``"16zT"``), ``frames`` (NewData records of the depth node), ``first_timestamp_us``
    / ``last_timestamp_us``, ``hfov``/``vfov`` in radians (``None`` when not recorded),
    ``version`` of the file format, ``node_id`` of the depth node.
    """

    width: int
    height: int
    fps: int
    codec: str
    frames: int
    first_timestamp_us: int
    last_timestamp_us: int
    hfov: float | None
    vfov: float | None
    version: tuple[int, int, int, int]
    node_id: int = DEPTH_NODE_ID

    def intrinsics(self) -> Intrinsics:
        """Intrinsics from the recorded field of view, else OpenNI's defaults for the size."""
        return intrinsics_from_fov(self.width, self.height, self.hfov, self.vfov)


def intrinsics_from_fov(width: int, height: int, hfov: float | None, vfov: float | None) -> Intrinsics:
    """Pinhole intrinsics of a ``width`` x ``height`` image with fields of view ``hfov``/``vfov``
    (radians), principal point at the centre; :meth:`Intrinsics.openni_default` when a field of
    view is missing or implausible.  Focal lengths are rounded to 1e-3 px (OpenNI passes the
    field of view as float32)."""
    ok = all(v is not None and math.isfinite(v) and 0.05 < v < 3.0 for v in (hfov, vfov))
    if not ok:
        return Intrinsics.openni_default(width, height)
    fx = round((width / 2.0) / math.tan(float(hfov) / 2.0), 3)  # type: ignore[arg-type]
    fy = round((height / 2.0) / math.tan(float(vfov) / 2.0), 3)  # type: ignore[arg-type]
    return Intrinsics(int(width), int(height), fx, fy, (width - 1) / 2.0, (height - 1) / 2.0)


def read_oni_header(path: str | os.PathLike[str]) -> OniInfo:
    """Check an ``.oni`` file and describe its depth stream, without the native library.

    Walks every record header (a few bytes per frame, no pixel data), so a missing, empty,
    truncated or foreign file, or one without a depth stream, raises :class:`DepthFileError`
    naming the problem.
    """
    p = Path(path)
    try:
        f = open(p, "rb")
    except FileNotFoundError:
        raise DepthFileError(f"recording {p} does not exist") from None
    except IsADirectoryError:
        raise DepthFileError(f"recording {p} is a folder, not an .oni file") from None
    except OSError as exc:
        raise DepthFileError(f"recording {p} cannot be opened: {exc.strerror}") from exc
    with f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(_FILE_HEADER.size)
        if len(head) < _FILE_HEADER.size:
            raise DepthFileError(f"recording {p} is not an .oni file: only {size} bytes long")
        magic, major, minor, maint, build, _max_ts, max_node = _FILE_HEADER.unpack(head)
        if magic != FILE_MAGIC:
            raise DepthFileError(
                f"recording {p} is not an OpenNI .oni file (starts with {magic!r}, expected "
                f"{FILE_MAGIC!r})"
            )
        version = (major, minor, maint, build)
        if not OLDEST_VERSION <= version <= FORMAT_VERSION:
            raise DepthFileError(
                f"recording {p} has .oni format version {'.'.join(map(str, version))}; OpenNI2 "
                f"plays {'.'.join(map(str, OLDEST_VERSION))} to {'.'.join(map(str, FORMAT_VERSION))}"
            )
        header_size = _RECORD_HEADER.size if version >= FIRST_64BIT_VERSION else 24
        return _walk_records(f, p, size, header_size, version, max_node)


def _walk_records(f: BinaryIO, p: Path, size: int, header_size: int,
                  version: tuple[int, int, int, int], max_node: int) -> OniInfo:
    depth_nodes: dict[int, dict[str, object]] = {}
    pos = _FILE_HEADER.size
    ended = False
    while pos < size:
        f.seek(pos)
        raw = f.read(header_size)
        if len(raw) < header_size:
            break
        if header_size == _RECORD_HEADER.size:
            magic, kind, node, fields_size, payload, _undo = _RECORD_HEADER.unpack(raw)
        else:
            magic, kind, node, fields_size, payload, _undo = struct.unpack("<IIIIII", raw)
        if magic != RECORD_MAGIC or kind not in _KNOWN_RECORDS or fields_size < header_size:
            raise DepthFileError(f"recording {p} is corrupt: no valid record at byte {pos}")
        end = pos + fields_size + payload
        if end > size:
            raise DepthFileError(
                f"recording {p} is truncated: a record at byte {pos} needs {end - size} bytes "
                "more than the file has (copy interrupted?)"
            )
        if kind == REC_END:
            ended = True
            break
        if node > max_node and kind != REC_END:
            raise DepthFileError(f"recording {p} is corrupt: node id {node} at byte {pos} exceeds "
                                 f"the header's maximum {max_node}")
        fields = f.read(fields_size - header_size)
        if kind in (REC_NODE_ADDED, REC_NODE_ADDED_1_0_0_5, REC_NODE_ADDED_1_0_0_4):
            name_len = struct.unpack_from("<I", fields)[0]
            if 4 + name_len + 8 > len(fields):
                raise DepthFileError(f"recording {p} is corrupt: bad node record at byte {pos}")
            node_type, codec = struct.unpack_from("<i4s", fields, 4 + name_len)
            if node_type == NODE_TYPE_DEPTH:
                depth_nodes[node] = {"codec": codec, "frames": 0, "first": None, "last": 0}
        elif node in depth_nodes and kind in (REC_GENERAL_PROPERTY, REC_INT_PROPERTY, REC_REAL_PROPERTY):
            name_len = struct.unpack_from("<I", fields)[0]
            name = fields[4: 4 + name_len].rstrip(b"\0").decode("ascii", "replace")
            data_len_at = 4 + name_len
            if data_len_at + 4 <= len(fields):
                data_len = struct.unpack_from("<I", fields, data_len_at)[0]
                data = fields[data_len_at + 4: data_len_at + 4 + data_len]
                if name == "xnMapOutputMode" and len(data) == 12:
                    depth_nodes[node]["mode"] = struct.unpack("<III", data)
                elif name == "xnFOV" and len(data) == 16:
                    depth_nodes[node]["fov"] = struct.unpack("<dd", data)
        elif kind == REC_NEW_DATA and node in depth_nodes:
            if len(fields) < 12:
                raise DepthFileError(f"recording {p} is corrupt: bad frame record at byte {pos}")
            stamp = struct.unpack_from("<Q", fields)[0]
            info = depth_nodes[node]
            info["frames"] = int(info["frames"]) + 1  # type: ignore[call-overload]
            if info["first"] is None:
                info["first"] = stamp
            info["last"] = stamp
        pos = end
    if not depth_nodes:
        raise DepthFileError(f"recording {p} holds no depth stream")
    node_id = min(depth_nodes)
    info = depth_nodes[node_id]
    if not ended:
        raise DepthFileError(
            f"recording {p} is truncated: it stops at byte {size} without an end record after "
            f"{info['frames']} frames (recording interrupted or copy incomplete)"
        )
    if "mode" not in info:
        raise DepthFileError(f"recording {p} is corrupt: its depth stream has no resolution "
                             "(xnMapOutputMode)")
    if not info["frames"]:
        raise DepthFileError(f"recording {p} holds no depth frames")
    w, h, fps = info["mode"]  # type: ignore[misc]
    fov = info.get("fov") or (None, None)
    codec = bytes(info["codec"]).decode("ascii", "replace")  # type: ignore[arg-type]
    return OniInfo(int(w), int(h), int(fps), codec, int(info["frames"]),  # type: ignore[call-overload]
                   int(info["first"]), int(info["last"]),  # type: ignore[call-overload]
                   fov[0], fov[1], version, node_id)  # type: ignore[index]


# --- decoding ---------------------------------------------------------------------------------
def read_oni_frames(path: str | os.PathLike[str]) -> list[DepthFrame]:
    """Every depth frame of an ``.oni`` recording, decoded here (no native library).

    Returns :class:`DepthFrame` objects: (H, W) uint16 mm, the recorded timestamps (us) and
    frame ids, intrinsics from the recorded field of view.  Plays codecs ``NONE``, ``16zP`` and
    ``16zT`` (what :class:`OniWriter` and OpenNI's recorder write for depth).  Raises
    :class:`DepthFileError` for a file :func:`read_oni_header` rejects, another codec, or a
    frame that does not decode to exactly H x W pixels.
    """
    p = Path(path)
    info = read_oni_header(p)
    codec = info.codec.encode("ascii", "replace")
    if codec not in _CODEC_NAMES:
        raise DepthFileError(f"recording {p} uses depth codec {info.codec!r}; this reader plays "
                             f"{', '.join(c.decode() for c in _CODEC_NAMES)} (play it through "
                             "hw.openni2 instead)")
    name = _CODEC_NAMES[codec]
    header_size = _RECORD_HEADER.size if info.version >= FIRST_64BIT_VERSION else 24
    intrinsics = info.intrinsics()
    shape = (info.height, info.width)
    frames: list[DepthFrame] = []
    with open(p, "rb") as f:
        data = f.read()
    pos = _FILE_HEADER.size
    while pos + header_size <= len(data):
        if header_size == _RECORD_HEADER.size:
            _magic, kind, node, fields_size, payload, _undo = _RECORD_HEADER.unpack_from(data, pos)
        else:
            _magic, kind, node, fields_size, payload, _undo = struct.unpack_from("<IIIIII", data, pos)
        if kind == REC_END:
            break
        if kind == REC_NEW_DATA and node == info.node_id:
            stamp, frame_id = struct.unpack_from("<QI", data, pos + header_size)
            start = pos + fields_size
            raw = np.frombuffer(data, dtype=np.uint8, count=payload, offset=start)
            try:
                depth = decode_frame(raw, shape, name)
            except FrameError as exc:
                raise DepthFileError(f"recording {p} is corrupt: frame {frame_id} (byte {pos}): "
                                     f"{exc}") from None
            frames.append(DepthFrame(depth, int(stamp), int(frame_id), intrinsics))
        pos += fields_size + payload
    return frames


def decode_frame(payload: np.ndarray | bytes, shape: tuple[int, int], codec: str) -> np.ndarray:
    """One frame's payload (uint8 array or bytes) coded with ``codec`` ("none", "16z", "16zt")
    -> (H, W) uint16 mm.  Raises :class:`FrameError` when it does not decode to exactly
    ``shape``."""
    raw = np.frombuffer(payload, dtype=np.uint8) if isinstance(payload, bytes) else payload
    height, width = shape
    count = height * width
    if codec == "none":
        if raw.size != 2 * count:
            raise FrameError(f"{raw.size} bytes of raw depth, expected {2 * count} for {width}x{height}")
        return raw.view("<u2").astype(np.uint16).reshape(shape)
    if codec == "16z":
        return _decode_16z_checked(raw, count).reshape(shape)
    if codec == "16zt":
        if raw.size < 2:
            raise FrameError("a 16zT frame shorter than its table length")
        n = int(raw[0]) | int(raw[1]) << 8
        if raw.size < 2 + 2 * n:
            raise FrameError(f"a 16zT frame of {raw.size} bytes cannot hold its {n}-entry table")
        table = raw[2: 2 + 2 * n].view("<u2").astype(np.uint16)
        indices = _decode_16z_checked(raw[2 + 2 * n:], count)
        if n == 0 or int(indices.max()) >= n:
            raise FrameError(f"a 16zT frame indexes past the end of its {n}-entry table")
        return table[indices].reshape(shape)
    raise FrameError(f"codec {codec!r}: choose one of {sorted(CODECS)}")


def _decode_16z_checked(raw: np.ndarray, count: int) -> np.ndarray:
    out = np.empty(count, dtype=np.uint16)
    got = _decode_16z(np.ascontiguousarray(raw), out)
    if got != count:
        what = "more" if got < 0 else str(got)
        raise FrameError(f"the 16z stream decodes to {what} pixels, expected {count}")
    return out


@njit(cache=True, nogil=True)
def _decode_16z(data, out):  # pragma: no cover - compiled
    """Decode a 16zP stream ``data`` (N,) uint8 into ``out`` (M,) uint16; returns the number of
    pixels written, or -1 if the stream is truncated or holds more than M pixels."""
    n_in = data.size
    n_out = out.size
    if n_in < 2 or n_out < 1:
        return -1
    last = np.int64(data[0]) | (np.int64(data[1]) << 8)
    out[0] = last
    o = 1
    i = 2
    while i < n_in:
        c = np.int64(data[i])
        i += 1
        if c >= 0xE0 and c != 0xFF:  # 0xE0 + n: n pairs equal to the last pixel
            run = 2 * (c - 0xE0)
            if o + run > n_out:
                return -1
            for _ in range(run):
                out[o] = last
                o += 1
            continue
        big = c == 0xFF
        if not big:  # high nibble: a step of 6 - nibble
            if o >= n_out:
                return -1
            last = (last - ((c >> 4) - 6)) & 0xFFFF
            out[o] = last
            o += 1
            low = c & 0x0F
            if low == 0x0D:  # a lone step
                continue
            if low != 0x0F:  # a second small step
                if o >= n_out:
                    return -1
                last = (last - (low - 6)) & 0xFFFF
                out[o] = last
                o += 1
                continue
        # a large step: d + 192 (one byte, top bit set) or the new value big-endian (two bytes)
        if i >= n_in or o >= n_out:
            return -1
        b = np.int64(data[i])
        i += 1
        if b & 0x80:
            last = (last - (b - 192)) & 0xFFFF
        else:
            if i >= n_in:
                return -1
            last = (b << 8) | np.int64(data[i])
            i += 1
        out[o] = last
        o += 1
    return o
