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

This module writes recordings (:class:`OniWriter`, :func:`write_oni`) and is the one to import
from; the codecs live in :mod:`hw.oni_codec`, the container layout and the reader in
:mod:`hw.oni_format`, and every name is re-exported here.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hw.atomic import AtomicFile
from hw.depth import DepthFrame, Intrinsics
from hw.errors import DepthFileError, FrameError

# re-exported: the codecs and the container (public names in __all__; the private helpers,
# ``import x as x``, stay importable from here as they were before the split)
from hw.oni_codec import _CODEC_NAMES as _CODEC_NAMES
from hw.oni_codec import (
    CODECS,
    MAX_16Z_VALUE,
    MAX_16ZT_VALUES,
    decode_frame,
    encode_16z,
    encode_16zt,
)
from hw.oni_codec import _decode_16z as _decode_16z
from hw.oni_codec import _decode_16z_checked as _decode_16z_checked
from hw.oni_codec import _encode_pairs as _encode_pairs
from hw.oni_format import (
    _FILE_HEADER,
    _RECORD_HEADER,
    _SEEK_ENTRY,
    DEPTH_NODE_ID,
    FILE_MAGIC,
    FIRST_64BIT_VERSION,
    FORMAT_VERSION,
    NODE_TYPE_DEPTH,
    OLDEST_VERSION,
    ONI_PIXEL_FORMAT_DEPTH_1_MM,
    PLAYER_MAX_FRAME_BYTES,
    PROP_CAMERA,
    PROP_INTRINSICS,
    REC_END,
    REC_GENERAL_PROPERTY,
    REC_INT_PROPERTY,
    REC_NEW_DATA,
    REC_NODE_ADDED,
    REC_NODE_ADDED_1_0_0_4,
    REC_NODE_ADDED_1_0_0_5,
    REC_NODE_DATA_BEGIN,
    REC_NODE_REMOVED,
    REC_NODE_STATE_READY,
    REC_REAL_PROPERTY,
    REC_SEEK_TABLE,
    REC_STRING_PROPERTY,
    RECORD_MAGIC,
    XN_PIXEL_FORMAT_GRAYSCALE_16_BIT,
    OniInfo,
    intrinsics_from_fov,
    read_oni_frames,
    read_oni_header,
)
from hw.oni_format import _KNOWN_RECORDS as _KNOWN_RECORDS
from hw.oni_format import _walk_records as _walk_records

__all__ = [
    # the writer (this module)
    "OniWriter", "write_oni",
    # codecs (hw.oni_codec)
    "CODECS", "MAX_16Z_VALUE", "MAX_16ZT_VALUES", "encode_16z", "encode_16zt", "decode_frame",
    # the container and reading it (hw.oni_format)
    "OniInfo", "read_oni_header", "read_oni_frames", "intrinsics_from_fov",
    "FILE_MAGIC", "RECORD_MAGIC", "FORMAT_VERSION", "OLDEST_VERSION", "FIRST_64BIT_VERSION",
    "REC_NODE_ADDED_1_0_0_4", "REC_INT_PROPERTY", "REC_REAL_PROPERTY", "REC_STRING_PROPERTY",
    "REC_GENERAL_PROPERTY", "REC_NODE_REMOVED", "REC_NODE_DATA_BEGIN", "REC_NODE_STATE_READY",
    "REC_NEW_DATA", "REC_END", "REC_NODE_ADDED_1_0_0_5", "REC_NODE_ADDED", "REC_SEEK_TABLE",
    "NODE_TYPE_DEPTH", "ONI_PIXEL_FORMAT_DEPTH_1_MM", "XN_PIXEL_FORMAT_GRAYSCALE_16_BIT",
    "DEPTH_NODE_ID", "PLAYER_MAX_FRAME_BYTES",
]


