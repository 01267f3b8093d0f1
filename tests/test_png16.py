"""hw.png16: 16-bit grayscale PNGs decoded without Pillow.  Its row kernel has a plain NumPy
twin here (the PNG specification's filters, section 9.2, written out); PNGs with every filter
type are written here and checked against Pillow, the reader every other PNG goes to, and
Pillow's own PNGs (adaptive filters) against it too."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from hw.errors import DepthFileError
from hw.imagefile import MAX_PIXELS, decode_image
from hw.png16 import decode_png16, unfilter16


# --- the NumPy twin and a writer of any filter ---------------------------------------------------
def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def twin_unfilter16(raw: np.ndarray, height: int, width: int) -> np.ndarray | None:
    """The twin of unfilter16: (H, W) uint16, None at a filter type beyond 4."""
    rows = raw.reshape(height, 1 + 2 * width).astype(np.int64)
    prev = np.zeros(2 * width, dtype=np.int64)
    out = np.empty((height, 2 * width), dtype=np.int64)
    for i in range(height):
        kind, row = rows[i, 0], rows[i, 1:]
        if kind > 4:
            return None
        cur = np.zeros(2 * width, dtype=np.int64)
        for x in range(2 * width):  # left and upper-left depend on this row's earlier bytes
            left = cur[x - 2] if x >= 2 else 0
            up_left = prev[x - 2] if x >= 2 else 0
            predictor = [0, left, prev[x], (left + prev[x]) // 2,
                         int(_paeth(np.int64(left), prev[x], np.int64(up_left)))][kind]
            cur[x] = (row[x] + predictor) % 256
        out[i] = cur
        prev = cur
    return (out[:, 0::2] * 256 + out[:, 1::2]).astype(np.uint16)


def filtered_rows(depth: np.ndarray, kinds: list[int]) -> bytes:
    """The PNG image data (before deflate) of ``depth`` (H, W) uint16, row i filtered with
    ``kinds[i]``."""
    data = depth.astype(">u2").view(np.uint8).reshape(depth.shape[0], -1).astype(np.int64)
    out = []
    prev = np.zeros(data.shape[1], dtype=np.int64)
    for row, kind in zip(data, kinds, strict=True):
        left = np.concatenate([[0, 0], row[:-2]])
        up_left = np.concatenate([[0, 0], prev[:-2]])
        predictor = [np.zeros_like(row), left, prev, (left + prev) // 2,
                     _paeth(left, prev, up_left)][kind]
        out.append(bytes([kind]) + ((row - predictor) % 256).astype(np.uint8).tobytes())
        prev = row
    return b"".join(out)


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(
        ">I", zlib.crc32(kind + body))


def png(width: int, height: int, image_data: bytes, *, depth: int = 16, colour: int = 0,
        interlace: int = 0, extra: bytes = b"", split: int = 1) -> bytes:
    """A PNG of already filtered ``image_data``, deflated, in ``split`` IDAT chunks."""
    deflated = zlib.compress(image_data)
    step = -(-len(deflated) // split)
    idat = b"".join(chunk(b"IDAT", deflated[i:i + step]) for i in range(0, len(deflated), step))
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra + idat + chunk(b"IEND", b"")


def _pillow(data: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(data)))


def _depths(rng: np.random.Generator) -> list[np.ndarray]:
    """Depth-like images and hard ones: smooth walls, every value, sharp edges, 1-pixel wide."""
    v, u = np.mgrid[0:37, 0:53]
    wall = (1500 + 7 * u + 3 * v).astype(np.uint16)
    wall[10:20, 5:30] = 0
    wall[25:, 40:] = 65535
    return [wall, rng.integers(0, 65536, (29, 31)).astype(np.uint16),
            rng.integers(0, 65536, (5, 1)).astype(np.uint16),
            np.full((3, 4), 65535, np.uint16)]


# --- the kernel against its twin and Pillow -----------------------------------------------------
@pytest.mark.parametrize("kinds", ["each", "mixed"])
def test_the_row_kernel_matches_its_twin_and_pillow_for_every_filter(kinds):
    rng = np.random.default_rng(7)
    for depth in _depths(rng):
        height, width = depth.shape
        choices = [[k] * height for k in range(5)] if kinds == "each" else \
            [list(rng.integers(0, 5, height))]
        for chosen in choices:
            raw = filtered_rows(depth, chosen)
            out = np.empty_like(depth)
            assert unfilter16(np.frombuffer(raw, np.uint8), out)
            assert np.array_equal(out, depth)
            assert np.array_equal(twin_unfilter16(np.frombuffer(raw, np.uint8), height, width),
                                  depth)
            data = png(width, height, raw, split=3)
            assert np.array_equal(_pillow(data), depth)  # the written PNG is right
            assert np.array_equal(decode_png16(data, "x", MAX_PIXELS), depth)


def test_the_kernel_and_its_twin_refuse_a_filter_type_beyond_4():
    raw = bytearray(filtered_rows(np.ones((3, 2), np.uint16), [0, 0, 0]))
    raw[5] = 7  # the second row's filter type
    out = np.empty((3, 2), np.uint16)
    assert not unfilter16(np.frombuffer(bytes(raw), np.uint8), out)
    assert twin_unfilter16(np.frombuffer(bytes(raw), np.uint8), 3, 2) is None
    with pytest.raises(DepthFileError, match="x: corrupt PNG .*filter type"):
        decode_png16(png(2, 3, bytes(raw)), "x", MAX_PIXELS)


@pytest.mark.parametrize("level", [0, 1, 6, 9])
def test_pillows_own_pngs_decode_as_pillow_reads_them(level):
    depth = _depths(np.random.default_rng(3))[0]
    buffer = io.BytesIO()
    Image.fromarray(depth).save(buffer, format="PNG", compress_level=level)
    assert np.array_equal(decode_png16(buffer.getvalue(), "x", MAX_PIXELS), depth)


# --- what goes to Pillow, and what is refused ---------------------------------------------------
@pytest.mark.parametrize("case", ["8-bit", "rgb", "interlaced", "trns", "plte", "no-iend",
                                  "short-chunk", "ihdr-not-first", "idat-apart", "not-png"])
def test_anything_but_a_plain_16_bit_gray_png_goes_to_pillow(case):
    depth = np.arange(12, dtype=np.uint16).reshape(3, 4)
    raw = filtered_rows(depth, [0, 0, 0])
    if case == "8-bit":
        data = png(4, 3, b"".join(b"\0" + bytes(4) for _ in range(3)), depth=8)
    elif case == "rgb":
        data = png(4, 3, raw, colour=2)
    elif case == "interlaced":
        data = png(4, 3, raw, interlace=1)
    elif case == "trns":
        data = png(4, 3, raw, extra=chunk(b"tRNS", b"\0\5"))
    elif case == "plte":  # a critical chunk a grayscale PNG must not have
        data = png(4, 3, raw, extra=chunk(b"PLTE", bytes(3)))
    elif case == "no-iend":
        data = png(4, 3, raw)[:-12]
    elif case == "short-chunk":
        data = png(4, 3, raw)[:-20] + png(4, 3, raw)[-12:]
    elif case == "ihdr-not-first":
        whole = png(4, 3, raw)
        data = whole[:8] + chunk(b"tEXt", b"a\0b") + whole[8:]
    elif case == "idat-apart":
        whole = png(4, 3, raw, split=2)
        first_end = 8 + 25 + 12 + struct.unpack_from(">I", whole, 33)[0]
        data = whole[:first_end] + chunk(b"tEXt", b"a\0b") + whole[first_end:]
    else:
        data = b"GIF89a" + bytes(40)
    assert decode_png16(data, "x", MAX_PIXELS) is None


def test_ancillary_chunks_are_passed_over():
    depth = np.arange(12, dtype=np.uint16).reshape(3, 4)
    data = png(4, 3, filtered_rows(depth, [1, 2, 3]), extra=chunk(b"tEXt", b"a\0b"))
    assert np.array_equal(decode_png16(data, "x", MAX_PIXELS), depth)


@pytest.mark.parametrize("case", ["corrupt-stream", "checksum", "unended", "short", "long",
                                  "too-large"])
def test_a_plain_png_with_bad_image_data_is_a_typed_error_naming_it(case):
    depth = np.arange(12, dtype=np.uint16).reshape(3, 4)
    raw = filtered_rows(depth, [0, 0, 0])
    if case in ("corrupt-stream", "checksum"):
        deflated = bytearray(zlib.compress(raw))
        if case == "checksum":  # the stream whole, its Adler-32 wrong: a bit flipped in transit
            deflated[-1] ^= 1
        else:
            deflated[2:6] = b"\xff\xff\xff\xff"
        ihdr = struct.pack(">IIBBBBB", 4, 3, 16, 0, 0, 0, 0)
        data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", bytes(deflated)) \
            + chunk(b"IEND", b"")
    elif case == "unended":  # every row there, the stream's end and checksum cut off
        deflater = zlib.compressobj()
        deflated = deflater.compress(raw) + deflater.flush(zlib.Z_SYNC_FLUSH)
        ihdr = struct.pack(">IIBBBBB", 4, 3, 16, 0, 0, 0, 0)
        data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", deflated) \
            + chunk(b"IEND", b"")
    elif case == "short":
        data = png(4, 4, raw)
    elif case == "long":
        data = png(4, 2, raw)
    else:
        data = png(4, 3, raw)
    match = "too large" if case == "too-large" else "run7.png: truncated"
    with pytest.raises(DepthFileError, match=match):
        decode_png16(data, "run7.png", 11 if case == "too-large" else MAX_PIXELS)


def test_decode_image_reads_plain_pngs_here_and_others_with_pillow():
    depth = np.arange(12, dtype=np.uint16).reshape(3, 4)
    assert np.array_equal(decode_image(png(4, 3, filtered_rows(depth, [4, 4, 4])), "x"), depth)
    interlaced = png(4, 3, filtered_rows(depth, [0, 0, 0]), interlace=1)
    with pytest.raises(DepthFileError, match="x: truncated or corrupt PNG"):
        decode_image(interlaced, "x")  # Pillow's answer: Adam7 rows are laid out otherwise


_FUZZ_BASE = png(5, 4, filtered_rows(np.arange(20, dtype=np.uint16).reshape(4, 5) * 999,
                                     [0, 1, 3, 4]), extra=chunk(b"tEXt", b"a\0b"))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(_FUZZ_BASE) - 1), st.integers(0, 255)),
                min_size=1, max_size=4), st.integers(8, len(_FUZZ_BASE)))
def test_damaged_pngs_give_samples_or_a_depth_file_error_never_another_exception(flips, keep):
    data = bytearray(_FUZZ_BASE)
    for at, value in flips:
        data[at] = value
    data = bytes(data[:keep])
    for decode in (lambda d: decode_png16(d, "x", MAX_PIXELS), lambda d: decode_image(d, "x")):
        try:
            out = decode(data)
        except DepthFileError:
            continue
        assert out is None or (out.dtype in (np.uint16, np.uint8) and out.ndim == 2)
