"""hw.oni: the .oni writer, the 16z / 16zT codecs, the header check and the pure-Python reader --
played back through the real libOpenNI2 (OniFile driver), so every pixel and timestamp is checked
by the native player (and :func:`read_oni_frames` must agree with it on every file)."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest

from hw.depth import Intrinsics
from hw.errors import DepthFileError, FrameError
from hw.oni import (
    MAX_16Z_VALUE,
    MAX_16ZT_VALUES,
    OniWriter,
    decode_frame,
    encode_16z,
    encode_16zt,
    read_oni_frames,
    read_oni_header,
    write_oni,
)
from hw.openni2 import open_recording


def room_depth(height: int, width: int, seed: int) -> np.ndarray:
    """A Kinect-like depth image (mm): a tilted floor/wall gradient, a box, noise, holes."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    depth = 1500.0 + 4.0 * yy + 1.5 * xx
    depth[height // 4: height // 2, width // 3: width // 2] = 900.0 + seed  # a box
    depth += rng.normal(0.0, 2.0, depth.shape)  # small noise: most steps fit in a nibble
    out = depth.astype(np.uint16)
    out[rng.random(out.shape) < 0.02] = 0  # dropouts
    out[: height // 10, :] = 0  # a band with no reading
    return out


def kinect_depth(height: int, width: int, seed: int) -> np.ndarray:
    """:func:`room_depth` quantised like a Kinect (disparity steps: ~2.6 mm at 1 m, ~24 mm at
    3 m), so a frame holds a few hundred distinct values."""
    z = room_depth(height, width, seed).astype(np.float64) / 1000.0
    c = 0.00285  # step = c z^2 (m)
    levels = np.round(1.0 / (c * np.maximum(z, 0.3)))
    out = np.round(1000.0 / (c * levels)).astype(np.uint16)
    out[z == 0] = 0
    return out


def play(path: Path, timeout: float = 5.0) -> list:
    """Every frame of a recording, through the real OpenNI2 player; checks that
    :func:`read_oni_frames` decodes exactly the same frames without it."""
    frames = []
    with open_recording(str(path)) as source:
        while True:
            frame = source.read(timeout)
            if frame is None:
                break
            frames.append(frame)
        assert source.read(0.1) is None  # stays ended
    ours = read_oni_frames(path)
    assert len(ours) == len(frames)
    for mine, theirs in zip(ours, frames, strict=True):
        np.testing.assert_array_equal(mine.depth, theirs.depth)
        assert (mine.timestamp_us, mine.index) == (theirs.timestamp_us, theirs.index)
    return frames


@pytest.mark.parametrize("codec", ["none", "16z", "16zt"])
def test_write_then_play_back_exact_pixels_timestamps_and_count(tmp_path: Path, codec: str) -> None:
    images = [room_depth(480, 640, 0), kinect_depth(480, 640, 1), room_depth(480, 640, 2),
              kinect_depth(480, 640, 3)]
    stamps = [0, 33_000, 70_123, 100_000]
    path = tmp_path / f"room-{codec}.oni"
    with OniWriter(path, 640, 480, codec=codec) as writer:
        for image, stamp in zip(images, stamps, strict=True):
            writer.write(image, stamp)
    frames = play(path)
    assert len(frames) == 4
    for image, stamp, frame, index in zip(images, stamps, frames, range(1, 5), strict=True):
        assert frame.depth.dtype == np.uint16 and frame.shape == (480, 640)
        np.testing.assert_array_equal(frame.depth, image)
        assert frame.timestamp_us == stamp
        assert frame.index == index
    info = read_oni_header(path)
    expected_codec = {"none": "NONE", "16z": "16zP", "16zt": "16zT"}[codec]
    assert (info.width, info.height, info.frames, info.codec) == (640, 480, 4, expected_codec)
    assert (info.first_timestamp_us, info.last_timestamp_us) == (0, 100_000)


def test_default_timestamps_follow_fps(tmp_path: Path) -> None:
    path = tmp_path / "fps.oni"
    write_oni(path, [room_depth(24, 32, s) for s in range(3)], fps=25)
    assert [f.timestamp_us for f in play(path)] == [0, 40_000, 80_000]
    assert read_oni_header(path).fps == 25


def test_16z_codes_every_kind_of_step_exactly(tmp_path: Path) -> None:
    # odd pixel count (a lone last difference), steps of every size class, value extremes,
    # and runs of equal pixels of 14, 15, 16 and 31 pairs (the run byte holds at most 15)
    rng = np.random.default_rng(7)
    parts = [
        np.array([0, 6, 0, 7, 0, 63, 0, 64, 0, MAX_16Z_VALUE, 0, MAX_16Z_VALUE, MAX_16Z_VALUE - 6]),
        np.full(29, 500), np.array([501]), np.full(31, 400), np.array([401]), np.full(33, 300),
        np.full(63, 700), np.array([0]),
        rng.integers(0, MAX_16Z_VALUE + 1, 200),  # mostly large jumps
        np.cumsum(rng.integers(-6, 7, 300)) + 5000,  # small steps
        np.cumsum(rng.integers(-63, 64, 300)) + 15000,  # medium steps
    ]
    flat = np.concatenate(parts)
    width = 7
    rows = flat.size // width
    rows -= rows % 2 == 0  # odd rows x odd width: an odd number of pixels
    image = flat[: rows * width].reshape(rows, width).astype(np.uint16)
    assert image.size % 2 == 1 and image.size > 900
    path = tmp_path / "steps.oni"
    write_oni(path, [image, image[::-1].copy()], codec="16z")
    frames = play(path)
    np.testing.assert_array_equal(frames[0].depth, image)
    np.testing.assert_array_equal(frames[1].depth, image[::-1])


def test_16z_is_much_smaller_than_raw() -> None:
    image = room_depth(480, 640, 1)
    assert len(encode_16z(image)) < image.nbytes / 3
    flat = encode_16z(np.full(101, 5, dtype=np.uint16))  # 100 equal steps: 50 pairs in runs
    assert flat == b"\x05\x00" + b"\xef\xef\xef\xe5"


def test_16z_rejects_values_it_cannot_store(tmp_path: Path) -> None:
    image = np.full((4, 4), MAX_16Z_VALUE + 1, dtype=np.uint16)
    with pytest.raises(FrameError, match="codec='none'"):
        write_oni(tmp_path / "big.oni", [image], codec="16z")
    assert not (tmp_path / "big.oni").exists()
    write_oni(tmp_path / "big.oni", [image], codec="none")  # raw keeps full uint16
    np.testing.assert_array_equal(play(tmp_path / "big.oni")[0].depth, image)


def test_16zt_byte_layout() -> None:
    # table length, the sorted distinct values, then 16z over the indices [1, 1, 2, 0]:
    # first index 1, a pair of steps (0, -1) -> 0x65, a lone step +2 -> 0x8D
    payload = encode_16zt(np.array([[1000, 1000], [2000, 0]], dtype=np.uint16))
    assert payload == bytes.fromhex("0300" "0000 e803 d007" "0100" "65" "8d")
    shape = (2, 2)
    np.testing.assert_array_equal(decode_frame(payload, shape, "16zt"), [[1000, 1000], [2000, 0]])


def test_16zt_is_much_smaller_than_16z_on_quantised_depth() -> None:
    image = kinect_depth(480, 640, 5)
    assert 100 < np.unique(image).size < 2000
    zt, z = len(encode_16zt(image)), len(encode_16z(image))
    assert zt < 0.7 * z, (zt, z)  # ~0.65 here; ~0.42 on the sim_fixtures Kinect frames


@pytest.mark.parametrize("case", ["zeros", "one_value", "full_range", "many_values", "max_values"])
def test_16zt_edge_cases_play_back_exactly(tmp_path: Path, case: str) -> None:
    rng = np.random.default_rng(3)
    if case == "zeros":
        image = np.zeros((480, 640), dtype=np.uint16)
    elif case == "one_value":  # beyond what 16z can hold
        image = np.full((48, 64), 65535, dtype=np.uint16)
    elif case == "full_range":  # 0 and 65535 next to each other: index jumps, not value jumps
        image = rng.choice(np.array([0, 1, 40000, 65535], dtype=np.uint16), (48, 64))
    elif case == "many_values":  # > 255 values, mostly large index jumps, odd pixel count
        image = rng.integers(0, 65536, (99, 101)).astype(np.uint16)
        assert np.unique(image).size > 5000
    else:  # exactly the table's limit: every odd value once, shuffled, 65535 included
        image = rng.permutation(np.arange(1, 65536, 2, dtype=np.uint16)).reshape(128, 256)
        assert np.unique(image).size == MAX_16ZT_VALUES
    path = tmp_path / f"{case}.oni"
    write_oni(path, [image, image[::-1].copy()], codec="16zt")
    assert read_oni_header(path).codec == "16zT"
    frames = play(path)
    assert len(frames) == 2
    np.testing.assert_array_equal(frames[0].depth, image)
    np.testing.assert_array_equal(frames[1].depth, image[::-1])


def test_16zt_rejects_more_distinct_values_than_its_table_holds(tmp_path: Path) -> None:
    values = np.concatenate([np.arange(0, 65536, 2), [1]]).astype(np.uint16)  # 32769 values
    image = np.zeros(129 * 256, dtype=np.uint16)
    image[: values.size] = values
    image = image.reshape(129, 256)
    assert np.unique(image).size == MAX_16ZT_VALUES + 1
    with pytest.raises(FrameError, match=r"32769 distinct.*codec='16z'"):
        write_oni(tmp_path / "many.oni", [image], codec="16zt")
    assert list(tmp_path.iterdir()) == []


def test_reader_rejects_frames_that_do_not_decode_to_the_image_size(tmp_path: Path) -> None:
    image = kinect_depth(24, 32, 0)
    good = encode_16z(image)
    with pytest.raises(FrameError, match="decodes to"):
        decode_frame(good[:-3], (24, 32), "16z")  # truncated
    with pytest.raises(FrameError, match="decodes to"):
        decode_frame(good + b"\x66", (24, 32), "16z")  # two pixels too many
    table_payload = encode_16zt(image)
    with pytest.raises(FrameError, match="past the end"):  # a table one entry short
        n = int.from_bytes(table_payload[:2], "little")
        short = (n - 1).to_bytes(2, "little") + table_payload[2: 2 * n] + table_payload[2 + 2 * n:]
        decode_frame(short, (24, 32), "16zt")
    with pytest.raises(FrameError, match="bytes of raw depth"):
        decode_frame(image.tobytes()[:-2], (24, 32), "none")
    # in a file: the reader names the frame
    path = tmp_path / "t.oni"
    write_oni(path, [image, image], codec="16zt")
    data = bytearray(path.read_bytes())
    at = data.rindex(table_payload)
    data[at: at + 2] = (0).to_bytes(2, "little")  # the second frame's table is empty
    bad = tmp_path / "bad.oni"
    bad.write_bytes(bytes(data))
    with pytest.raises(DepthFileError, match="corrupt: frame 2"):
        read_oni_frames(bad)


def test_intrinsics_round_trip_through_the_field_of_view(tmp_path: Path) -> None:
    intrinsics = Intrinsics(320, 240, 290.25, 288.5, 159.5, 119.5)
    path = tmp_path / "k.oni"
    write_oni(path, [room_depth(240, 320, 0)], intrinsics=intrinsics)
    assert read_oni_header(path).intrinsics() == intrinsics
    with open_recording(str(path)) as source:
        got = source.read(5.0).intrinsics
    assert got.fx == pytest.approx(290.25, abs=1e-3) and got.fy == pytest.approx(288.5, abs=1e-3)
    assert (got.cx, got.cy) == (159.5, 119.5)


def test_writer_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "partial.oni"
    with pytest.raises(RuntimeError):
        with OniWriter(path, 32, 24) as writer:
            writer.write(room_depth(24, 32, 0))
            raise RuntimeError("camera unplugged")
    assert list(tmp_path.iterdir()) == []  # neither the file nor its temp file
    with pytest.raises(FrameError, match="no frames"):
        OniWriter(path, 32, 24).close()
    assert list(tmp_path.iterdir()) == []


def test_writer_rejects_bad_frames(tmp_path: Path) -> None:
    with OniWriter(tmp_path / "x.oni", 32, 24) as writer:
        with pytest.raises(FrameError, match=r"\(24, 32\) uint16"):
            writer.write(np.zeros((24, 32), dtype=np.float32))
        with pytest.raises(FrameError, match=r"\(24, 32\) uint16"):
            writer.write(np.zeros((32, 24), dtype=np.uint16))
        writer.write(np.zeros((24, 32), dtype=np.uint16), 1000)
        with pytest.raises(FrameError, match="must not decrease"):
            writer.write(np.zeros((24, 32), dtype=np.uint16), 999)
    assert read_oni_header(tmp_path / "x.oni").frames == 1
    with pytest.raises(FrameError, match="codec"):
        OniWriter(tmp_path / "y.oni", 32, 24, codec="jpeg")
    with pytest.raises(FrameError, match="1600x1200"):
        OniWriter(tmp_path / "y.oni", 4000, 3000)
    with pytest.raises(DepthFileError, match="does not exist"):
        OniWriter(tmp_path / "no" / "such" / "dir.oni", 32, 24)


@pytest.fixture()
def good_file(tmp_path: Path) -> Path:
    path = tmp_path / "good.oni"
    write_oni(path, [room_depth(48, 64, s) for s in range(3)], codec="16z")
    return path


def test_header_check_describes_a_good_file(good_file: Path) -> None:
    info = read_oni_header(good_file)
    assert (info.width, info.height, info.fps, info.frames, info.version) == \
        (64, 48, 30, 3, (1, 0, 1, 0))


def test_header_check_rejects_missing_empty_and_foreign_files(tmp_path: Path) -> None:
    with pytest.raises(DepthFileError, match="does not exist"):
        read_oni_header(tmp_path / "nope.oni")
    with pytest.raises(DepthFileError, match="folder"):
        read_oni_header(tmp_path)
    (tmp_path / "empty.oni").write_bytes(b"")
    with pytest.raises(DepthFileError, match="not an .oni file"):
        read_oni_header(tmp_path / "empty.oni")
    (tmp_path / "png.oni").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(DepthFileError, match="not an OpenNI .oni file"):
        read_oni_header(tmp_path / "png.oni")
    noise = np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes()
    (tmp_path / "garbage.oni").write_bytes(b"NI10" + noise)
    with pytest.raises(DepthFileError):
        read_oni_header(tmp_path / "garbage.oni")


def test_header_check_rejects_a_newer_format_version(good_file: Path, tmp_path: Path) -> None:
    data = bytearray(good_file.read_bytes())
    data[4:12] = struct.pack("<BBHI", 2, 0, 0, 0)
    bad = tmp_path / "v2.oni"
    bad.write_bytes(bytes(data))
    with pytest.raises(DepthFileError, match="version 2.0.0.0"):
        read_oni_header(bad)


@pytest.mark.parametrize("keep", [30, 200, 0.5, -10, -1])
def test_header_check_rejects_truncated_files(good_file: Path, tmp_path: Path, keep: float) -> None:
    data = good_file.read_bytes()
    cut = int(len(data) * keep) if isinstance(keep, float) else \
        (keep if keep > 0 else len(data) + keep)
    bad = tmp_path / "cut.oni"
    bad.write_bytes(data[:cut])
    with pytest.raises(DepthFileError, match="truncated|not an .oni|corrupt|no depth"):
        read_oni_header(bad)


def test_header_check_rejects_a_corrupted_record(good_file: Path, tmp_path: Path) -> None:
    data = bytearray(good_file.read_bytes())
    data[24:28] = b"XXXX"  # the first record's magic
    bad = tmp_path / "bad.oni"
    bad.write_bytes(bytes(data))
    with pytest.raises(DepthFileError, match="corrupt"):
        read_oni_header(bad)


def test_write_oni_keeps_depth_frames_timestamps(tmp_path: Path, good_file: Path) -> None:
    originals = play(good_file)
    shifted = [type(f)(f.depth, f.timestamp_us + 5_000_000, f.index, f.intrinsics)
               for f in originals]
    copy = tmp_path / "copy.oni"
    assert write_oni(copy, shifted) == 3
    again = play(copy)
    assert [f.timestamp_us for f in again] == [f.timestamp_us for f in originals]  # rebased to 0
    for a, b in zip(again, originals, strict=True):
        np.testing.assert_array_equal(a.depth, b.depth)
    assert os.path.getsize(copy) > os.path.getsize(good_file)  # "none" is the default codec


def _decode_16z_twin(data: bytes, count: int) -> list[int]:
    """Plain-Python twin of hw.oni_codec._decode_16z (the 16zP stream -> pixel values)."""
    out = [data[0] | (data[1] << 8)]
    last, i = out[0], 2
    while i < len(data) and len(out) < count:
        c = data[i]
        i += 1
        if 0xE0 <= c < 0xFF:  # 0xE0 + n: n pairs equal to the last pixel
            out += [last] * (2 * (c - 0xE0))
            continue
        if c != 0xFF:
            last = (last - ((c >> 4) - 6)) & 0xFFFF
            out.append(last)
            low = c & 0x0F
            if low == 0x0D:
                continue
            if low != 0x0F:
                last = (last - (low - 6)) & 0xFFFF
                out.append(last)
                continue
        b = data[i]
        i += 1
        if b & 0x80:
            last = (last - (b - 192)) & 0xFFFF
        else:
            last = (b << 8) | data[i]
            i += 1
        out.append(last)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_16z_decoder_kernel_matches_its_python_twin(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # smooth runs, small and large steps, equal runs, zeros, and values that need two bytes
    depth = np.cumsum(rng.integers(-9, 10, size=(20, 31)), axis=1).astype(np.int64) + 1500
    depth[rng.random(depth.shape) < 0.1] = 0
    depth[3, 5:25] = 2000
    depth[7, ::3] = rng.integers(0, 32767, size=depth[7, ::3].shape)
    depth = np.clip(depth, 0, 32767).astype(np.uint16)
    payload = encode_16z(depth)
    got = decode_frame(payload, depth.shape, "16z")
    np.testing.assert_array_equal(got.ravel(), _decode_16z_twin(payload, depth.size))
    np.testing.assert_array_equal(got, depth)


def test_hw_oni_re_exports_the_codec_and_container_modules() -> None:
    """hw.oni stays the one import: names from hw.oni_codec / hw.oni_format are the same objects."""
    import hw.oni as oni
    import hw.oni_codec as oni_codec
    import hw.oni_format as oni_format

    assert len(oni.__all__) == len(set(oni.__all__))
    for name in oni.__all__:
        assert hasattr(oni, name), name
        for module in (oni_codec, oni_format):
            if hasattr(module, name):
                assert getattr(oni, name) is getattr(module, name), name
    assert oni._decode_16z is oni_codec._decode_16z  # the numba kernel the twin above checks


def test_the_stored_intrinsics_are_read_and_damaged_ones_passed_over(tmp_path: Path) -> None:
    """robot_change's intrinsics property is written only where the field of view does not
    give them back; read back whole; a principal point nowhere near the image (damaged) falls
    back to the field of view's."""
    off = Intrinsics(64, 48, 50.0, 52.0, 40.0, 30.0)
    path = tmp_path / "off.oni"
    write_oni(path, [np.full((48, 64), 1000, np.uint16)], intrinsics=off)
    assert read_oni_header(path).intrinsics() == off
    centred = tmp_path / "centred.oni"
    write_oni(centred, [np.full((48, 64), 1000, np.uint16)])
    assert b"robotChange" not in centred.read_bytes()
    data = bytearray(path.read_bytes())
    at = data.index(b"robotChangeIntrinsics") + len(b"robotChangeIntrinsics") + 1 + 4
    data[at + 16: at + 24] = struct.pack("<d", 1e6)  # cx
    path.write_bytes(bytes(data))
    got = read_oni_header(path).intrinsics()
    assert (got.cx, got.cy) == (31.5, 23.5) and got.fx == pytest.approx(50.0, abs=1e-3)
