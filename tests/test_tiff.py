"""hw.tiff: our TIFF reader against Pillow (libtiff) and a hand-made TIFF writer, and its numba
PackBits/LZW kernels against plain-Python twins."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from hw import errors
from hw.tiff import lzw_decode, packbits_decode, read_tiff

RNG = np.random.default_rng(7)


def sample_image(shape, dtype=np.uint16):
    """Depth-like content with runs (for PackBits/LZW), random noise, 0 and the maximum."""
    height, width = shape
    y, x = np.mgrid[:height, :width]
    image = (700 + 9 * x + 4 * y).astype(dtype)
    image[:, : width // 3] = 0
    noise = RNG.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype, endpoint=True)
    image[height // 2 :] = noise[height // 2 :]
    image.flat[-1] = np.iinfo(dtype).max
    return image


def pillow_tiff(array, **save_options) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="TIFF", **save_options)
    return buffer.getvalue()


def pillow_decode(data: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(data))).astype(np.uint16)


# ---------------------------------------- plain-Python codecs (independent of hw.tiff)


def packbits_encode(data: bytes) -> bytes:
    """PackBits: runs of 3+ equal bytes as repeat packets, the rest as literal packets."""
    out = bytearray()
    i = 0
    while i < len(data):
        run = 1
        while i + run < len(data) and run < 128 and data[i + run] == data[i]:
            run += 1
        if run >= 3:
            out += bytes([257 - run, data[i]])
            i += run
            continue
        start = i
        while i < len(data) and i - start < 128:
            if i + 2 < len(data) and data[i] == data[i + 1] == data[i + 2]:
                break
            i += 1
        out.append(i - start - 1)
        out += data[start:i]
    return bytes(out)


def packbits_decode_plain(src: bytes, size: int) -> bytes:
    out = bytearray()
    i = 0
    while i < len(src) and len(out) < size:
        header = src[i]
        i += 1
        if header < 128:
            out += src[i : i + header + 1]
            i += header + 1
        elif header > 128:
            if i < len(src):
                out += bytes([src[i]]) * (257 - header)
            i += 1
    return bytes(out[:size])


def lzw_encode(data: bytes) -> bytes:
    """TIFF LZW: clear code first, MSB-first codes of 9-12 bits, the width growing when the
    next free code reaches 2**width (the decoder sees that one code early), clear when full."""
    codes: list[tuple[int, int]] = []
    width = 9

    def reset():
        return {bytes([i]): i for i in range(256)}, 258

    table, next_code = reset()
    codes.append((256, width))
    current = b""
    for value in data:
        candidate = current + bytes([value])
        if candidate in table:
            current = candidate
            continue
        codes.append((table[current], width))
        table[candidate] = next_code
        next_code += 1
        if next_code == 4094:
            codes.append((256, width))
            table, next_code = reset()
            width = 9
        elif next_code == 1 << width:
            width += 1
        current = bytes([value])
    if current:
        codes.append((table[current], width))
        next_code += 1
        if next_code == 1 << width and width < 12:
            width += 1
    codes.append((257, width))
    bits = "".join(format(code, f"0{size}b") for code, size in codes)
    bits += "0" * (-len(bits) % 8)
    return int(bits, 2).to_bytes(len(bits) // 8, "big") if bits else b""


def lzw_decode_plain(src: bytes) -> bytes:
    """Plain-Python twin of the numba LZW kernel."""
    bits = "".join(format(byte, "08b") for byte in src)
    position, width = 0, 9
    table: dict[int, bytes] = {}
    previous: bytes | None = None
    out = bytearray()
    while position + width <= len(bits):
        code = int(bits[position : position + width], 2)
        position += width
        if code == 256:
            table = {i: bytes([i]) for i in range(256)}
            width, previous = 9, None
            continue
        if code == 257:
            break
        if previous is None:
            entry = table[code]
        else:
            entry = table[code] if code in table else previous + previous[:1]
            table[len(table) + 2] = previous + entry[:1]  # codes 256/257 are not in the table
        out += entry
        previous = entry
        if len(table) + 2 + 1 >= (1 << width) and width < 12:
            width += 1
    return bytes(out)


# --------------------------------------------------------------- a hand-made TIFF writer

_FORMATS = {3: "H", 4: "I"}


def build_tiff(array, *, order="<", compression=1, predictor=1, rows_per_strip=None,
               tile=None, tags=None, omit_counts=False) -> bytes:
    """A TIFF made byte by byte: header, strips or tiles, then the directory."""
    height, width = array.shape
    dtype = np.dtype(f"{order}u{array.dtype.itemsize}")

    def encode(block: np.ndarray) -> bytes:
        block = block.astype(dtype.newbyteorder("="))
        if predictor == 2:
            block = block.copy()
            block[:, 1:] = block[:, 1:] - block[:, :-1]
        raw = block.astype(dtype).tobytes()
        return {1: lambda b: b, 32773: packbits_encode, 8: zlib.compress,
                32946: zlib.compress, 5: lzw_encode}[compression](raw)

    pieces = []
    if tile is None:
        rows = rows_per_strip or height
        for top in range(0, height, rows):
            pieces.append(encode(array[top : top + rows]))
    else:
        tile_h, tile_w = tile
        for top in range(0, height, tile_h):
            for left in range(0, width, tile_w):
                block = np.zeros(tile, dtype=array.dtype)
                part = array[top : top + tile_h, left : left + tile_w]
                block[: part.shape[0], : part.shape[1]] = part
                pieces.append(encode(block))
    body = bytearray(b"II*\x00" if order == "<" else b"MM\x00*")
    body += b"\x00\x00\x00\x00"
    offsets = []
    for piece in pieces:
        offsets.append(len(body))
        body += piece
    counts = [len(piece) for piece in pieces]
    entries = {256: (4, [width]), 257: (4, [height]), 258: (3, [8 * array.dtype.itemsize]),
               259: (3, [compression]), 262: (3, [1]), 277: (3, [1])}
    if predictor != 1:
        entries[317] = (3, [predictor])
    if tile is None:
        entries.update({273: (4, offsets), 278: (4, [rows_per_strip or height]),
                        279: (4, counts)})
        if omit_counts:
            del entries[279]
    else:
        entries.update({322: (4, [tile[1]]), 323: (4, [tile[0]]), 324: (4, offsets),
                        325: (4, counts)})
    entries.update(tags or {})
    if len(body) % 2:
        body += b"\x00"
    ifd_at = len(body)
    struct.pack_into(order + "I", body, 4, ifd_at)
    extra_at = ifd_at + 2 + 12 * len(entries) + 4
    directory, extra = bytearray(struct.pack(order + "H", len(entries))), bytearray()
    for tag in sorted(entries):
        kind, values = entries[tag]
        packed = struct.pack(order + _FORMATS[kind] * len(values), *values)
        if len(packed) <= 4:
            field = packed.ljust(4, b"\x00")
        else:
            field = struct.pack(order + "I", extra_at + len(extra))
            extra += packed
        directory += struct.pack(order + "HHI", tag, kind, len(values)) + field
    directory += b"\x00\x00\x00\x00"  # no next directory
    return bytes(body + directory + extra)


# ------------------------------------------------------------------------- the kernels


def test_numba_packbits_matches_plain_python():
    for trial in range(30):
        data = bytes(RNG.integers(0, 4, size=int(RNG.integers(1, 600)), dtype=np.uint8))
        packed = packbits_encode(data)
        dst = np.zeros(len(data), np.uint8)
        written = packbits_decode(np.frombuffer(packed, np.uint8), dst)
        assert written == len(data)
        assert dst.tobytes() == packbits_decode_plain(packed, len(data)) == data
    # arbitrary bytes (including the -128 no-op) decode the same way, cut at the output size
    for trial in range(30):
        src = RNG.integers(0, 256, size=50, dtype=np.uint8)
        dst = np.zeros(200, np.uint8)
        written = packbits_decode(src, dst)
        assert dst[:written].tobytes() == packbits_decode_plain(src.tobytes(), 200)


@pytest.mark.parametrize("size", [0, 1, 5, 700, 20_000])
def test_numba_lzw_matches_plain_python(size):
    data = bytes(RNG.integers(0, 256 if size < 1000 else 7, size=size, dtype=np.uint8))
    packed = lzw_encode(data)
    dst = np.zeros(size, np.uint8)
    written = lzw_decode(np.frombuffer(packed, np.uint8), dst)
    assert written == size
    assert dst.tobytes() == lzw_decode_plain(packed) == data


def test_lzw_kernel_reports_bad_codes_and_old_style_streams():
    bits = "100000000" + "111111111" + "000000"  # clear, then code 511 before any entry
    bad = np.frombuffer(int(bits, 2).to_bytes(3, "big"), np.uint8)
    assert lzw_decode(bad, np.zeros(10, np.uint8)) == -2
    assert lzw_decode(np.array([0, 1, 2, 3], np.uint8), np.zeros(10, np.uint8)) == -3


# ------------------------------------------------------------------ files that we read


def test_real_pcl_grabber_depth_tiffs_decode_like_pillow(shared_data):
    paths = sorted((shared_data / "pcl-grabber-seq").glob("*_depth.tiff"))
    assert len(paths) == 3
    for path in paths:
        depth = read_tiff(path)
        assert depth.dtype == np.uint16 and depth.shape == (480, 640)
        np.testing.assert_array_equal(depth, np.array(Image.open(path)), err_msg=str(path))
        assert 0 < depth.max() < 2000


def test_real_rgb_tiff_is_refused(shared_data):
    path = sorted((shared_data / "pcl-grabber-seq").glob("*_rgb.tiff"))[0]
    with pytest.raises(errors.DepthFileError, match="RGB TIFF .* is not a depth image"):
        read_tiff(path)


@pytest.mark.parametrize("compression", ["raw", "packbits", "tiff_lzw", "tiff_deflate",
                                         "tiff_adobe_deflate"])
@pytest.mark.parametrize("predictor", [1, 2])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (120, 90)])
def test_pillow_written_tiffs_decode_identically(compression, predictor, dtype, shape):
    array = sample_image(shape, dtype)
    data = pillow_tiff(array, compression=compression, tiffinfo={317: predictor})
    ours = read_tiff(data)
    assert ours.dtype == dtype
    np.testing.assert_array_equal(ours, array)
    np.testing.assert_array_equal(ours, pillow_decode(data))


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("compression, predictor", [(1, 1), (32773, 1), (8, 1), (8, 2),
                                                    (32946, 2), (5, 1), (5, 2)])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
@pytest.mark.parametrize("layout", ["one strip", "strips of 4", "strips of 1", "tiles"])
def test_hand_made_tiffs_decode_like_pillow(order, compression, predictor, dtype, layout):
    array = sample_image((37, 23), dtype)
    options = {"one strip": {}, "strips of 4": {"rows_per_strip": 4},
               "strips of 1": {"rows_per_strip": 1}, "tiles": {"tile": (16, 16)}}[layout]
    data = build_tiff(array, order=order, compression=compression, predictor=predictor,
                      **options)
    ours = read_tiff(data)
    assert ours.dtype == dtype and ours.dtype.isnative
    np.testing.assert_array_equal(ours, array)
    np.testing.assert_array_equal(ours, pillow_decode(data))


@pytest.mark.parametrize("order", ["<", ">"])
def test_large_lzw_strip_by_hand_decodes_like_pillow(order):
    # thousands of codes: every code width 9-12 and table resets (clear codes)
    array = sample_image((200, 150))
    data = build_tiff(array, order=order, compression=5, predictor=2)
    np.testing.assert_array_equal(read_tiff(data), array)
    np.testing.assert_array_equal(pillow_decode(data), array)


def test_uncompressed_strips_without_byte_counts(tmp_path):
    array = sample_image((10, 6))
    path = tmp_path / "no_counts.tif"
    path.write_bytes(build_tiff(array, rows_per_strip=3, omit_counts=True))
    np.testing.assert_array_equal(read_tiff(path), array)


def test_only_the_first_page_of_a_multi_page_file_is_read():
    first, second = sample_image((8, 9)), sample_image((4, 5)) + 1
    buffer = io.BytesIO()
    Image.fromarray(first).save(buffer, format="TIFF", save_all=True,
                                append_images=[Image.fromarray(second)])
    assert Image.open(io.BytesIO(buffer.getvalue())).n_frames == 2
    np.testing.assert_array_equal(read_tiff(buffer.getvalue()), first)


# ---------------------------------------------------------------------------- bad input


def test_missing_file_is_named(tmp_path):
    with pytest.raises(errors.DepthFileError, match=r"gone\.tiff: no such file"):
        read_tiff(tmp_path / "gone.tiff")


@pytest.mark.parametrize(
    "tags, complaint",
    [
        ({259: (3, [7])}, r"compression 7 \(JPEG\) is not supported"),
        ({259: (3, [34676])}, r"compression 34676 \(unknown\) is not supported"),
        ({339: (3, [3])}, "floating-point TIFF samples are not supported"),
        ({339: (3, [2])}, "signed integer TIFF samples are not supported"),
        ({262: (3, [2]), 277: (3, [3])}, "RGB TIFF with 3 samples per pixel is not a depth"),
        ({262: (3, [3])}, "palette TIFF .* is not a depth image"),
        ({262: (3, [0])}, "WhiteIsZero TIFF is not supported"),
        ({258: (3, [12])}, "12-bit TIFF is not supported"),
        ({317: (3, [3]), 259: (3, [8])}, r"predictor 3 \(floating-point\)"),
        ({256: (4, [100_000]), 257: (4, [100_000])}, "100000x100000 pixels is too large"),
    ],
)
def test_unsupported_tiffs_are_refused_with_the_reason(tmp_path, tags, complaint):
    path = tmp_path / "odd.tif"
    path.write_bytes(build_tiff(sample_image((4, 4)), tags=tags))
    with pytest.raises(errors.DepthFileError, match=r"odd\.tif: .*" + complaint):
        read_tiff(path)


def test_bigtiff_is_refused():
    with pytest.raises(errors.DepthFileError, match="BigTIFF is not supported"):
        read_tiff(b"II+\x00\x08\x00\x00\x00" + bytes(16))


@pytest.mark.parametrize("compression", [1, 32773, 8, 5])
def test_truncated_tiffs_are_reported(tmp_path, compression):
    data = build_tiff(sample_image((30, 20)), compression=compression, rows_per_strip=10)
    path = tmp_path / "cut.tif"
    ifd_at = struct.unpack_from("<I", data, 4)[0]
    # strips end before the directory: cut the file inside the directory and inside the data
    for length in (ifd_at + 20, ifd_at // 2, 6):
        path.write_bytes(data[:length])
        with pytest.raises(errors.DepthFileError, match=r"cut\.tif: (truncated|corrupt)"):
            read_tiff(path)


def test_a_strip_that_decodes_short_is_truncated():
    # the directory says 6 rows of 6, the strip holds 3 rows: half the bytes
    forged = build_tiff(sample_image((3, 6)), compression=8,
                        tags={257: (4, [6]), 278: (4, [6])})
    with pytest.raises(errors.DepthFileError,
                       match="strip 0: truncated TIFF, Deflate data gives 36 of 72 bytes"):
        read_tiff(forged)


@pytest.mark.parametrize("garbage, complaint", [
    (b"", "empty"),
    (b"GIF89a" + bytes(20), "not a TIFF"),
    (b"II\x2b\x01" + bytes(20), "not a TIFF"),
])
def test_garbage_is_not_a_tiff(garbage, complaint):
    with pytest.raises(errors.DepthFileError, match=complaint):
        read_tiff(garbage)


def test_corrupt_deflate_data_is_reported():
    data = bytearray(build_tiff(sample_image((5, 5)), compression=8))
    data[8:14] = b"\x00\xff\x00\xff\x00\xff"
    with pytest.raises(errors.DepthFileError, match="Deflate data does not decompress"):
        read_tiff(bytes(data))
