"""16-bit grayscale PNGs, the depth images of image folders, ROS ``compressedDepth`` messages
and RealSense recordings, decoded without Pillow: the chunks walked, the image data inflated
(Intel's ISA-L through ``isal`` where it is installed, about 1.6x as fast as zlib on a
recording's frame; else zlib), the rows unfiltered by a kernel (NumPy twin in
tests/test_png16.py).  A RealSense recording's 640 x 480 frame: 1.2 ms against Pillow's 2.3
(docs/benchmarks.md).

    depth = decode_png16(data, "frame.png", MAX_PIXELS)  # (H, W) uint16; None: not such a PNG

Only a plain one (bit depth 16, colour type 0, not interlaced, no ``tRNS``, its chunks whole
and in order) is decoded here; for anything else the answer is None and the caller reads it
with Pillow, which names what it is.  A plain PNG whose image data is corrupt or truncated is
a :class:`hw.errors.DepthFileError` naming it.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np
from numba import njit

from hw.errors import DepthFileError

try:  # ISA-L's inflate (the isal wheel, x86_64 and aarch64); zlib's where it is absent
    from isal import isal_zlib as _inflate
except ImportError:  # pragma: no cover - the wheel is a dependency where it exists
    _inflate = zlib

__all__ = ["decode_png16"]

_MAGIC = b"\x89PNG\r\n\x1a\n"
_CHUNK = struct.Struct(">I4s")
_IHDR = struct.Struct(">IIBBBBB")


def decode_png16(data: bytes, name: str, max_pixels: int) -> np.ndarray | None:
    """The (H, W) uint16 samples of the plain 16-bit grayscale PNG ``data``, or None when it
    is not one (see the module).  ``name`` names it in errors; a header of more than
    ``max_pixels`` pixels is refused before anything is inflated."""
    header = _plain_header(data)
    if header is None:
        return None
    width, height, idat = header
    if width * height > max_pixels:
        raise DepthFileError(f"{name}: {width}x{height} pixels is too large for a depth image")
    expected = height * (1 + 2 * width)
    inflater = _inflate.decompressobj()
    try:
        raw = inflater.decompress(b"".join(idat), expected + 1)
    except _inflate.error as exc:
        raise DepthFileError(f"{name}: truncated or corrupt PNG (its image data: {exc})") \
            from None
    if len(raw) != expected:
        what = "more" if len(raw) > expected else "less"
        raise DepthFileError(f"{name}: truncated or corrupt PNG (its image data inflates to "
                             f"{what} than the {width}x{height} rows it declares)")
    if not inflater.eof:
        raise DepthFileError(f"{name}: truncated PNG (its image data stops before its end)")
    out = np.empty((height, width), dtype=np.uint16)
    if not unfilter16(np.frombuffer(raw, dtype=np.uint8), out):
        raise DepthFileError(f"{name}: corrupt PNG (a row's filter type is not 0-4)")
    return out


def _plain_header(data: bytes) -> tuple[int, int, list[memoryview]] | None:
    """(width, height, the IDAT chunks' data) of a plain 16-bit grayscale PNG (see the
    module), else None."""
    if not data.startswith(_MAGIC):
        return None
    view = memoryview(data)
    pos = len(_MAGIC)
    idat: list[memoryview] = []
    size = None
    previous = b""
    while pos + 12 <= len(data):
        length, kind = _CHUNK.unpack_from(data, pos)
        end = pos + 12 + length
        if end > len(data):
            return None
        body = view[pos + 8:pos + 8 + length]
        if size is None:  # IHDR comes first
            if kind != b"IHDR" or length != _IHDR.size:
                return None
            width, height, depth, colour, method, filtering, interlace = _IHDR.unpack(body)
            if (depth, colour, method, filtering, interlace) != (16, 0, 0, 0, 0) \
                    or not width or not height:
                return None
            size = (width, height)
        elif kind == b"IDAT":
            if idat and previous != b"IDAT":
                return None  # IDAT chunks must follow each other
            idat.append(body)
        elif kind == b"IEND":
            return (*size, idat) if idat else None
        elif kind == b"tRNS" or kind[0] & 0x20 == 0:  # a transparency, or a critical chunk
            return None
        previous = kind
        pos = end
    return None


@njit(cache=True, nogil=True)
def unfilter16(raw, out):
    """PNG rows of a 16-bit grayscale image undone: ``raw`` (H * (1 + 2 W),) uint8 (each row's
    filter type, then its filtered big-endian samples) into ``out`` (H, W) uint16.  Filters
    (PNG spec 9.2, two bytes a pixel): 0 none, 1 Sub, 2 Up, 3 Average, 4 Paeth.  Returns
    False at a filter type beyond 4."""
    height, width = out.shape
    stride = 2 * width
    prev = np.zeros(stride, dtype=np.uint8)
    cur = np.zeros(stride, dtype=np.uint8)
    for i in range(height):
        row = raw[i * (stride + 1) + 1:(i + 1) * (stride + 1)]
        kind = raw[i * (stride + 1)]
        if kind == 0:
            for x in range(stride):  # not cur[:] = row: a slice copy costs ~2 s of compile
                cur[x] = row[x]
        elif kind == 1:
            cur[0], cur[1] = row[0], row[1]
            for x in range(2, stride):
                cur[x] = row[x] + cur[x - 2]
        elif kind == 2:
            for x in range(stride):
                cur[x] = row[x] + prev[x]
        elif kind == 3:
            for x in range(stride):
                left = np.int32(cur[x - 2]) if x >= 2 else np.int32(0)
                cur[x] = row[x] + ((left + np.int32(prev[x])) >> 1)
        elif kind == 4:
            for x in range(stride):
                up = np.int32(prev[x])
                if x < 2:  # no left nor upper left: Paeth is Up
                    cur[x] = row[x] + prev[x]
                    continue
                left = np.int32(cur[x - 2])
                up_left = np.int32(prev[x - 2])
                pa = abs(up - up_left)  # |p - left| with p = left + up - up_left
                pb = abs(left - up_left)
                pc = abs(left + up - 2 * up_left)
                cur[x] = row[x] + (left if pa <= pb and pa <= pc else (up if pb <= pc
                                                                        else up_left))
        else:
            return False
        for j in range(width):
            out[i, j] = (np.uint16(cur[2 * j]) << 8) | np.uint16(cur[2 * j + 1])
        prev, cur = cur, prev
    return True
