"""The ``.oni`` container: its record layout, and reading a recording without the native library.

Holds the format's constants (file and record headers, record types, the depth node's id and
pixel formats; shared with the writer in :mod:`hw.oni`), :func:`read_oni_header` (walks the
record headers -> :class:`OniInfo`: size in pixels, fps, codec, frame count, timestamps in us,
fields of view in radians) and :func:`read_oni_frames` (-> :class:`DepthFrame` objects, (H, W)
uint16 mm, decoded by :mod:`hw.oni_codec`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import struct
from pathlib import Path
from typing import BinaryIO

import numpy as np

from hw.depth import DepthFrame, Intrinsics
from hw.errors import DepthFileError, FrameError
from hw.oni_codec import _CODEC_NAMES, decode_frame

# --- container constants (OpenNI2 Source/Drivers/OniFile/DataRecords.h) ---------------------
# magic, version (major, minor, maint, build), max ts, max node id
_FILE_HEADER = struct.Struct("<4sBBHIQI")
# magic, type, node id, fields size, payload size, undo pos
_RECORD_HEADER = struct.Struct("<IIIIIQ")
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
#: Properties of the depth stream that robot_change writes besides OpenNI's own (which keep
#: only the field of view: a principal point off the centre, as an Azure Kinect's or a
#: SUN3D Xtion's, was lost): the intrinsics (fx, fy, cx, cy as four little-endian doubles) and
#: the camera's name (UTF-8).  OpenNI2's player passes over properties it does not know.
PROP_INTRINSICS = "robotChangeIntrinsics"
PROP_CAMERA = "robotChangeCamera"


# --- checking a file --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class OniInfo:
    """What :func:`read_oni_header` found in a recording's depth stream.

    ``width``/``height`` pixels, ``fps``, ``codec`` (the four-character id, e.g. ``"NONE"``,
    ``"16zP"``, ``"16zT"``), ``frames`` (NewData records of the depth node), ``first_timestamp_us``
    / ``last_timestamp_us``, ``hfov``/``vfov`` in radians (``None`` when not recorded),
    ``version`` of the file format, ``node_id`` of the depth node; ``stored`` (fx, fy, cx, cy)
    and ``camera`` the intrinsics and camera name robot_change wrote (None, "" otherwise).
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
    stored: tuple[float, float, float, float] | None = None
    camera: str = ""

    def intrinsics(self) -> Intrinsics:
        """The stored intrinsics, else those of the recorded field of view, else OpenNI's
        defaults for the size."""
        if self.stored is not None:
            return Intrinsics(self.width, self.height, *self.stored)
        return intrinsics_from_fov(self.width, self.height, self.hfov, self.vfov)


def intrinsics_from_fov(width: int, height: int, hfov: float | None,
                        vfov: float | None) -> Intrinsics:
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
                f"plays {'.'.join(map(str, OLDEST_VERSION))} to "
                f"{'.'.join(map(str, FORMAT_VERSION))}"
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
        elif node in depth_nodes and kind in (REC_GENERAL_PROPERTY, REC_INT_PROPERTY,
                                              REC_REAL_PROPERTY):
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
                elif name == PROP_INTRINSICS and len(data) == 32:
                    stored = struct.unpack("<dddd", data)
                    if all(math.isfinite(v) for v in stored) and min(stored[:2]) > 0:
                        depth_nodes[node]["stored"] = stored
                elif name == PROP_CAMERA:
                    depth_nodes[node]["camera"] = data.decode("utf-8", "replace")[:64]
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
    stored = info.get("stored")
    if stored is not None and not (-w <= stored[2] <= 2 * w and -h <= stored[3] <= 2 * h):
        stored = None  # a principal point nowhere near the image: damaged; the field of view
    return OniInfo(int(w), int(h), int(fps), codec, int(info["frames"]),  # type: ignore[call-overload]
                   int(info["first"]), int(info["last"]),  # type: ignore[call-overload]
                   fov[0], fov[1], version, node_id,  # type: ignore[index]
                   stored, str(info.get("camera", "")))  # type: ignore[arg-type]



# --- reading frames -------------------------------------------------------------------------------
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
            _magic, kind, node, fields_size, payload, _undo = struct.unpack_from(
                "<IIIIII", data, pos)
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
