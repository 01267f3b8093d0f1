"""Compressed depth images as ROS writes them: image_transport's ``compressedDepth`` (PNG or
RVL, after a 12-byte header) and its ``compressed`` PNG of a 16-bit image.

    depth = decode_compressed_depth(message.format, message.data, "run1 /camera/depth 17")
    format, data = encode_compressed_depth(depth, "rvl")      # what image_transport would send

``compressedDepth`` (format ``"16UC1; compressedDepth png"``, ``"... rvl"``, or the older bare
``"16UC1; compressedDepth"``): 12 bytes of header (int32 format, float32 ``depthParam[2]``,
little-endian), then a PNG, or an RVL stream after its width and height (uint32 each).  A 16UC1
image is carried as it is (millimetres); a 32FC1 one (metres) as quantised inverse depth,
``d = A / (q - B)`` with ``A, B = depthParam`` and ``q = 0`` for no reading.  ``compressed``
(format ``"16UC1; png compressed"`` or ``"mono16; ..."``): the PNG alone.  RVL is Wilson's
"Fast lossless depth image compression" (2017): runs of zeros and of readings, each reading
the zigzag delta from the previous one, in 3-bit nibbles with a continuation bit packed into
little-endian 32-bit words, most significant nibble first.

Every failure is a :class:`hw.errors.FrameError` naming ``where``.  Output: (H, W) uint16
millimetres, 0 = no reading.
"""

from __future__ import annotations

import io
import struct

import numpy as np
from numba import njit
from PIL import Image

from hw.errors import DepthFileError, FrameError
from hw.imagefile import decode_image

__all__ = ["COMPRESSED_TYPE", "decode_compressed_depth", "depth_format", "encode_compressed_depth"]

COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
#: Encodings of the image inside, and the unit of a sample.
_ENCODINGS = {"16UC1": "mm", "mono16": "mm", "32FC1": "m"}
_HEADER = struct.Struct("<iff")  # image_transport's ConfigHeader: format, depthParam[2]
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: Largest RVL image decoded (4096 x 4096): RVL's run lengths let a few bytes claim any size, so
#: the size its header gives is bounded before anything is allocated.
_MAX_RVL_PIXELS = 4096 * 4096


def depth_format(format_text: str) -> tuple[str, str] | None:
    """``(encoding, codec)`` of a CompressedImage ``format`` that holds depth, else ``None``.

    codec: ``"png"`` or ``"rvl"`` after a compressedDepth header, ``"plain-png"`` for the
    ``compressed`` transport's PNG of a 16-bit image."""
    encoding, _, rest = str(format_text).partition(";")
    encoding, rest = encoding.strip(), rest.strip().lower()
    if encoding not in _ENCODINGS:
        return None
    if rest.startswith("compresseddepth"):
        codec = rest[len("compresseddepth"):].strip() or "png"
        return (encoding, codec) if codec in ("png", "rvl") else None
    if encoding != "32FC1" and rest.startswith("png"):
        return encoding, "plain-png"
    return None


def decode_compressed_depth(format_text: str, data: bytes | np.ndarray, where: str) -> np.ndarray:
    """The (H, W) uint16 millimetres a depth CompressedImage carries (see the module)."""
    kind = depth_format(format_text)
    if kind is None:
        raise FrameError(f"{where}: format {format_text!r} is not compressed depth (expected "
                         "'16UC1; compressedDepth png', '... rvl', '32FC1; compressedDepth ...' "
                         "or '16UC1; png compressed')")
    encoding, codec = kind
    payload = np.asarray(data, dtype=np.uint8).tobytes() if not isinstance(data, bytes) else data
    if codec == "plain-png":
        return _png(payload, where)
    if len(payload) <= _HEADER.size:
        raise FrameError(f"{where}: a compressedDepth payload of {len(payload)} bytes has no "
                         "image after its 12-byte header")
    _, quant_a, quant_b = _HEADER.unpack_from(payload)
    body = payload[_HEADER.size:]
    samples = _png(body, where) if codec == "png" else _rvl(body, where)
    if _ENCODINGS[encoding] == "mm":
        return samples
    if not (np.isfinite(quant_a) and np.isfinite(quant_b) and quant_a > 0):
        raise FrameError(f"{where}: a 32FC1 compressedDepth header with depth parameters "
                         f"{quant_a}, {quant_b} cannot be inverted")
    with np.errstate(divide="ignore", invalid="ignore"):
        metres = np.float32(quant_a) / (samples.astype(np.float32) - np.float32(quant_b))
    millimetres = np.floor(metres.astype(np.float64) * 1000.0 + 0.5)
    good = (samples > 0) & np.isfinite(millimetres) & (millimetres > 0) & (millimetres <= 65535)
    return np.where(good, millimetres, 0).astype(np.uint16)


def encode_compressed_depth(depth: np.ndarray, codec: str = "png", *,
                            png_level: int = 1) -> tuple[str, bytes]:
    """``(format, data)`` of the compressedDepth message image_transport sends for the (H, W)
    uint16 millimetre image ``depth``; ``codec`` ``"png"`` or ``"rvl"``."""
    depth = np.ascontiguousarray(depth)
    if depth.ndim != 2 or depth.dtype != np.uint16 or 0 in depth.shape:
        raise FrameError(f"encode_compressed_depth: an (H, W) uint16 image, got {depth.dtype} "
                         f"{depth.shape}")
    header = _HEADER.pack(0, 0.0, 0.0)
    if codec == "png":
        buffer = io.BytesIO()
        Image.fromarray(depth).save(buffer, format="PNG", compress_level=png_level)
        return "16UC1; compressedDepth png", header + buffer.getvalue()
    if codec == "rvl":
        words = np.empty(depth.size + 16, dtype=np.uint32)  # at worst 8 nibbles a pixel
        used = _rvl_encode(depth.ravel(), words)
        size = struct.pack("<II", depth.shape[1], depth.shape[0])
        return "16UC1; compressedDepth rvl", header + size + words[:used].astype("<u4").tobytes()
    raise FrameError(f"encode_compressed_depth: codec {codec!r}: choose 'png' or 'rvl'")


