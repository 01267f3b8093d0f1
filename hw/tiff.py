"""A small TIFF reader for depth images: baseline grayscale, 8 or 16 bits per pixel.

Reads the first image of a file: little- or big-endian, strips or tiles, compression none (1),
PackBits (32773), Deflate (8 and 32946) and LZW (5), with horizontal differencing (predictor 2)
for Deflate and LZW.  Anything else -- colour, float samples, JPEG, BigTIFF -- raises a
:class:`hw.errors.DepthFileError` that names the file and what is unsupported.
"""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
from numba import njit

from hw.errors import DepthFileError
from hw.png import MAX_PIXELS, read_file

# tag numbers
WIDTH, HEIGHT, BITS, COMPRESSION, PHOTOMETRIC = 256, 257, 258, 259, 262
STRIP_OFFSETS, SAMPLES, ROWS_PER_STRIP, STRIP_COUNTS = 273, 277, 278, 279
PREDICTOR, TILE_WIDTH, TILE_LENGTH, TILE_OFFSETS, TILE_COUNTS = 317, 322, 323, 324, 325
SAMPLE_FORMAT = 339

COMPRESSIONS = {1: "none", 5: "LZW", 8: "Deflate", 32773: "PackBits", 32946: "Deflate"}
_KNOWN_COMPRESSIONS = {2: "CCITT RLE", 3: "CCITT G3", 4: "CCITT G4", 6: "old-style JPEG",
                       7: "JPEG", 34712: "JPEG 2000", 50000: "Zstandard", 34925: "LZMA",
                       50001: "WebP"}
_PHOTOMETRIC = {0: "WhiteIsZero", 1: "BlackIsZero", 2: "RGB", 3: "palette",
                4: "transparency mask", 5: "CMYK", 6: "YCbCr", 8: "CIELab"}
# field type -> (numpy dtype without byte order, bytes per value)
_TYPES = {1: ("u1", 1), 2: ("u1", 1), 3: ("u2", 2), 4: ("u4", 4), 5: ("u4", 8), 6: ("i1", 1),
          7: ("u1", 1), 8: ("i2", 2), 9: ("i4", 4), 10: ("i4", 8), 11: ("f4", 4),
          12: ("f8", 8), 13: ("u4", 4), 16: ("u8", 8), 17: ("i8", 8), 18: ("u8", 8)}
_INTEGER_TYPES = {1, 3, 4, 6, 8, 9, 13, 16, 17, 18}


def read_tiff(source: str | os.PathLike | bytes) -> np.ndarray:
    """Decode the first image of a grayscale TIFF.

    ``source``: a path, or the file's bytes.  Returns (H, W) uint16 (native byte order) for
    16 bits per sample, uint8 for 8.  Raises :class:`DepthFileError` when the file is missing,
    truncated or corrupt, or uses a feature this reader does not support (the message names it).
    """
    if isinstance(source, (bytes, bytearray, memoryview)):
        return decode_tiff(bytes(source), "TIFF data")
    return decode_tiff(read_file(source), str(source))


