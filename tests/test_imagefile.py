"""hw.imagefile: depth PNG and TIFF files through Pillow, checked against files made by hand
(an independent PNG encoder and TIFF writer, straight from the specifications), against
tifffile for the real TIFFs, and for every kind of bad file a DepthFileError naming it."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from hw import errors
from hw.imagefile import read_image, write_png

RNG = np.random.default_rng(20240611)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


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
    idats = [chunk(b"IDAT", compressed[a:b]) for a, b in zip(cut[:-1], cut[1:], strict=True)]
    text = chunk(b"tEXt", b"Comment\x00made by hand")
    return PNG_SIGNATURE + chunk(b"IHDR", header) + text + b"".join(idats) + chunk(b"IEND", b"")


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




# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (17, 33), (120, 160)])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_round_trip(tmp_path, shape, dtype):
    array = random_depth(shape, dtype)
    write_png(tmp_path / "a.png", array)
    back = read_image(tmp_path / "a.png")
    assert back.dtype == dtype and back.shape == shape
    np.testing.assert_array_equal(back, array)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # atomic: no temp file left


@pytest.mark.parametrize("level", [0, 1, 9])
def test_the_zlib_level_is_honoured(tmp_path, level):
    depth = smooth_depth((240, 320))
    write_png(tmp_path / f"{level}.png", depth, level=level)
    np.testing.assert_array_equal(read_image(tmp_path / f"{level}.png"), depth)
    if level == 0:
        assert (tmp_path / "0.png").stat().st_size > depth.nbytes


@pytest.mark.parametrize("kinds", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4, 2, 1]])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_hand_made_pngs_decode_right(kinds, dtype):
    array = smooth_depth((7, 9)).astype(dtype) if dtype == np.uint8 else smooth_depth((7, 9))
    rows = (kinds * 7)[:7]
    np.testing.assert_array_equal(read_image(hand_png(array, rows, idat_pieces=3)), array)


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("compression, predictor", [(1, 1), (32773, 1), (8, 1), (8, 2),
                                                    (32946, 2), (5, 1), (5, 2)])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
@pytest.mark.parametrize("layout", ["one strip", "strips of 4", "tiles"])
def test_hand_made_tiffs_decode_right(order, compression, predictor, dtype, layout):
    array = sample_image((37, 23), dtype)
    options = {"one strip": {}, "strips of 4": {"rows_per_strip": 4},
               "tiles": {"tile": (16, 16)}}[layout]
    data = build_tiff(array, order=order, compression=compression, predictor=predictor,
                      **options)
    got = read_image(data)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, array)


def test_only_the_first_page_of_a_multi_page_tiff_is_read():
    first, second = sample_image((6, 5)), sample_image((6, 5))[::-1].copy()
    buffer = io.BytesIO()
    Image.fromarray(first).save(buffer, format="TIFF", save_all=True,
                                append_images=[Image.fromarray(second)])
    np.testing.assert_array_equal(read_image(buffer.getvalue()), first)


# -------------------------------------------------------------------------- real data


def test_real_pcl_grabber_depth_tiffs_decode_like_tifffile(shared_data):
    tifffile = pytest.importorskip("tifffile")
    paths = sorted((shared_data / "pcl-grabber-seq").glob("*_depth.tiff"))
    assert len(paths) == 3
    for path in paths:
        depth = read_image(path)
        assert depth.dtype == np.uint16 and depth.shape == (480, 640)
        np.testing.assert_array_equal(depth, tifffile.imread(path), err_msg=str(path))
        assert 0 < depth.max() < 2000


def test_real_rgb_tiff_is_refused(shared_data):
    path = sorted((shared_data / "pcl-grabber-seq").glob("*_rgb.tiff"))[0]
    with pytest.raises(errors.DepthFileError, match="RGB TIFF is not a depth image"):
        read_image(path)


def test_tum_and_table_top_depth_pngs_decode(shared_data):
    tum = read_image(shared_data / "open3d-tum-sample" / "TUM_depth.png")
    assert tum.shape == (480, 640) and tum.dtype == np.uint16 and tum.max() > 5000  # 5000/m
    paths = sorted((shared_data / "osd-tabletop" / "derived").glob("*_depth_mm.png"))
    assert paths
    for path in paths:
        depth = read_image(path)
        assert depth.dtype == np.uint16 and 0 < depth.max() < 2000, path  # mm on a table top


# ---------------------------------------------------------------------------- bad input


def test_missing_file_and_folder_are_named(tmp_path):
    with pytest.raises(errors.DepthFileError, match=r"missing\.png: no such file"):
        read_image(tmp_path / "missing.png")
    with pytest.raises(errors.DepthFileError, match="is a folder"):
        read_image(tmp_path)


@pytest.mark.parametrize("mode, complaint", [
    ("RGB", "RGB PNG is not a depth image"), ("RGBA", "RGBA PNG is not a depth image"),
    ("LA", "gray\\+alpha PNG is not a depth image"), ("P", "palette PNG is not a depth image"),
    ("1", "1-bit .* PNG is not a depth image"),
])
def test_non_grayscale_pngs_are_refused(mode, complaint):
    buffer = io.BytesIO()
    Image.new(mode, (4, 3)).save(buffer, format="PNG")
    with pytest.raises(errors.DepthFileError, match=complaint):
        read_image(buffer.getvalue())


@pytest.mark.parametrize("tags, complaint", [
    ({339: (3, [3]), 258: (3, [32])}, "floating-point TIFF is not a depth image"),
    ({262: (3, [2]), 277: (3, [3])}, "TIFF"),
])
def test_non_depth_tiffs_are_refused(tmp_path, tags, complaint):
    path = tmp_path / "odd.tif"
    path.write_bytes(build_tiff(sample_image((4, 4)), tags=tags))
    with pytest.raises(errors.DepthFileError, match=r"odd\.tif: .*" + complaint):
        read_image(path)


def test_every_truncation_is_a_depth_file_error_naming_the_file(tmp_path):
    buffer = io.BytesIO()
    Image.fromarray(random_depth((20, 30))).save(buffer, format="PNG")
    data = buffer.getvalue()
    path = tmp_path / "cut.png"
    for length in sorted({0, 5, 8, 12, 30, 40, len(data) // 2, len(data) - 40}):
        path.write_bytes(data[:length])
        with pytest.raises(errors.DepthFileError, match=r"cut\.png: "):
            read_image(path)
    # a cut in the trailer only (the last chunk's CRC, IEND) leaves every pixel: read whole,
    # never wrong
    for length in (len(data) - 13, len(data) - 1):
        path.write_bytes(data[:length])
        np.testing.assert_array_equal(read_image(path), np.array(Image.open(io.BytesIO(data))))
    tiff = build_tiff(sample_image((30, 20)), compression=8, rows_per_strip=10)
    for length in (len(tiff) // 2, 20, 6):
        path.write_bytes(tiff[:length])
        with pytest.raises(errors.DepthFileError, match=r"cut\.png: "):
            read_image(path)


def test_a_bad_crc_and_corrupt_image_data_are_reported():
    data = bytearray(hand_png(random_depth((6, 6)), [0] * 6))
    data[len(PNG_SIGNATURE) + 8 + 2] ^= 0x01  # a byte of IHDR's width
    with pytest.raises(errors.DepthFileError, match="truncated or corrupt PNG"):
        read_image(bytes(data))
    good = hand_png(random_depth((5, 5)), [0] * 5)
    start = good.index(b"IDAT") - 4
    (length,) = struct.unpack_from(">I", good, start)
    forged = chunk(b"IDAT", b"\x78\x9c" + b"\xff" * (length - 2))
    with pytest.raises(errors.DepthFileError, match="truncated or corrupt PNG"):
        read_image(good[:start] + forged + good[start + 12 + length:])


def test_a_header_asking_for_a_huge_image_is_refused():
    header = struct.pack(">IIBBBBB", 100_000, 100_000, 16, 0, 0, 0, 0)
    data = PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0"))
    with pytest.raises(errors.DepthFileError, match="(too large|corrupt)"):
        read_image(data + chunk(b"IEND", b""))


@pytest.mark.parametrize("garbage, complaint", [
    (b"", "empty"), (b"hello world, not an image", "neither a PNG nor a TIFF"),
    (b"GIF89a" + bytes(20), "neither a PNG nor a TIFF"),
    (b"II+\x00\x08\x00\x00\x00" + bytes(16), "BigTIFF is not supported"),
])
def test_garbage_is_refused(garbage, complaint):
    with pytest.raises(errors.DepthFileError, match=complaint):
        read_image(garbage)


@pytest.mark.parametrize("array, level", [
    (np.zeros((3, 4), np.int32), 6), (np.zeros((3, 4, 2), np.uint8), 6),
    (np.zeros((0, 4), np.uint16), 6), (np.zeros((3, 4), np.uint16), 10),
])
def test_the_writer_refuses_what_it_cannot_write(tmp_path, array, level):
    with pytest.raises(errors.FrameError):
        write_png(tmp_path / "x.png", array, level=level)


def test_writing_into_a_missing_folder_is_a_depth_file_error(tmp_path):
    with pytest.raises(errors.DepthFileError, match="cannot write"):
        write_png(tmp_path / "no" / "such" / "x.png", np.zeros((2, 2), np.uint16))
