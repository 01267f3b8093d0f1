"""hw.png: our PNG codec against Pillow, a hand-made encoder, and a plain-Python unfilter."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from hw import errors
from hw.png import (
    PNG_SIGNATURE,
    encode_png,
    filter_rows,
    read_png,
    unfilter_rows,
    write_png,
)

RNG = np.random.default_rng(20240611)
SHAPES = [(1, 1), (1, 7), (5, 1), (3, 5), (17, 33), (31, 64)]


def random_depth(shape, dtype=np.uint16):
    """Random values over the whole range, with 0 and the maximum always present."""
    values = RNG.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype, endpoint=True)
    values.flat[0] = 0
    values.flat[-1] = np.iinfo(dtype).max
    return values


def smooth_depth(shape):
    """Depth-like values (a slanted plane, a box, holes) so every filter type is worth using."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    depth = (800 + 3 * x + 5 * y).astype(np.uint16)
    depth[shape[0] // 3 : shape[0] // 2, shape[1] // 4 : shape[1] // 2] = 650
    depth[::7, ::5] = 0
    return depth


def pillow_decode(data: bytes) -> np.ndarray:
    return np.array(Image.open(io.BytesIO(data)))


# --- a hand-made encoder, independent of hw.png, so the reader is not checked against itself


def plain_unfilter(raw: np.ndarray, height: int, row_bytes: int, bpp: int) -> np.ndarray:
    """Plain-Python twin of the numba kernel, written straight from the PNG specification."""
    out = np.zeros((height, row_bytes), dtype=np.uint8)
    for y in range(height):
        kind = int(raw[y * (row_bytes + 1)])
        line = raw[y * (row_bytes + 1) + 1 : (y + 1) * (row_bytes + 1)]
        for x in range(row_bytes):
            a = int(out[y, x - bpp]) if x >= bpp else 0
            b = int(out[y - 1, x]) if y > 0 else 0
            c = int(out[y - 1, x - bpp]) if x >= bpp and y > 0 else 0
            if kind == 0:
                predicted = 0
            elif kind == 1:
                predicted = a
            elif kind == 2:
                predicted = b
            elif kind == 3:
                predicted = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                predicted = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            out[y, x] = (int(line[x]) + predicted) % 256
    return out


def hand_filter(rows: np.ndarray, bpp: int, kinds: list[int]) -> bytes:
    """Filter each row with the given type, in plain Python (the spec's forward filters)."""
    height, row_bytes = rows.shape
    out = bytearray()
    for y in range(height):
        out.append(kinds[y])
        for x in range(row_bytes):
            value = int(rows[y, x])
            a = int(rows[y, x - bpp]) if x >= bpp else 0
            b = int(rows[y - 1, x]) if y > 0 else 0
            c = int(rows[y - 1, x - bpp]) if x >= bpp and y > 0 else 0
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            paeth = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            predicted = (0, a, b, (a + b) // 2, paeth)[kinds[y]]
            out.append((value - predicted) % 256)
    return bytes(out)


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def hand_png(array: np.ndarray, kinds: list[int], *, colour_type: int = 0,
             interlace: int = 0, idat_pieces: int = 1) -> bytes:
    """A PNG built byte by byte: IHDR, the filtered rows zlib-compressed in ``idat_pieces``
    IDAT chunks, a text chunk, IEND."""
    bit_depth = 16 if array.dtype == np.uint16 else 8
    height, width = array.shape[:2]
    rows = array.astype(">u2" if bit_depth == 16 else np.uint8).view(np.uint8).reshape(height, -1)
    channels = 1 if array.ndim == 2 else array.shape[2]
    compressed = zlib.compress(hand_filter(rows, channels * bit_depth // 8, kinds), 9)
    header = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, interlace)
    cut = np.linspace(0, len(compressed), idat_pieces + 1).astype(int)
    idats = [chunk(b"IDAT", compressed[a:b]) for a, b in zip(cut[:-1], cut[1:])]
    text = chunk(b"tEXt", b"Comment\x00made by hand")
    return PNG_SIGNATURE + chunk(b"IHDR", header) + text + b"".join(idats) + chunk(b"IEND", b"")


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("filter_type", [None, 0, 1, 2, 3, 4])
def test_uint16_round_trip(tmp_path, shape, filter_type):
    depth = random_depth(shape)
    path = tmp_path / "depth.png"
    write_png(path, depth, filter_type=filter_type)
    back = read_png(path)
    assert back.dtype == np.uint16 and back.dtype.isnative
    np.testing.assert_array_equal(back, depth)
    np.testing.assert_array_equal(pillow_decode(path.read_bytes()), depth)


@pytest.mark.parametrize("shape", SHAPES)
def test_uint8_round_trip(shape):
    gray = random_depth(shape, np.uint8)
    data = encode_png(gray, level=1)
    back = read_png(data)
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, gray)
    np.testing.assert_array_equal(pillow_decode(data), gray)


@pytest.mark.parametrize("filter_type", [None, 1, 3, 4])
def test_rgb_is_written_for_pillow_but_not_read_as_depth(filter_type):
    rgb = random_depth((9, 13, 3), np.uint8)
    data = encode_png(rgb, filter_type=filter_type)
    np.testing.assert_array_equal(pillow_decode(data), rgb)
    with pytest.raises(errors.DepthFileError, match="8-bit RGB PNG is not a depth image"):
        read_png(data)


def test_adaptive_filtering_uses_several_filters_and_compresses_smooth_depth():
    depth = smooth_depth((120, 160))
    rows = depth.astype(">u2").view(np.uint8).reshape(120, -1)
    chosen = set(filter_rows(rows, 2, None)[:, 0].tolist())
    assert len(chosen) >= 2
    adaptive = encode_png(depth)
    assert len(adaptive) < len(encode_png(depth, filter_type=0))
    np.testing.assert_array_equal(read_png(adaptive), depth)


@pytest.mark.parametrize("level", [0, 1, 9])
def test_zlib_level_is_honoured(level):
    depth = smooth_depth((40, 50))
    data = encode_png(depth, level=level)
    np.testing.assert_array_equal(read_png(data), depth)
    if level == 0:
        assert len(data) > depth.nbytes  # stored, not compressed


def test_large_image_spans_several_idat_chunks():
    depth = random_depth((700, 800))  # ~1.1 MB of incompressible data -> 2 IDAT chunks
    data = encode_png(depth, level=1)
    assert data.count(b"IDAT") >= 2
    np.testing.assert_array_equal(read_png(data), depth)


def test_write_is_atomic_and_leaves_no_temp_file(tmp_path, monkeypatch):
    path = tmp_path / "depth.png"
    write_png(path, smooth_depth((8, 8)))
    old = path.read_bytes()

    def broken_replace(*args):
        raise OSError("disk gone")

    monkeypatch.setattr("hw.atomic.os.replace", broken_replace)
    with pytest.raises(OSError, match="disk gone"):
        write_png(path, random_depth((8, 8)))
    assert path.read_bytes() == old
    assert [p.name for p in tmp_path.iterdir()] == ["depth.png"]


def test_write_into_a_missing_folder_is_a_depth_file_error(tmp_path):
    with pytest.raises(errors.DepthFileError, match="cannot write"):
        write_png(tmp_path / "nowhere" / "depth.png", smooth_depth((4, 4)))


@pytest.mark.parametrize(
    "array, options, complaint",
    [
        (np.zeros((4, 4), np.float32), {}, "float32"),
        (np.zeros((4, 4, 3), np.uint16), {}, "uint16"),
        (np.zeros((4, 4, 4), np.uint8), {}, r"\(4, 4, 4\)"),
        (np.zeros((0, 4), np.uint16), {}, "4x0"),
        (np.zeros((4, 4), np.uint16), {"level": 10}, "level"),
        (np.zeros((4, 4), np.uint16), {"filter_type": 5}, "filter type"),
    ],
)
def test_writer_refuses_what_it_cannot_write(array, options, complaint):
    with pytest.raises(errors.FrameError, match=complaint):
        encode_png(array, **options)


# ----------------------------------------------------------- against Pillow and by hand


@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
@pytest.mark.parametrize("shape", [(1, 1), (6, 11), (64, 97)])
def test_pillow_written_pngs_decode_identically(dtype, shape):
    array = smooth_depth(shape).astype(dtype) if dtype == np.uint16 else random_depth(shape, dtype)
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", optimize=True)
    data = buffer.getvalue()
    np.testing.assert_array_equal(read_png(data), pillow_decode(data))
    np.testing.assert_array_equal(read_png(data), array)


@pytest.mark.parametrize("kind", range(5))
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_each_filter_type_by_hand_decodes_like_pillow(kind, dtype):
    array = random_depth((13, 21), dtype)
    array[4:9] = smooth_depth((5, 21)).astype(dtype)
    data = hand_png(array, [kind] * 13, idat_pieces=3)
    ours = read_png(data)
    np.testing.assert_array_equal(ours, pillow_decode(data))
    np.testing.assert_array_equal(ours, array)


def test_mixed_filter_types_by_hand_decode_like_pillow():
    array = random_depth((25, 10))
    kinds = [int(k) for k in RNG.integers(0, 5, 25)]
    data = hand_png(array, kinds)
    np.testing.assert_array_equal(read_png(data), pillow_decode(data))
    np.testing.assert_array_equal(read_png(data), array)


@pytest.mark.parametrize("bpp", [1, 2, 3])
def test_numba_unfilter_matches_plain_python(bpp):
    height, row_bytes = 9, 6 * bpp
    raw = RNG.integers(0, 256, size=height * (row_bytes + 1), dtype=np.uint8)
    raw[:: row_bytes + 1] = [0, 1, 2, 3, 4, 4, 3, 2, 1]
    out = np.empty((height, row_bytes), dtype=np.uint8)
    unfilter_rows(raw, out, bpp)
    np.testing.assert_array_equal(out, plain_unfilter(raw, height, row_bytes, bpp))
    # the first row has no row above: Up, Average and Paeth must treat it as zeros
    for kind in (2, 3, 4):
        raw[0] = kind
        unfilter_rows(raw, out, bpp)
        np.testing.assert_array_equal(out, plain_unfilter(raw, height, row_bytes, bpp))


# -------------------------------------------------------------------------- real data


def test_tum_depth_png_decodes_like_pillow(shared_data):
    path = shared_data / "open3d-tum-sample" / "TUM_depth.png"
    depth = read_png(path)
    assert depth.shape == (480, 640) and depth.dtype == np.uint16
    np.testing.assert_array_equal(depth, np.array(Image.open(path)))


def test_osd_tabletop_depth_pngs_decode_like_pillow(shared_data):
    paths = sorted((shared_data / "osd-tabletop" / "derived").glob("*_depth_mm.png"))
    assert paths
    for path in paths:
        depth = read_png(path)
        np.testing.assert_array_equal(depth, np.array(Image.open(path)), err_msg=str(path))
        assert 0 < depth.max() < 2000  # millimetres on a table top


# ---------------------------------------------------------------------------- bad input


def test_missing_file_is_named(tmp_path):
    with pytest.raises(errors.DepthFileError, match=r"missing\.png: no such file"):
        read_png(tmp_path / "missing.png")


def test_a_folder_is_not_a_png(tmp_path):
    with pytest.raises(errors.DepthFileError, match="is a folder"):
        read_png(tmp_path)


@pytest.mark.parametrize(
    "mode, complaint",
    [
        ("RGB", "8-bit RGB PNG is not a depth image"),
        ("RGBA", "8-bit RGBA PNG is not a depth image"),
        ("LA", "8-bit gray\\+alpha PNG is not a depth image"),
        ("P", "-bit palette PNG is not a depth image"),
        ("1", "1-bit grayscale PNG is not supported"),
    ],
)
def test_non_grayscale_pngs_are_refused(mode, complaint):
    buffer = io.BytesIO()
    Image.new(mode, (4, 3)).save(buffer, format="PNG")
    with pytest.raises(errors.DepthFileError, match=complaint):
        read_png(buffer.getvalue())


def test_16_bit_gray_alpha_is_refused():
    data = hand_png(random_depth((3, 4, 2)), [0, 0, 0], colour_type=4)
    with pytest.raises(errors.DepthFileError, match="16-bit gray\\+alpha PNG is not a depth"):
        read_png(data)


def test_interlaced_png_is_refused_clearly():
    data = hand_png(random_depth((4, 4)), [0] * 4, interlace=1)
    with pytest.raises(errors.DepthFileError, match="Adam7"):
        read_png(data)


def test_every_truncation_is_a_depth_file_error_naming_the_file(tmp_path):
    data = encode_png(random_depth((20, 30)))
    path = tmp_path / "cut.png"
    for length in sorted({0, 5, 8, 12, 30, 40, len(data) // 2, len(data) - 13, len(data) - 1}):
        path.write_bytes(data[:length])
        with pytest.raises(errors.DepthFileError, match=r"cut\.png: (truncated|empty)"):
            read_png(path)


def test_bad_crc_is_reported(tmp_path):
    data = bytearray(encode_png(random_depth((6, 6))))
    data[len(PNG_SIGNATURE) + 8 + 2] ^= 0x01  # a byte of IHDR's width
    path = tmp_path / "crc.png"
    path.write_bytes(bytes(data))
    with pytest.raises(errors.DepthFileError, match=r"crc\.png: corrupt PNG, chunk IHDR .*CRC"):
        read_png(path)


def test_corrupt_image_data_with_valid_crc_is_reported():
    data = hand_png(random_depth((5, 5)), [0] * 5)
    start = data.index(b"IDAT") - 4
    (length,) = struct.unpack_from(">I", data, start)
    forged = chunk(b"IDAT", b"\x78\x9c" + b"\xff" * (length - 2))
    data = data[:start] + forged + data[start + 12 + length :]
    with pytest.raises(errors.DepthFileError, match="does not decompress"):
        read_png(data)


def test_a_header_asking_for_a_huge_image_is_refused():
    header = struct.pack(">IIBBBBB", 100_000, 100_000, 16, 0, 0, 0, 0)
    data = PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0"))
    with pytest.raises(errors.DepthFileError, match="100000x100000 pixels is too large"):
        read_png(data + chunk(b"IEND", b""))


def test_unknown_filter_type_is_reported():
    header = struct.pack(">IIBBBBB", 2, 2, 8, 0, 0, 0, 0)
    body = zlib.compress(bytes([0, 1, 2, 7, 3, 4]))
    data = PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", body) + chunk(b"IEND", b"")
    with pytest.raises(errors.DepthFileError, match="row 1 has unknown filter type 7"):
        read_png(data)


def test_image_data_longer_than_the_header_says_is_reported():
    header = struct.pack(">IIBBBBB", 2, 2, 8, 0, 0, 0, 0)
    body = zlib.compress(bytes(9))
    data = PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", body) + chunk(b"IEND", b"")
    with pytest.raises(errors.DepthFileError, match="more than the 2x2 pixels"):
        read_png(data)


@pytest.mark.parametrize("garbage", [b"", b"hello world, not an image", bytes(range(256)) * 4])
def test_garbage_is_not_a_png(garbage):
    with pytest.raises(errors.DepthFileError, match="(not a PNG|empty)"):
        read_png(garbage)