# --- the writer -------------------------------------------------------------------------------
class OniWriter:
    """Write depth frames to an OpenNI2 ``.oni`` recording, atomically.

    ``OniWriter(path, width, height, fps=30, codec="none", intrinsics=None, camera="")`` --
    frames are (height, width) uint16 depth in millimetres; ``codec`` is ``"none"`` (raw),
    ``"16z"`` (lossless, values <= 32767 mm) or ``"16zt"`` (lossless, the smallest on quantised
    depth, <= 32768 distinct values per frame); ``intrinsics`` (default
    :meth:`Intrinsics.openni_default`) are stored as the stream's field of view (OpenNI's) and,
    where that does not give them back (a principal point off the centre), whole
    (robot_change's, :data:`~hw.oni_format.PROP_INTRINSICS`), and so is ``camera``, the
    camera's name (at most 64 bytes; none by default).  The file
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
        camera: str = "",
    ) -> None:
        self.path = Path(path)
        whole = isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
        if not (whole and 0 < width <= 1600 and 0 < height <= 1200):
            raise FrameError(
                f"an .oni depth stream of {width}x{height} pixels is not supported: OpenNI2's "
                "player takes at most 1600x1200"
            )
        if not isinstance(fps, (int, np.integer)) or not 0 < fps <= 1000:
            raise FrameError(f"fps={fps!r}: expected a whole number of frames per second in "
                             "1..1000")
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
        self.camera = str(camera).encode("utf-8")[:64].decode("utf-8", "ignore")
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
    def __enter__(self) -> OniWriter:
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
            described = (f"{depth.dtype} array of shape {depth.shape}"
                         if isinstance(depth, np.ndarray) else type(depth).__name__)
            raise FrameError(
                f"expected a ({self.height}, {self.width}) uint16 depth image in mm for "
                f"{self.path.name}, got a {described}"
            )
        if timestamp_us is None:
            timestamp_us = round(self.frames * 1_000_000 / self.fps)
        timestamp_us = int(timestamp_us)
        if timestamp_us < 0 or (self._last_timestamp is not None
                                and timestamp_us < self._last_timestamp):
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
            raise FrameError(f"{self.path}: no frames were written; "
                             "an .oni file needs at least one")
        f = self._file
        max_ts = int(self._last_timestamp or 0)
        seek_pos = f.tell()
        table = [_SEEK_ENTRY.pack(0, 0, 0)] + [_SEEK_ENTRY.pack(ts, 0, pos)
                                               for ts, pos in self._index]
        self._write_record(REC_SEEK_TABLE, b"", b"".join(table))
        self._write_record(REC_END, b"", b"")
        end = f.tell()
        # patch what is only known now: header, NodeAdded and NodeDataBegin
        f.seek(0)
        f.write(_FILE_HEADER.pack(FILE_MAGIC, *FORMAT_VERSION, max_ts, DEPTH_NODE_ID))
        f.seek(self._node_added_pos)
        self._write_record(REC_NODE_ADDED,
                           self._node_added_fields(self.frames, self._first_timestamp, max_ts,
                                                   seek_pos), b"")
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
            (REC_INT_PROPERTY, "xnPixelFormat",
             struct.pack("<Q", XN_PIXEL_FORMAT_GRAYSCALE_16_BIT)),
            (REC_INT_PROPERTY, "oniPixelFormat", struct.pack("<Q", ONI_PIXEL_FORMAT_DEPTH_1_MM)),
            (REC_GENERAL_PROPERTY, "xnFOV", struct.pack("<dd", hfov, vfov)),
            (REC_INT_PROPERTY, "Cropping", struct.pack("<Q", 1)),
            # XnCropping: enabled (32-bit bool), x offset, y offset, width, height (uint16)
            (REC_GENERAL_PROPERTY, "xnCropping", struct.pack("<iHHHH", 0, 0, 0, w, h)),
            (REC_INT_PROPERTY, "Mirror", struct.pack("<Q", 1)),
            (REC_INT_PROPERTY, "xnMirror", struct.pack("<Q", 0)),
        ]
        # robot_change's own, only where they tell more than OpenNI's (a file OpenNI's alone
        # describes stays byte for byte what it was)
        K = self.intrinsics
        if intrinsics_from_fov(w, h, hfov, vfov) != K:
            props.append((REC_GENERAL_PROPERTY, PROP_INTRINSICS,
                          struct.pack("<dddd", K.fx, K.fy, K.cx, K.cy)))
        if self.camera:
            props.append((REC_GENERAL_PROPERTY, PROP_CAMERA, self.camera.encode("utf-8")))
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
    camera: str = "",
) -> int:
    """Write depth images ((H, W) uint16 mm arrays, or :class:`DepthFrame` objects whose
    timestamps and intrinsics are kept) to ``path`` atomically, naming ``camera`` (the
    camera's name, "": none).  Returns the number of frames.
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
                                   intrinsics=intrinsics or own, camera=camera)
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
