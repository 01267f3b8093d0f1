"""A small PNG codec for depth images: grayscale 8/16-bit in, gray or RGB out.

Reading accepts what depth datasets contain -- non-interlaced grayscale PNGs of 8 or 16 bits
(colour type 0) with any of the five scanline filters -- and refuses everything else with a
:class:`hw.errors.DepthFileError` naming the file and the problem.  Every chunk's CRC is
checked.  Writing covers uint16 gray (depth in millimetres), uint8 gray and uint8 RGB (pictures),
atomically (temp file in the same folder, fsync, rename).

No Pillow or imageio at run time: zlib from the standard library, NumPy, and one numba kernel
that undoes the scanline filters.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Union

import numpy as np
from numba import njit

from hw.atomic import write_atomically
from hw.errors import DepthFileError, FrameError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: Filter types of PNG's filter method 0, by number.
FILTER_NAMES = ("None", "Sub", "Up", "Average", "Paeth")

_COLOUR_TYPES = {0: "grayscale", 2: "RGB", 3: "palette", 4: "gray+alpha", 6: "RGBA"}
_ALLOWED_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
#: Largest image (in pixels) the readers accept: far beyond any depth camera, and it keeps a
#: forged header from asking for terabytes.
MAX_PIXELS = 1 << 28
_IDAT_CHUNK = 1 << 20  # bytes of compressed data per IDAT chunk when writing

Source = Union[str, os.PathLike, bytes, bytearray, memoryview]


# --------------------------------------------------------------------------------- reading


def read_png(source: Source) -> np.ndarray:
    """Decode a grayscale PNG.

    ``source``: a path, or the file's bytes.  Returns an (H, W) array: uint16 (native byte
    order) for a 16-bit PNG, uint8 for an 8-bit one.  Raises :class:`DepthFileError` when the
    file is missing, truncated, corrupt (bad CRC, bad zlib stream), interlaced, or not a
    grayscale 8/16-bit image (e.g. "8-bit RGB PNG is not a depth image").
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        return decode_png(bytes(source), "PNG data")
    return decode_png(read_file(source), str(source))


def read_file(path: str | os.PathLike) -> bytes:
    """The bytes of ``path``; :class:`DepthFileError` when it is missing or unreadable."""
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise DepthFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DepthFileError(f"{path}: is a folder, expected an image file") from None
    except OSError as exc:
        raise DepthFileError(f"{path}: cannot read it ({exc.strerror or exc})") from None


def decode_png(data: bytes, name: str) -> np.ndarray:
    """Decode the bytes of a grayscale PNG (see :func:`read_png`); ``name`` is used in error
    messages (the file's path)."""
    header, idat = _parse_chunks(data, name)
    width, height, bit_depth, colour_type, interlace = header
    bpp = bit_depth // 8  # bytes per pixel (one sample)
    row_bytes = width * bpp
    expected = height * (row_bytes + 1)

    decompressor = zlib.decompressobj()
    try:
        raw = decompressor.decompress(idat, expected + 1)
    except zlib.error as exc:
        raise DepthFileError(f"{name}: corrupt PNG, its image data does not decompress "
                             f"({exc})") from None
    if len(raw) > expected:
        raise DepthFileError(f"{name}: corrupt PNG, its image data holds more than the "
                             f"{width}x{height} pixels the header declares")
    if len(raw) < expected or not decompressor.eof:
        raise DepthFileError(f"{name}: truncated PNG, its image data ends after "
                             f"{len(raw)} of {expected} bytes")

    buffer = np.frombuffer(raw, dtype=np.uint8)
    filters = buffer[:: row_bytes + 1]
    bad = np.flatnonzero(filters > 4)
    if bad.size:
        raise DepthFileError(f"{name}: corrupt PNG, row {int(bad[0])} has unknown filter type "
                             f"{int(filters[bad[0]])} (0-4 exist)")
    pixels = np.empty((height, row_bytes), dtype=np.uint8)
    unfilter_rows(buffer, pixels, bpp)
    if bit_depth == 8:
        return pixels
    return pixels.view(">u2").astype(np.uint16)


