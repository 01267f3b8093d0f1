"""Compressed depth in bags (hw.compressed_depth, hw.rosbag): image_transport's compressedDepth
(PNG and RVL, 16UC1 and quantised 32FC1) and compressed PNG, in ROS 1 and ROS 2 bags written by
rosbags' own writers (RealSense recordings, compressedDepth written by librealsense itself, are
in test_realsense.py).

The RVL kernels have a plain-Python twin here, written from the reference codec's description
(image_transport_plugins' rvl_codec.cpp), that they must match bit for bit.
"""

from __future__ import annotations

import io
import struct

import numpy as np
import pytest
from PIL import Image
from test_rosbag import CAMERA, write_bag

from hw.compressed_depth import decode_compressed_depth, depth_format, encode_compressed_depth
from hw.depth import open_depth
from hw.errors import FrameError

TOPIC = "/camera/depth/image_raw/compressedDepth"


# --- the plain-Python twin of RVL ----------------------------------------------------------------
def twin_rvl_encode(pixels: np.ndarray) -> bytes:
    nibbles: list[int] = []

    def put(value: int) -> None:
        while True:
            nibble, value = value & 7, value >> 3
            nibbles.append(nibble | (8 if value else 0))
            if not value:
                return

    values = [int(v) for v in pixels.ravel()]
    i, previous = 0, 0
    while i < len(values):
        start = i
        while i < len(values) and values[i] == 0:
            i += 1
        put(i - start)
        start = i
        while i < len(values) and values[i] != 0:
            i += 1
        put(i - start)
        for value in values[start:i]:
            delta = value - previous
            put((delta << 1) ^ (delta >> 63))
            previous = value
    nibbles += [0] * (-len(nibbles) % 8)
    words = [int("".join(f"{n:x}" for n in nibbles[k:k + 8]), 16)
             for k in range(0, len(nibbles), 8)]
    return struct.pack(f"<{len(words)}I", *words)


def twin_rvl_decode(stream: bytes, count: int) -> np.ndarray:
    words = struct.unpack(f"<{len(stream) // 4}I", stream)
    nibbles = [(word >> (28 - 4 * k)) & 0xF for word in words for k in range(8)]
    position = 0

    def take() -> int:
        nonlocal position
        value, shift = 0, 0
        while True:
            nibble = nibbles[position]
            position += 1
            value |= (nibble & 7) << shift
            shift += 3
            if not nibble & 8:
                return value

    out, previous = [], 0
    while len(out) < count:
        out += [0] * take()
        for _ in range(take()):
            code = take()
            previous = (previous + ((code >> 1) ^ -(code & 1))) & 0xFFFF
            out.append(previous)
    return np.array(out, dtype=np.uint16)


def random_depth(rng, height=48, width=64) -> np.ndarray:
    depth = rng.integers(400, 8000, (height, width)).astype(np.uint16)
    depth[rng.random((height, width)) < 0.3] = 0  # holes, in runs and alone
    depth[5:9, :] = 0
    depth[20, 3] = 65535  # the largest step there is
    return depth


def test_rvl_kernels_match_their_twin_bit_for_bit():
    rng = np.random.default_rng(7)
    for trial in range(6):
        depth = random_depth(rng) if trial else np.zeros((48, 64), np.uint16)
        text, data = encode_compressed_depth(depth, "rvl")
        assert text == "16UC1; compressedDepth rvl"
        stream = data[12 + 8:]
        assert stream == twin_rvl_encode(depth)
        assert np.array_equal(twin_rvl_decode(stream, depth.size), depth.ravel())
        assert np.array_equal(decode_compressed_depth(text, data, "x"), depth)


def test_rvl_known_answer():
    # 0, 0, 5, 6: nibbles 2 (zeros), 2 (readings), A 1 (zigzag 10), 2 (zigzag 1) -> one word
    depth = np.array([[0, 0, 5, 6]], np.uint16)
    _, data = encode_compressed_depth(depth, "rvl")
    assert data == bytes(12) + struct.pack("<II", 4, 1) + struct.pack("<I", 0x22A12000)


def test_compressed_depth_png_and_the_compressed_transport():
    depth = random_depth(np.random.default_rng(1))
    text, data = encode_compressed_depth(depth, "png")
    assert text == "16UC1; compressedDepth png" and data[12:20] == b"\x89PNG\r\n\x1a\n"
    assert np.array_equal(decode_compressed_depth(text, data, "x"), depth)
    assert np.array_equal(decode_compressed_depth("16UC1; compressedDepth", data, "x"), depth)
    buffer = io.BytesIO()
    Image.fromarray(depth).save(buffer, format="PNG")
    for text in ("16UC1; png compressed", "mono16; png compressed mono16"):
        assert np.array_equal(decode_compressed_depth(text, buffer.getvalue(), "x"), depth)
    for text in ("bgr8; jpeg compressed bgr8", "rgb8; compressedDepth png", "16UC1; jpeg",
                 "32FC1; png compressed", "16UC1; compressedDepth zstd"):
        assert depth_format(text) is None


def quantised_inverse_depth(depth_mm: np.ndarray, z0: float = 100.0, max_m: float = 10.0):
    """A 32FC1 image as image_transport's compressedDepth sends it (its encoder's arithmetic)."""
    a = np.float32(z0 * (z0 + 1.0))
    b = np.float32(1.0 - a / np.float32(max_m))
    metres = np.where(depth_mm > 0, depth_mm / 1000.0, np.inf).astype(np.float32)
    q = np.where(metres < max_m, (a / metres + b), 0).astype(np.uint16)
    buffer = io.BytesIO()
    Image.fromarray(q).save(buffer, format="PNG")
    return "32FC1; compressedDepth png", struct.pack("<iff", 0, a, b) + buffer.getvalue()


