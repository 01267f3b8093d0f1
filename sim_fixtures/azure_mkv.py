"""The one real Azure Kinect capture (``../shared/data/azure-kinect-tof-1capture``): its depth
frame(s) out of the Matroska recording and the depth camera's pinhole intrinsics out of the
factory calibration, with no SDK and no new dependency.

    from sim_fixtures.azure_mkv import AZURE_DIR, read_depth_frames, depth_intrinsics
    frames = read_depth_frames(AZURE_DIR / "recording.mkv")    # [(576, 640) uint16 mm]
    K = depth_intrinsics(AZURE_DIR / "calibration.json")        # hw.depth.Intrinsics, NFOV

The recording (k4arecord, libmatroska) is an EBML document: ``EBML`` header, then a
``Segment`` holding ``Tracks`` (one ``TrackEntry`` a track: number, name ``COLOR`` / ``DEPTH``
/ ``IR`` / ``IMU``, codec) and ``Cluster`` s (a ``Timecode`` and ``SimpleBlock`` s or
``BlockGroup`` / ``Block`` s, each naming its track).  The DEPTH track's codec is
``V_MS/VFW/FOURCC`` with the four-character code ``b16g``: 16-bit **big-endian** grey,
millimetres, 0 = no reading; 640 x 576 in the NFOV unbinned mode.

Every element is an id (a variable-length integer keeping its marker bit, 1-4 bytes) and a size
(a variable-length integer without it, 1-8 bytes; all value bits set = unknown size, allowed
for the Segment and Clusters of a recording written as a stream: such an element ends where an
element that cannot be its child begins, or at the end of its parent).

A file that is missing raises :class:`FileNotFoundError`; one that is not such a recording
(truncated, another format, no DEPTH track, a depth block of the wrong size) raises
:class:`MkvError` (a ValueError), naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import struct
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics

__all__ = [
    "AZURE_DIR",
    "NFOV_UNBINNED",
    "DepthBlock",
    "MkvError",
    "MkvTrack",
    "depth_intrinsics",
    "read_depth_blocks",
    "read_depth_frames",
    "read_tracks",
]

#: ../shared/data/azure-kinect-tof-1capture beside the repository (read only).
AZURE_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "azure-kinect-tof-1capture"

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
CHAPTERS = 0x1043A770
TAGS = 0x1254C367
VOID = 0xEC
CRC32 = 0xBF

#: The Segment's children: an unknown-size Cluster ends where one of these begins.
_SEGMENT_CHILDREN = frozenset((SEEK_HEAD, INFO, TRACKS, CLUSTER, CUES, ATTACHMENTS, CHAPTERS,
                               TAGS))
#: Top-level elements: an unknown-size Segment ends where one of these begins.
_TOP_LEVEL = frozenset((EBML, SEGMENT))
#: Master elements this reader descends into.
_MASTERS = frozenset((SEGMENT, TRACKS, TRACK_ENTRY, VIDEO, CLUSTER, BLOCK_GROUP))

#: The NFOV unbinned depth mode of the Azure Kinect SDK's mode conversion
#: (transformation_get_mode_specific_depth_camera_calibration): the normalised calibration
#: scaled to the binned sensor (1024 x 1024 px), then cropped by (192, 180) px to 640 x 576.
NFOV_UNBINNED = {"binned": (1024, 1024), "crop": (192, 180), "size": (640, 576)}
_DEPTH_MODES = {
    "NFOV_2X2BINNED": {"binned": (512, 512), "crop": (96, 90), "size": (320, 288)},
    "NFOV_UNBINNED": NFOV_UNBINNED,
    "WFOV_2X2BINNED": {"binned": (512, 512), "crop": (0, 0), "size": (512, 512)},
    "WFOV_UNBINNED": {"binned": (1024, 1024), "crop": (0, 0), "size": (1024, 1024)},
}


class MkvError(ValueError):
    """Not a readable Azure Kinect recording (truncated, another format, no DEPTH track, a
    depth block of the wrong size); the message names the file."""


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
    """One depth frame: ``depth`` (H, W) uint16 mm, 0 = no reading, and its ``timestamp_us``
    (the block's time in the recording, microseconds)."""

    depth: np.ndarray
    timestamp_us: int


@dataclasses.dataclass(frozen=True)
class _Element:
    id: int
    start: int       # offset of the id
    data: int        # offset of the payload
    end: int | None  # offset after the payload; None: unknown size


class _Reader:
    """EBML walk over the bytes of one file (``name`` for the messages)."""

    def __init__(self, data: bytes, name: str):
        self.data = data
        self.name = name

    def fail(self, what: str) -> MkvError:
        return MkvError(f"{self.name}: not a readable Azure Kinect recording (Matroska): {what}")

    def vint(self, pos: int, limit: int, keep_marker: bool, what: str) -> tuple[int, int, bool]:
        """(value, length, all value bits set) of the variable-length integer at ``pos``."""
        if pos >= limit:
            raise self.fail(f"{what} at byte {pos} runs past the end (file truncated?)")
        first = self.data[pos]
        if first == 0:
            raise self.fail(f"{what} at byte {pos} has no length marker (a corrupt file)")
        length = 9 - first.bit_length()
        if length > (4 if keep_marker else 8):
            raise self.fail(f"{what} at byte {pos} is {length} bytes long (at most "
                            f"{4 if keep_marker else 8})")
        if pos + length > limit:
            raise self.fail(f"{what} at byte {pos} runs past the end (file truncated?)")
        value = int.from_bytes(self.data[pos:pos + length], "big")
        marker = 1 << (7 * length)
        ones = (value ^ marker) == marker - 1
        return (value if keep_marker else value ^ marker), length, ones

    def element(self, pos: int, limit: int) -> _Element:
        eid, n_id, _ = self.vint(pos, limit, True, "element id")
        size, n_size, unknown = self.vint(pos + n_id, limit, False, f"size of element "
                                          f"0x{eid:X}")
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

    def children(self, parent_id: int, start: int, end: int | None, limit: int):
        """The child elements of a master element whose payload starts at ``start`` and ends
        at ``end`` (None: unknown size, ending where an element that cannot be its child
        begins, or at ``limit``)."""
        stop_ids = _TOP_LEVEL if parent_id == SEGMENT else \
            (_SEGMENT_CHILDREN | _TOP_LEVEL) if parent_id == CLUSTER else frozenset()
        bound = limit if end is None else end
        pos = start
        while pos < bound:
            if end is None:
                eid, _, _ = self.vint(pos, bound, True, "element id")
                if eid in stop_ids:
                    return
            el = self.element(pos, bound)
            yield el
            if el.end is None:
                # an unknown-size child: it ends where its own children end
                pos = self.end_of(el, bound)
            else:
                pos = el.end

    def end_of(self, el: _Element, limit: int) -> int:
        """Where an element ends (walking an unknown-size one's children)."""
        if el.end is not None:
            return el.end
        pos = el.data
        for child in self.children(el.id, el.data, None, limit):
            pos = child.end if child.end is not None else self.end_of(child, limit)
        return pos

    def payload(self, el: _Element) -> bytes:
        return self.data[el.data:el.end]

    def uint(self, el: _Element) -> int:
        return int.from_bytes(self.payload(el), "big")

    def text(self, el: _Element) -> str:
        return self.payload(el).rstrip(b"\0").decode("utf-8", "replace")


def _read_bytes(path) -> tuple[bytes, str]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such recording (the Azure Kinect capture lives in "
                                "../shared/data/azure-kinect-tof-1capture beside the project's "
                                "checkout)")
    return path.read_bytes(), str(path)


def _segment(r: _Reader) -> _Element:
    """The Segment after the EBML header (checked to be a Matroska document)."""
    size = len(r.data)
    if size < 4 or int.from_bytes(r.data[:4], "big") != EBML:
        raise r.fail("no EBML header (another format)")
    header = r.element(0, size)
    doc_type = next((r.text(c) for c in r.children(EBML, header.data, header.end, size)
                     if c.id == DOC_TYPE), "")
    if doc_type not in ("matroska", "webm"):
        raise r.fail(f"EBML document of type {doc_type!r}, not matroska")
    pos = header.end
    while pos < size:
        el = r.element(pos, size)
        if el.id == SEGMENT:
            return el
        if el.end is None:
            break
        pos = el.end
    raise r.fail("no Segment after the EBML header")


def _tracks(r: _Reader, segment: _Element) -> list[MkvTrack]:
    limit = len(r.data)
    out = []
    for el in r.children(SEGMENT, segment.data, segment.end, limit):
        if el.id != TRACKS:
            continue
        for entry in r.children(TRACKS, el.data, el.end, limit):
            if entry.id != TRACK_ENTRY:
                continue
            fields = {"number": 0, "name": "", "codec": "", "fourcc": "", "width": 0,
                      "height": 0}
            for c in r.children(TRACK_ENTRY, entry.data, entry.end, limit):
                if c.id == TRACK_NUMBER:
                    fields["number"] = r.uint(c)
                elif c.id == TRACK_NAME:
                    fields["name"] = r.text(c)
                elif c.id == CODEC_ID:
                    fields["codec"] = r.text(c)
                elif c.id == CODEC_PRIVATE:
                    # V_MS/VFW/FOURCC: a BITMAPINFOHEADER, biCompression at bytes 16-19
                    private = r.payload(c)
                    if len(private) >= 20:
                        fields["fourcc"] = private[16:20].decode("latin-1")
                elif c.id == VIDEO:
                    for v in r.children(VIDEO, c.data, c.end, limit):
                        if v.id == PIXEL_WIDTH:
                            fields["width"] = r.uint(v)
                        elif v.id == PIXEL_HEIGHT:
                            fields["height"] = r.uint(v)
            out.append(MkvTrack(**fields))
        return out
    raise r.fail("no Tracks element in the Segment")


def read_tracks(path) -> list[MkvTrack]:
    """The recording's tracks (:class:`MkvTrack`), in file order."""
    data, name = _read_bytes(path)
    r = _Reader(data, name)
    return _tracks(r, _segment(r))


def _timecode_scale_ns(r: _Reader, segment: _Element) -> int:
    limit = len(r.data)
    for el in r.children(SEGMENT, segment.data, segment.end, limit):
        if el.id == INFO:
            for c in r.children(INFO, el.data, el.end, limit):
                if c.id == TIMECODE_SCALE:
                    return r.uint(c)
            break
        if el.id == CLUSTER:
            break
    return 1_000_000  # Matroska's default: milliseconds


def _blocks(r: _Reader, segment: _Element):
    """(track number, timecode in the cluster's scale, frame bytes) of every block, in file
    order (laced blocks raise: the k4arecord video tracks are never laced)."""
    limit = len(r.data)
    for cluster in r.children(SEGMENT, segment.data, segment.end, limit):
        if cluster.id != CLUSTER:
            continue
        base = 0
        for el in r.children(CLUSTER, cluster.data, cluster.end, limit):
            if el.id == CLUSTER_TIMECODE:
                base = r.uint(el)
            elif el.id == SIMPLE_BLOCK:
                yield _block(r, el, base)
            elif el.id == BLOCK_GROUP:
                for c in r.children(BLOCK_GROUP, el.data, el.end, limit):
                    if c.id == BLOCK:
                        yield _block(r, c, base)


def _block(r: _Reader, el: _Element, base: int) -> tuple[int, int, int, int]:
    """(track, timecode, start, end) of the frame in a SimpleBlock / Block."""
    track, n, _ = r.vint(el.data, el.end, False, "block track number")
    head = el.data + n
    if head + 3 > el.end:
        raise r.fail(f"block at byte {el.start} is shorter than its header")
    (relative,) = struct.unpack(">h", r.data[head:head + 2])
    flags = r.data[head + 2]
    if flags & 0x06:
        raise r.fail(f"block at byte {el.start} (track {track}) is laced; this reader reads "
                     "one frame a block")
    return track, base + relative, head + 3, el.end


def read_depth_blocks(path, track: str = "DEPTH") -> list[DepthBlock]:
    """Every frame of the ``track`` ("DEPTH"; "IR" is stored alike) as :class:`DepthBlock`
    ((H, W) uint16, big-endian ``b16g`` decoded), in file order."""
    data, name = _read_bytes(path)
    r = _Reader(data, name)
    segment = _segment(r)
    tracks = _tracks(r, segment)
    chosen = [t for t in tracks if t.name == track]
    if not chosen:
        raise r.fail(f"no {track} track (tracks: {', '.join(t.name or '?' for t in tracks)})")
    t = chosen[0]
    if t.fourcc != "b16g":
        raise r.fail(f"the {track} track's codec is {t.codec!r} / {t.fourcc!r}, not the "
                     "16-bit big-endian grey 'b16g'")
    if t.width <= 0 or t.height <= 0:
        raise r.fail(f"the {track} track has no picture size")
    scale_ns = _timecode_scale_ns(r, segment)
    out = []
    for number, timecode, start, end in _blocks(r, segment):
        if number != t.number:
            continue
        if end - start != 2 * t.width * t.height:
            raise r.fail(f"a {track} block holds {end - start} bytes, a {t.width} x {t.height} "
                         f"16-bit frame is {2 * t.width * t.height}")
        depth = np.frombuffer(data, ">u2", t.width * t.height, start)
        out.append(DepthBlock(depth.reshape(t.height, t.width).astype(np.uint16),
                              timecode * scale_ns // 1000))
    if not out:
        raise r.fail(f"no {track} frame in the recording")
    return out


def read_depth_frames(path=None) -> list[np.ndarray]:
    """The DEPTH frames of an Azure Kinect recording (default: the shared capture's
    ``recording.mkv``) as (H, W) uint16 mm arrays, 0 = no reading; (576, 640) in the NFOV
    unbinned mode."""
    return [b.depth for b in read_depth_blocks(AZURE_DIR / "recording.mkv" if path is None
                                               else path)]


def depth_intrinsics(path=None, mode: str = "NFOV_UNBINNED") -> Intrinsics:
    """The depth camera's pinhole intrinsics for a depth ``mode`` (default NFOV unbinned,
    640 x 576) from an Azure Kinect ``calibration.json`` (default: the shared capture's).

    The factory calibration (``Cameras`` -> ``CALIBRATION_CameraLocationD0``) holds
    Brown-Conrady parameters cx, cy, fx, fy, k1-k6, codx, cody, p2, p1, the first four
    normalised to the 1024 x 1024 sensor with (0, 0) the top-left corner of the top-left
    pixel.  As the SDK converts them to a mode: scale by the mode's binned sensor size,
    subtract the mode's crop offset, and subtract half a pixel (pixel centres at integer
    coordinates, as :class:`hw.depth.Intrinsics` counts them).  The lens distortion is left
    out (a pinhole model)."""
    path = Path(AZURE_DIR / "calibration.json" if path is None else path)
    if mode not in _DEPTH_MODES:
        raise ValueError(f"unknown depth mode {mode!r}; known: {', '.join(_DEPTH_MODES)}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such calibration file")
    try:
        cameras = json.loads(path.read_text())["CalibrationInformation"]["Cameras"]
        depth = [c for c in cameras if c.get("Location") == "CALIBRATION_CameraLocationD0"]
        if not depth:
            raise KeyError("no CALIBRATION_CameraLocationD0 camera")
        cam = depth[0]
        model = cam["Intrinsics"]["ModelType"]
        cx, cy, fx, fy = (float(v) for v in cam["Intrinsics"]["ModelParameters"][:4])
        sensor = (int(cam["SensorWidth"]), int(cam["SensorHeight"]))
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise MkvError(f"{path}: not an Azure Kinect calibration: {exc}") from exc
    if model != "CALIBRATION_LensDistortionModelBrownConrady" or sensor != (1024, 1024):
        raise MkvError(f"{path}: depth camera model {model!r} on a {sensor[0]} x {sensor[1]} "
                       "sensor; expected Brown-Conrady on the 1024 x 1024 sensor")
    m = _DEPTH_MODES[mode]
    (bw, bh), (ox, oy), (w, h) = m["binned"], m["crop"], m["size"]
    return Intrinsics(w, h, fx * bw, fy * bh, cx * bw - ox - 0.5, cy * bh - oy - 0.5)