def decode_tiff(data: bytes, name: str) -> np.ndarray:
    """Decode the bytes of a TIFF (see :func:`read_tiff`); ``name`` is used in messages."""
    order = _byte_order(data, name)
    tags = _read_first_ifd(data, order, name)
    layout = _layout(tags, name)
    width, height, sample_bytes, compression, predictor = layout
    dtype = np.dtype(f"{order}u{sample_bytes}")
    image = np.empty((height, width), dtype=np.uint16 if sample_bytes == 2 else np.uint8)

    if TILE_WIDTH in tags or TILE_OFFSETS in tags:
        tile_w = _scalar(tags, TILE_WIDTH, name)
        tile_h = _scalar(tags, TILE_LENGTH, name)
        if tile_w <= 0 or tile_h <= 0 or tile_w * tile_h > MAX_PIXELS:
            raise DepthFileError(f"{name}: corrupt TIFF, tile size {tile_w}x{tile_h}")
        across, down = -(-width // tile_w), -(-height // tile_h)
        offsets, counts = _pieces(tags, TILE_OFFSETS, TILE_COUNTS, across * down, name)
        for index in range(across * down):
            top, left = (index // across) * tile_h, (index % across) * tile_w
            tile = _decode_piece(data, offsets[index], counts[index], tile_h, tile_w, dtype,
                                 compression, predictor, f"{name} tile {index}")
            rows, cols = min(tile_h, height - top), min(tile_w, width - left)
            image[top : top + rows, left : left + cols] = tile[:rows, :cols]
        return image

    rows_per_strip = min(_scalar(tags, ROWS_PER_STRIP, name, default=height), height)
    if rows_per_strip <= 0:
        raise DepthFileError(f"{name}: corrupt TIFF, RowsPerStrip is {rows_per_strip}")
    strips = -(-height // rows_per_strip)
    if STRIP_COUNTS not in tags and compression == 1:  # allowed for uncompressed data
        counts_default = [rows_per_strip * width * sample_bytes] * strips
        tags = {**tags, STRIP_COUNTS: np.array(counts_default, dtype=np.int64)}
    offsets, counts = _pieces(tags, STRIP_OFFSETS, STRIP_COUNTS, strips, name)
    for index in range(strips):
        top = index * rows_per_strip
        rows = min(rows_per_strip, height - top)
        image[top : top + rows] = _decode_piece(data, offsets[index], counts[index], rows,
                                                width, dtype, compression, predictor,
                                                f"{name} strip {index}")
    return image


def _byte_order(data: bytes, name: str) -> str:
    if len(data) < 8:
        raise DepthFileError(f"{name}: {'empty' if not data else 'truncated'} TIFF, "
                             f"only {len(data)} bytes")
    marker = data[:2]
    if marker not in (b"II", b"MM"):
        raise DepthFileError(f"{name}: not a TIFF (it does not start with 'II' or 'MM')")
    order = "<" if marker == b"II" else ">"
    (magic,) = struct.unpack_from(order + "H", data, 2)
    if magic == 43:
        raise DepthFileError(f"{name}: BigTIFF is not supported; save it as classic TIFF")
    if magic != 42:
        raise DepthFileError(f"{name}: not a TIFF (version {magic}, expected 42)")
    return order


def _read_first_ifd(data: bytes, order: str, name: str) -> dict[int, np.ndarray]:
    """The first image file directory as {tag: 1-D array of its values} (rationals as pairs)."""
    (offset,) = struct.unpack_from(order + "I", data, 4)
    if offset < 8 or offset + 2 > len(data):
        raise DepthFileError(f"{name}: truncated TIFF, its first directory at byte {offset} "
                             f"is outside the {len(data)}-byte file")
    (count,) = struct.unpack_from(order + "H", data, offset)
    if offset + 2 + 12 * count > len(data):
        raise DepthFileError(f"{name}: truncated TIFF, its directory of {count} entries runs "
                             "past the end of the file")
    tags: dict[int, np.ndarray] = {}
    for entry in range(count):
        at = offset + 2 + 12 * entry
        tag, kind, n = struct.unpack_from(order + "HHI", data, at)
        if kind not in _TYPES:
            continue  # unknown field types must be skipped (TIFF 6.0, section 2)
        code, size = _TYPES[kind]
        total = size * n
        if total <= 4:
            start = at + 8
        else:
            (start,) = struct.unpack_from(order + "I", data, at + 8)
            if start + total > len(data):
                raise DepthFileError(f"{name}: truncated TIFF, tag {tag}'s values at byte "
                                     f"{start} run past the end of the file")
        if kind in _INTEGER_TYPES:
            values = np.frombuffer(data, dtype=order + code, count=n, offset=start)
            tags[tag] = values.astype(np.int64)
        elif tag in (WIDTH, HEIGHT, BITS, COMPRESSION, PHOTOMETRIC, SAMPLES, STRIP_OFFSETS,
                     STRIP_COUNTS, ROWS_PER_STRIP, PREDICTOR, TILE_WIDTH, TILE_LENGTH,
                     TILE_OFFSETS, TILE_COUNTS, SAMPLE_FORMAT):
            raise DepthFileError(f"{name}: corrupt TIFF, tag {tag} has non-integer type {kind}")
    return tags


def _scalar(tags: dict[int, np.ndarray], tag: int, name: str, default: int | None = None) -> int:
    values = tags.get(tag)
    if values is None or values.size == 0:
        if default is None:
            raise DepthFileError(f"{name}: corrupt TIFF, required tag {tag} is missing")
        return default
    return int(values[0])


def _layout(tags: dict[int, np.ndarray], name: str) -> tuple[int, int, int, int, int]:
    """Check that the image is one we read; returns (width, height, bytes per sample,
    compression, predictor)."""
    width, height = _scalar(tags, WIDTH, name), _scalar(tags, HEIGHT, name)
    if not (0 < width and 0 < height):
        raise DepthFileError(f"{name}: corrupt TIFF, image size {width}x{height}")
    if width * height > MAX_PIXELS:
        raise DepthFileError(f"{name}: TIFF of {width}x{height} pixels is too large for a "
                             f"depth image (at most {MAX_PIXELS} pixels)")
    samples = _scalar(tags, SAMPLES, name, default=1)
    bits_all = tags.get(BITS, np.array([1]))
    bits = int(bits_all[0])
    photometric = _scalar(tags, PHOTOMETRIC, name, default=1)
    sample_format = _scalar(tags, SAMPLE_FORMAT, name, default=1)
    if samples != 1 or photometric not in (0, 1):
        kind = _PHOTOMETRIC.get(photometric, f"photometric {photometric}")
        raise DepthFileError(f"{name}: {bits}-bit {kind} TIFF with {samples} samples per pixel "
                             "is not a depth image; depth TIFFs are single-channel grayscale "
                             "(16-bit millimetres)")
    if photometric == 0:
        raise DepthFileError(f"{name}: WhiteIsZero TIFF is not supported; depth TIFFs are "
                             "BlackIsZero (larger value = farther)")
    if sample_format != 1:
        kind = {2: "signed integer", 3: "floating-point"}.get(sample_format,
                                                             f"format {sample_format}")
        raise DepthFileError(f"{name}: {bits}-bit {kind} TIFF samples are not supported; "
                             "convert the depth to unsigned 16-bit millimetres")
    if bits not in (8, 16):
        raise DepthFileError(f"{name}: {bits}-bit TIFF is not supported; depth TIFFs are "
                             "8- or 16-bit grayscale")
    compression = _scalar(tags, COMPRESSION, name, default=1)
    if compression not in COMPRESSIONS:
        what = _KNOWN_COMPRESSIONS.get(compression, "unknown")
        raise DepthFileError(f"{name}: TIFF compression {compression} ({what}) is not "
                             "supported; use none, PackBits, Deflate or LZW")
    predictor = _scalar(tags, PREDICTOR, name, default=1)
    if compression in (5, 8, 32946) and predictor not in (1, 2):
        what = "floating-point" if predictor == 3 else "unknown"
        raise DepthFileError(f"{name}: TIFF predictor {predictor} ({what}) is not supported; "
                             "only 1 (none) and 2 (horizontal differencing)")
    if compression in (1, 32773):
        predictor = 1  # libtiff applies predictors only with LZW/Deflate-style compression
    return width, height, bits // 8, compression, predictor


def _pieces(tags: dict[int, np.ndarray], offsets_tag: int, counts_tag: int, needed: int,
            name: str) -> tuple[np.ndarray, np.ndarray]:
    what = "tile" if offsets_tag == TILE_OFFSETS else "strip"
    offsets, counts = tags.get(offsets_tag), tags.get(counts_tag)
    if offsets is None or counts is None:
        raise DepthFileError(f"{name}: corrupt TIFF, {what} offsets or byte counts are missing")
    if offsets.size < needed or counts.size < needed:
        raise DepthFileError(f"{name}: corrupt TIFF, {needed} {what}s needed but "
                             f"{min(offsets.size, counts.size)} listed")
    return offsets, counts


def _decode_piece(data: bytes, offset: int, count: int, rows: int, cols: int,
                  dtype: np.dtype, compression: int, predictor: int, name: str) -> np.ndarray:
    """Decompress one strip or tile of ``rows`` x ``cols`` samples; returns (rows, cols) of
    ``dtype`` (the file's byte order)."""
    offset, count = int(offset), int(count)
    expected = rows * cols * dtype.itemsize
    if offset < 0 or count < 0 or offset + count > len(data):
        raise DepthFileError(f"{name}: truncated TIFF, data at bytes {offset}..{offset + count} "
                             f"lies beyond the end of the {len(data)}-byte file")
    packed = np.frombuffer(data, dtype=np.uint8, count=count, offset=offset)
    if compression == 1:
        raw = packed
    elif compression in (8, 32946):
        decompressor = zlib.decompressobj()
        try:
            out = decompressor.decompress(packed.tobytes(), expected)
        except zlib.error as exc:
            raise DepthFileError(f"{name}: corrupt TIFF, Deflate data does not decompress "
                                 f"({exc})") from None
        raw = np.frombuffer(out, dtype=np.uint8)
    else:
        raw = np.empty(expected, dtype=np.uint8)
        kernel = packbits_decode if compression == 32773 else lzw_decode
        written = kernel(packed, raw)
        if written == -2:
            raise DepthFileError(f"{name}: corrupt TIFF, bad {COMPRESSIONS[compression]} code")
        if compression == 5 and written == -3:
            raise DepthFileError(f"{name}: old-style (pre-TIFF 6.0) LZW is not supported; "
                                 "save the file again with a current writer")
        raw = raw[: max(written, 0)]
    if raw.size < expected:
        raise DepthFileError(f"{name}: truncated TIFF, {COMPRESSIONS[compression]} data gives "
                             f"{raw.size} of {expected} bytes")
    samples = raw[:expected].view(dtype).reshape(rows, cols)
    if predictor == 2:
        return np.cumsum(samples.astype(dtype.newbyteorder("=")), axis=1,
                         dtype=dtype.newbyteorder("="))
    return samples


@njit(cache=True, nogil=True)
def packbits_decode(src, dst):  # pragma: no cover - compiled
    """Decode PackBits ``src`` (uint8) into ``dst`` (uint8) until either is used up.

    Returns the number of bytes written; a run that would overflow ``dst`` is cut at its end
    (the caller checks the count).
    """
    i = 0
    out = 0
    n_src, n_dst = src.shape[0], dst.shape[0]
    while i < n_src and out < n_dst:
        header = np.int32(src[i])
        i += 1
        if header < 128:  # copy the next header + 1 bytes
            length = header + 1
            if i + length > n_src:
                length = n_src - i
            if out + length > n_dst:
                length = n_dst - out
            for k in range(length):
                dst[out + k] = src[i + k]
            out += length
            i += header + 1
        elif header > 128:  # repeat the next byte 257 - header times
            if i >= n_src:
                break
            length = 257 - header
            if out + length > n_dst:
                length = n_dst - out
            value = src[i]
            for k in range(length):
                dst[out + k] = value
            out += length
            i += 1
        # header == 128 (-128): no operation
    return out


@njit(cache=True, nogil=True)
def lzw_decode(src, dst):  # pragma: no cover - compiled
    """Decode TIFF LZW ``src`` (uint8; codes 9-12 bits, most significant bit first, the code
    width growing one code early) into ``dst`` (uint8).

    Returns the number of bytes written (output beyond ``dst`` is dropped), -2 for an invalid
    code, -3 for old-style (LSB-first) LZW.
    """
    n_src, n_dst = src.shape[0], dst.shape[0]
    if n_src >= 2 and src[0] == 0 and (src[1] & 1) == 1:
        return -3
    prefix = np.empty(4096, np.int32)
    suffix = np.empty(4096, np.uint8)
    first = np.empty(4096, np.uint8)
    length = np.empty(4096, np.int32)
    for code in range(256):
        prefix[code] = -1
        suffix[code] = code
        first[code] = code
        length[code] = 1
    total_bits = n_src * 8
    bit = 0
    width = 9
    next_code = 258
    previous = -1
    out = 0
    while bit + width <= total_bits:
        code = 0
        for k in range(width):
            position = bit + k
            code = (code << 1) | ((src[position >> 3] >> (7 - (position & 7))) & 1)
        bit += width
        if code == 256:  # clear
            width = 9
            next_code = 258
            previous = -1
            continue
        if code == 257:  # end of information
            break
        if previous == -1:
            if code > 255:
                return -2
            if out < n_dst:
                dst[out] = code
            out += 1
            previous = code
            continue
        if code < next_code:
            head = first[code]
        elif code == next_code:
            head = first[previous]
        else:
            return -2
        if next_code < 4096:
            prefix[next_code] = previous
            suffix[next_code] = head
            first[next_code] = first[previous]
            length[next_code] = length[previous] + 1
            next_code += 1
        # emit the string of ``code``, last byte first
        size = length[code]
        at = code
        for k in range(size - 1, -1, -1):
            if out + k < n_dst:
                dst[out + k] = suffix[at]
            at = prefix[at]
        out += size
        previous = code
        if next_code + 1 >= (1 << width) and width < 12:
            width += 1
    return min(out, n_dst)