def test_32fc1_quantised_inverse_depth_decodes_within_its_step():
    depth = random_depth(np.random.default_rng(2))
    depth[0, :4] = [12000, 9999, 450, 0]  # beyond max -> no reading; the rest near
    text, data = quantised_inverse_depth(depth)
    got = decode_compressed_depth(text, data, "x")
    assert got[0, 0] == 0 and got[0, 3] == 0
    seen = depth < 10000
    assert np.array_equal(got > 0, seen & (depth > 0))
    # inverse-depth steps: d^2 / A (A = 10100 m) -> 6.3 mm at 8 m, well under 1 mm at 1 m
    error = np.abs(got.astype(float) - depth)[seen & (depth > 0)]
    step = (depth[seen & (depth > 0)] / 1000.0) ** 2 / 10100.0 * 1000.0
    assert np.all(error <= step + 1.0)


@pytest.mark.parametrize("text,data,match", [
    ("16UC1; compressedDepth png", bytes(12), "no image after its 12-byte header"),
    ("16UC1; compressedDepth png", bytes(12) + b"GIF89a....", "not a PNG"),
    ("16UC1; compressedDepth rvl", bytes(12) + struct.pack("<II", 0, 480), "cannot hold"),
    ("16UC1; compressedDepth rvl", bytes(12) + struct.pack("<II", 60000, 60000), "cannot hold"),
    ("32FC1; compressedDepth png", struct.pack("<iff", 0, np.nan, 0) + b"\x89PNG\r\n\x1a\n",
     "cannot be inverted|corrupt PNG"),
    ("rgb8; jpeg compressed", b"\xff\xd8", "not compressed depth"),
])
def test_broken_payloads_are_frame_errors(text, data, match):
    with pytest.raises(FrameError, match=match):
        decode_compressed_depth(text, data, "bag /t message 3")


def test_a_truncated_rvl_stream_is_a_frame_error():
    depth = random_depth(np.random.default_rng(3))
    text, data = encode_compressed_depth(depth, "rvl")
    with pytest.raises(FrameError, match="RVL stream is truncated or corrupt"):
        decode_compressed_depth(text, data[:len(data) // 2], "x")


# --- in bags -------------------------------------------------------------------------------------
def codec(name: str):
    def make(k: int, depth: np.ndarray):
        if name == "png32":
            return quantised_inverse_depth(depth)
        return encode_compressed_depth(depth, name)
    return make


@pytest.mark.parametrize("kind", ("ros1", "db3", "mcap"))
@pytest.mark.parametrize("name", ("png", "rvl"))
def test_compressed_depth_topics_are_found_and_read_exactly(tmp_path, depth_frames, kind, name):
    bag = write_bag(tmp_path / "run", kind, depth_frames, topic=TOPIC, compressed=codec(name))
    with open_depth(f"rosbag:{bag}") as source:  # found without being named
        frames = list(source)
        assert source.topic == TOPIC and source.info_topic == "/camera/depth/camera_info"
        assert source.intrinsics == CAMERA
    assert len(frames) == len(depth_frames)
    for frame, depth in zip(frames, depth_frames, strict=True):
        assert np.array_equal(frame.depth, depth)


def test_a_quantised_32fc1_topic_reads_as_millimetres(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames[:2], topic=TOPIC,
                    compressed=codec("png32"))
    with open_depth(f"rosbag:{bag}") as source:
        frame = source.read()
    expected = quantised_inverse_depth(depth_frames[0])
    assert np.array_equal(frame.depth, decode_compressed_depth(*expected, "x"))
    assert np.abs(frame.depth.astype(int) - depth_frames[0])[depth_frames[0] > 0].max() <= 5


def test_a_corrupt_message_names_the_bag_topic_and_index_and_reading_goes_on(tmp_path,
                                                                            depth_frames):
    frames = depth_frames * 2

    def sometimes_broken(k: int, depth: np.ndarray):
        text, data = encode_compressed_depth(depth, "png")
        return (text, data[:200]) if k == 2 else (text, data)

    bag = write_bag(tmp_path / "run", "db3", frames, topic=TOPIC, compressed=sometimes_broken,
                    stamps=[10**9 * (k + 1) for k in range(len(frames))])
    with open_depth(f"rosbag:{bag}") as source:
        got = [source.read(), source.read()]
        with pytest.raises(FrameError) as caught:
            source.read()
        got += [source.read(), source.read(), source.read()]
        assert source.read() is None
        assert source.stats.dropped == 1
    assert f"{bag} {TOPIC} message 2" in str(caught.value)
    assert "truncated or corrupt PNG" in str(caught.value)
    assert [f.index for f in got] == [0, 1, 2, 3, 4]
    assert all(np.array_equal(f.depth, frames[k])
               for f, k in zip(got, (0, 1, 3, 4, 5), strict=True))


def test_the_listing_names_compressed_depth_as_depth(tmp_path, depth_frames):
    bag = write_bag(tmp_path / "run", "mcap", depth_frames[:1], topic=TOPIC,
                    compressed=codec("rvl"))
    with pytest.raises(Exception, match=f"Depth image topics in this bag: {TOPIC} "
                                        r"\(16UC1; compressedDepth rvl\)"):
        open_depth(f"rosbag:{bag}?topic=/nothing").open()