# --- the two image codecs ---------------------------------------------------------------------
def _png(data: bytes, where: str) -> np.ndarray:
    if not data.startswith(_PNG_MAGIC):
        raise FrameError(f"{where}: the compressed depth is not a PNG (by its first bytes)")
    try:
        samples = decode_image(data, where)
    except DepthFileError as exc:
        raise FrameError(str(exc)) from None
    if samples.dtype != np.uint16:
        raise FrameError(f"{where}: an 8-bit PNG is not compressed depth (16-bit expected)")
    return samples


def _rvl(body: bytes, where: str) -> np.ndarray:
    if len(body) < 8:
        raise FrameError(f"{where}: an RVL stream of {len(body)} bytes has no image size")
    width, height = struct.unpack_from("<II", body)
    pixels = width * height
    if not width or not height or pixels > _MAX_RVL_PIXELS:
        raise FrameError(f"{where}: an RVL stream of {len(body)} bytes cannot hold the "
                         f"{width}x{height} image its header gives")
    stream = body[8:]
    stream += b"\0" * (-len(stream) % 4)
    out = np.empty(pixels, dtype=np.uint16)
    got = _rvl_decode(np.frombuffer(stream, dtype="<u4").astype(np.uint32), out)
    if got != pixels:
        said = f"past the end of its {pixels} pixels" if got < 0 else f"{got} of {pixels} pixels"
        raise FrameError(f"{where}: the RVL stream is truncated or corrupt (it decodes {said})")
    return out.reshape(height, width)


@njit(cache=True, nogil=True)
def _rvl_next(words, state):  # pragma: no cover - compiled
    """The next variable-length value from ``words``; ``state`` (3,) int64: word index, the
    word being read (shifted), nibbles left in it.  -1 when the words run out or the value
    grows past 2^31."""
    value = np.int64(0)
    shift = 0
    while True:
        if state[2] == 0:
            if state[0] >= words.size:
                return np.int64(-1)
            state[1] = np.int64(words[state[0]])
            state[0] += 1
            state[2] = 8
        nibble = (state[1] >> 28) & 0xF
        state[1] = (state[1] << 4) & 0xFFFFFFFF
        state[2] -= 1
        value |= (nibble & 0x7) << shift
        shift += 3
        if not nibble & 0x8:
            return value
        if shift > 30:
            return np.int64(-1)


@njit(cache=True, nogil=True)
def _rvl_decode(words, out):  # pragma: no cover - compiled
    """Decode the RVL stream ``words`` (N,) uint32 into ``out`` (M,) uint16; the number of
    pixels written, or -1 when the stream is short or describes more than M pixels."""
    state = np.zeros(3, dtype=np.int64)
    n_out = out.size
    o = 0
    previous = np.int64(0)
    while o < n_out:
        zeros = _rvl_next(words, state)
        if zeros < 0 or o + zeros > n_out:
            return -1
        for _ in range(zeros):
            out[o] = 0
            o += 1
        readings = _rvl_next(words, state)
        if readings < 0 or o + readings > n_out:
            return -1
        for _ in range(readings):
            code = _rvl_next(words, state)
            if code < 0:
                return -1
            previous = (previous + ((code >> 1) ^ -(code & 1))) & 0xFFFF
            out[o] = previous
            o += 1
    return o


@njit(cache=True, nogil=True)
def _rvl_put(value, words, state):  # pragma: no cover - compiled
    while True:
        nibble = value & 0x7
        value >>= 3
        if value:
            nibble |= 0x8
        state[1] = ((state[1] << 4) | nibble) & 0xFFFFFFFF
        state[2] += 1
        if state[2] == 8:
            words[state[0]] = state[1]
            state[0] += 1
            state[1] = 0
            state[2] = 0
        if not value:
            return


@njit(cache=True, nogil=True)
def _rvl_encode(pixels, words):  # pragma: no cover - compiled
    """Encode ``pixels`` (M,) uint16 as RVL into ``words`` (M + 16 is enough: a pixel costs at
    most 6 nibbles of delta and 2 of run lengths); the number of words used."""
    state = np.zeros(3, dtype=np.int64)
    n = pixels.size
    i = 0
    previous = np.int64(0)
    while i < n:
        zeros = 0
        while i < n and pixels[i] == 0:
            zeros += 1
            i += 1
        _rvl_put(zeros, words, state)
        readings = 0
        while i + readings < n and pixels[i + readings] != 0:
            readings += 1
        _rvl_put(readings, words, state)
        for _ in range(readings):
            current = np.int64(pixels[i])
            delta = current - previous
            _rvl_put((delta << 1) ^ (delta >> 63), words, state)
            previous = current
            i += 1
    if state[2]:
        words[state[0]] = (state[1] << (4 * (8 - state[2]))) & 0xFFFFFFFF
        state[0] += 1
    return state[0]