def _parse_chunks(data: bytes, name: str) -> tuple[tuple[int, int, int, int, int], bytes]:
    """Walk the chunks: checks the signature, every CRC and the chunk order; returns the IHDR
    fields (width, height, bit depth, colour type, interlace) and the joined IDAT data."""
    if not data.startswith(PNG_SIGNATURE):
        if not data:
            what = "empty"
        elif PNG_SIGNATURE.startswith(data):
            what = f"truncated PNG, only {len(data)} bytes"
        else:
            what = "not a PNG (its first bytes are not the PNG signature)"
        raise DepthFileError(f"{name}: {what}")
    position = len(PNG_SIGNATURE)
    header = None
    idat: list[bytes] = []
    while True:
        if position + 8 > len(data):
            raise DepthFileError(f"{name}: truncated PNG, the file ends before its IEND chunk "
                                 f"(after {len(data)} bytes)")
        length, kind = struct.unpack_from(">I4s", data, position)
        end = position + 8 + length + 4
        if length > 0x7FFFFFFF or end > len(data):
            raise DepthFileError(f"{name}: truncated PNG, chunk {_chunk_name(kind)} at byte "
                                 f"{position} runs past the end of the file")
        body = data[position + 8 : position + 8 + length]
        (crc,) = struct.unpack_from(">I", data, end - 4)
        if zlib.crc32(kind + body) != crc:
            raise DepthFileError(f"{name}: corrupt PNG, chunk {_chunk_name(kind)} at byte "
                                 f"{position} fails its CRC check")
        position = end
        if header is None and kind != b"IHDR":
            raise DepthFileError(f"{name}: corrupt PNG, the first chunk is "
                                 f"{_chunk_name(kind)}, not IHDR")
        if kind == b"IHDR":
            if header is not None:
                raise DepthFileError(f"{name}: corrupt PNG, more than one IHDR chunk")
            header = _parse_header(body, name)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        elif not kind[:1].isalpha():
            raise DepthFileError(f"{name}: corrupt PNG, bad chunk type {kind!r}")
        elif kind[:1].isupper() and kind != b"PLTE":
            raise DepthFileError(f"{name}: PNG uses critical chunk {_chunk_name(kind)}, which "
                                 "this reader does not know")
        # ancillary chunks (gAMA, tEXt, pHYs, ...) and PLTE carry nothing a depth image needs
    if not idat:
        raise DepthFileError(f"{name}: corrupt PNG, it has no image data (IDAT chunk)")
    return header, b"".join(idat)


def _parse_header(body: bytes, name: str) -> tuple[int, int, int, int, int]:
    if len(body) != 13:
        raise DepthFileError(f"{name}: corrupt PNG, IHDR is {len(body)} bytes, not 13")
    width, height, bit_depth, colour_type, compression, filter_method, interlace = (
        struct.unpack(">IIBBBBB", body)
    )
    if not (0 < width <= 0x7FFFFFFF and 0 < height <= 0x7FFFFFFF):
        raise DepthFileError(f"{name}: corrupt PNG, image size {width}x{height}")
    if width * height > MAX_PIXELS:
        raise DepthFileError(f"{name}: PNG of {width}x{height} pixels is too large for a depth "
                             f"image (at most {MAX_PIXELS} pixels)")
    if colour_type not in _COLOUR_TYPES or bit_depth not in _ALLOWED_DEPTHS[colour_type]:
        raise DepthFileError(f"{name}: corrupt PNG, colour type {colour_type} with bit depth "
                             f"{bit_depth} does not exist")
    if compression != 0 or filter_method != 0 or interlace not in (0, 1):
        raise DepthFileError(f"{name}: corrupt PNG, unknown compression/filter/interlace "
                             f"method ({compression}/{filter_method}/{interlace})")
    if colour_type != 0:
        raise DepthFileError(f"{name}: {bit_depth}-bit {_COLOUR_TYPES[colour_type]} PNG is not "
                             "a depth image; depth PNGs are single-channel grayscale "
                             "(16-bit millimetres)")
    if bit_depth < 8:
        raise DepthFileError(f"{name}: {bit_depth}-bit grayscale PNG is not supported; depth "
                             "PNGs are 16-bit grayscale")
    if interlace:
        raise DepthFileError(f"{name}: Adam7-interlaced PNG is not supported; save it again "
                             "without interlacing")
    return width, height, bit_depth, colour_type, interlace


def _chunk_name(kind: bytes) -> str:
    return kind.decode("latin-1") if kind.isalpha() else repr(kind)


@njit(cache=True, nogil=True)
def unfilter_rows(raw, out, bpp):  # pragma: no cover - compiled
    """Undo PNG scanline filters.

    ``raw``: (H * (R + 1),) uint8, each row its filter byte (0-4, checked by the caller) then
    R filtered bytes.  ``out``: (H, R) uint8, written with the reconstructed bytes.  ``bpp``:
    bytes per complete pixel (the distance to the "left" byte).
    """
    height, row_bytes = out.shape
    stride = row_bytes + 1
    for y in range(height):
        kind = raw[y * stride]
        start = y * stride + 1
        if kind == 0 or (kind == 2 and y == 0):
            for x in range(row_bytes):
                out[y, x] = raw[start + x]
        elif kind == 1:
            for x in range(row_bytes):
                left = out[y, x - bpp] if x >= bpp else 0
                out[y, x] = (raw[start + x] + left) & 0xFF
        elif kind == 2:
            for x in range(row_bytes):
                out[y, x] = (raw[start + x] + out[y - 1, x]) & 0xFF
        elif kind == 3:
            for x in range(row_bytes):
                left = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
                up = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
                out[y, x] = (raw[start + x] + ((left + up) >> 1)) & 0xFF
        else:
            for x in range(row_bytes):
                left = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
                up = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
                corner = np.int32(out[y - 1, x - bpp]) if (x >= bpp and y > 0) else np.int32(0)
                estimate = left + up - corner
                dist_left = abs(estimate - left)
                dist_up = abs(estimate - up)
                dist_corner = abs(estimate - corner)
                if dist_left <= dist_up and dist_left <= dist_corner:
                    predictor = left
                elif dist_up <= dist_corner:
                    predictor = up
                else:
                    predictor = corner
                out[y, x] = (raw[start + x] + predictor) & 0xFF


# --------------------------------------------------------------------------------- writing


def write_png(path: str | os.PathLike, array: np.ndarray, *, level: int = 6,
              filter_type: int | None = None) -> None:
    """Write ``array`` as a PNG, atomically (temp file in the same folder, fsync, rename).

    ``array``: (H, W) uint16 (16-bit gray, e.g. depth in mm), (H, W) uint8 (8-bit gray) or
    (H, W, 3) uint8 (RGB).  ``level``: zlib level 0-9.  ``filter_type``: 0-4 to use one filter
    for every row, or ``None`` (default) to choose per row the one whose output has the smallest
    sum of absolute values (the libpng heuristic).  Raises :class:`FrameError` for another
    dtype or shape.
    """
    data = encode_png(array, level=level, filter_type=filter_type)
    try:
        write_atomically(path, data)
    except OSError as exc:
        raise DepthFileError(f"{path}: cannot write it ({exc.strerror or exc})") from None


def encode_png(array: np.ndarray, *, level: int = 6, filter_type: int | None = None) -> bytes:
    """The bytes of a PNG holding ``array`` (see :func:`write_png`)."""
    array = np.asarray(array)
    if array.dtype == np.uint16 and array.ndim == 2:
        bit_depth, colour_type, bpp = 16, 0, 2
    elif array.dtype == np.uint8 and array.ndim == 2:
        bit_depth, colour_type, bpp = 8, 0, 1
    elif array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3:
        bit_depth, colour_type, bpp = 8, 2, 3
    else:
        raise FrameError(f"cannot write a {array.dtype} array of shape {array.shape} as PNG; "
                         "expected (H, W) uint16, (H, W) uint8 or (H, W, 3) uint8")
    height, width = array.shape[:2]
    if not (0 < width <= 0x7FFFFFFF and 0 < height <= 0x7FFFFFFF):
        raise FrameError(f"cannot write a PNG of {width}x{height} pixels")
    if bit_depth == 16:
        rows = array.astype(">u2").view(np.uint8).reshape(height, -1)
    else:
        rows = np.ascontiguousarray(array).reshape(height, -1)
    if not (isinstance(level, (int, np.integer)) and 0 <= level <= 9):
        raise FrameError(f"PNG zlib level {level!r}: expected a whole number 0-9")
    if filter_type is not None and filter_type not in range(5):
        raise FrameError(f"PNG filter type {filter_type!r}: expected 0-4 or None (adaptive)")

    filtered = filter_rows(rows, bpp, filter_type)
    compressed = zlib.compress(filtered.tobytes(), level)
    header = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    parts = [PNG_SIGNATURE, _chunk(b"IHDR", header)]
    for start in range(0, max(len(compressed), 1), _IDAT_CHUNK):
        parts.append(_chunk(b"IDAT", compressed[start : start + _IDAT_CHUNK]))
    parts.append(_chunk(b"IEND", b""))
    return b"".join(parts)


def filter_rows(rows: np.ndarray, bpp: int, filter_type: int | None) -> np.ndarray:
    """Apply PNG scanline filters.

    ``rows``: (H, R) uint8 raw bytes.  Returns (H, R + 1) uint8: each row's filter byte then its
    filtered bytes.  ``filter_type`` None chooses per row (smallest sum of absolute values).
    """
    x = rows.astype(np.int16)
    left = np.zeros_like(x)
    left[:, bpp:] = x[:, :-bpp]
    up = np.zeros_like(x)
    up[1:] = x[:-1]
    corner = np.zeros_like(x)
    corner[1:, bpp:] = x[:-1, :-bpp]
    estimate = left + up - corner
    dist_left, dist_up, dist_corner = (np.abs(estimate - v) for v in (left, up, corner))
    paeth = np.where((dist_left <= dist_up) & (dist_left <= dist_corner), left,
                     np.where(dist_up <= dist_corner, up, corner))
    candidates = [x, x - left, x - up, x - ((left + up) >> 1), x - paeth]
    if filter_type is None:
        # sum of |value| with bytes read as signed, as libpng does
        costs = np.stack([np.abs((c & 0xFF).astype(np.uint8).view(np.int8).astype(np.int32))
                          .sum(axis=1) for c in candidates])
        choice = np.argmin(costs, axis=0)
    else:
        choice = np.full(rows.shape[0], filter_type)
    stacked = np.stack(candidates)  # (5, H, R)
    chosen = stacked[choice, np.arange(rows.shape[0])]
    out = np.empty((rows.shape[0], rows.shape[1] + 1), dtype=np.uint8)
    out[:, 0] = choice
    out[:, 1:] = chosen & 0xFF
    return out


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


