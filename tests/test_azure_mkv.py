"""The Azure Kinect recording reader (sim_fixtures.azure_mkv): the real capture in
../shared/data decodes to what its README measured, the depth camera's intrinsics follow the
SDK's mode conversion, and a file that is not such a recording (truncated, another format, no
DEPTH track) is a clear error naming it.  A small recording written here checks the walk
(unknown sizes, BlockGroups, timestamps) where the shared data is absent."""

from __future__ import annotations

import numpy as np
import pytest

from sim_fixtures.azure_mkv import (
    MkvError,
    depth_intrinsics,
    read_depth_blocks,
    read_depth_frames,
    read_tracks,
)

FOLDER = "azure-kinect-tof-1capture"


def _element(eid: int, payload: bytes, unknown: bool = False) -> bytes:
    """An EBML element: its id, an 8-byte size (all ones: unknown) and the payload."""
    size = b"\x01" + b"\xff" * 7 if unknown else (len(payload) | 1 << 56).to_bytes(8, "big")
    return eid.to_bytes((eid.bit_length() + 7) // 8, "big") + size + payload


def _uint(eid: int, value: int) -> bytes:
    return _element(eid, value.to_bytes(max(1, (value.bit_length() + 7) // 8), "big"))


def _track(number: int, name: str, width: int, height: int, fourcc: bytes) -> bytes:
    bitmap = (40).to_bytes(4, "little") + bytes(12) + fourcc + bytes(20)
    return _element(0xAE, _uint(0xD7, number) + _element(0x536E, name.encode())
                    + _element(0x86, b"V_MS/VFW/FOURCC") + _element(0x63A2, bitmap)
                    + _element(0xE0, _uint(0xB0, width) + _uint(0xBA, height)))


def _block(track: int, timecode: int, frame: np.ndarray) -> bytes:
    return bytes([0x80 | track]) + timecode.to_bytes(2, "big", signed=True) + b"\x80" + \
        frame.astype(">u2").tobytes()


def _recording(frames, doc_type=b"matroska", unknown=True, fourcc=b"b16g") -> bytes:
    """EBML header + a Segment (unknown size when ``unknown``): Info (1 ms timecodes), Tracks
    (DEPTH 3 x 2, IR), a Cluster at 10 with a SimpleBlock at +5, an unknown-size Cluster at 50
    with a BlockGroup, Cues."""
    header = _element(0x1A45DFA3, _element(0x4282, doc_type))
    tracks = _element(0x1654AE6B, _track(1, "DEPTH", 3, 2, fourcc) + _track(2, "IR", 3, 2,
                                                                             fourcc))
    info = _element(0x1549A966, _uint(0x2AD7B1, 1_000_000))
    ir = np.full((2, 3), 7, np.uint16)
    first = _element(0x1F43B675, _uint(0xE7, 10) + _element(0xA3, _block(2, 5, ir))
                     + _element(0xA3, _block(1, 5, frames[0])))
    second = _element(0x1F43B675, _uint(0xE7, 50) + _element(0xA0, _element(
        0xA1, _block(1, 0, frames[1]))), unknown=unknown)
    cues = _element(0x1C53BB6B, b"")
    return header + _element(0x18538067, info + tracks + first + second + cues,
                             unknown=unknown)


FRAMES = [np.array([[0, 1, 258], [1500, 65535, 3]], np.uint16),
          np.array([[9, 0, 0], [2000, 1, 2]], np.uint16)]


@pytest.mark.parametrize("unknown", [False, True])
def test_a_recording_s_depth_blocks_are_read_big_endian_with_their_times(tmp_path, unknown):
    path = tmp_path / "small.mkv"
    path.write_bytes(_recording(FRAMES, unknown=unknown))
    assert [t.name for t in read_tracks(path)] == ["DEPTH", "IR"]
    blocks = read_depth_blocks(path)
    assert [b.timestamp_us for b in blocks] == [15_000, 50_000]
    for block, frame in zip(blocks, FRAMES, strict=True):
        assert block.depth.dtype == np.uint16 and block.depth.shape == (2, 3)
        np.testing.assert_array_equal(block.depth, frame)
    np.testing.assert_array_equal(read_depth_blocks(path, "IR")[0].depth, 7)


def test_not_a_depth_recording_is_a_clear_error(tmp_path):
    path = tmp_path / "other.mkv"
    path.write_bytes(_recording(FRAMES, doc_type=b"dvdish"))
    with pytest.raises(MkvError, match=f"{path}.*not matroska"):
        read_depth_frames(path)
    path.write_bytes(_recording(FRAMES, fourcc=b"MJPG"))
    with pytest.raises(MkvError, match="not the 16-bit big-endian grey"):
        read_depth_frames(path)
    path.write_bytes(_recording(FRAMES).replace(b"DEPTH", b"DEPTX"))
    with pytest.raises(MkvError, match="no DEPTH track"):
        read_depth_frames(path)
    with pytest.raises(FileNotFoundError, match="missing.mkv"):
        read_depth_frames(tmp_path / "missing.mkv")


def test_the_capture_s_depth_frame_decodes_to_the_readme_statistics(shared_data):
    """README: valid 76.5 %, p1 / p50 / p99 0.18 / 1.49 / 2.19 m, max 3.69 m, 1873 distinct
    values 1 mm apart (no disparity steps); the block at 463,945 us."""
    path = shared_data / FOLDER / "recording.mkv"
    assert [(t.name, t.fourcc, t.width, t.height) for t in read_tracks(path)] == [
        ("COLOR", "MJPG", 1280, 720), ("DEPTH", "b16g", 640, 576), ("IR", "b16g", 640, 576),
        ("IMU", "", 0, 0)]
    (block,) = read_depth_blocks(path)
    assert block.timestamp_us == 463_945
    depth = block.depth
    assert depth.shape == (576, 640) and depth.dtype == np.uint16
    valid = depth[depth > 0]
    assert valid.size / depth.size == pytest.approx(0.765, abs=0.002)
    p1, p50, p99 = np.percentile(valid, [1, 50, 99])
    assert (p1, p50, p99) == (pytest.approx(180, abs=5), pytest.approx(1490, abs=5),
                              pytest.approx(2190, abs=5))
    assert valid.max() == 3690
    values = np.unique(valid)
    assert values.size == 1873
    assert np.mean(np.diff(values) == 1) > 0.98  # 1 mm steps
    # the corners are outside the NFOV mode's hexagonal field of view
    assert not depth[:20, :20].any() and not depth[-20:, -20:].any()
    np.testing.assert_array_equal(read_depth_frames(path)[0], depth)


def test_the_nfov_intrinsics_follow_the_sdk_mode_conversion(shared_data):
    """Normalised to the 1024 x 1024 sensor: x 1024, minus the NFOV crop (192, 180), minus
    half a pixel (pixel centres at integers)."""
    K = depth_intrinsics(shared_data / FOLDER / "calibration.json")
    assert (K.width, K.height) == (640, 576)
    assert K.fx == pytest.approx(0.4927808940410614 * 1024)  # ~504.6, as the README says
    assert K.fy == pytest.approx(0.49290284514427185 * 1024)
    assert K.cx == pytest.approx(0.5129697918891907 * 1024 - 192.5)  # 332.78
    assert K.cy == pytest.approx(0.5169235467910767 * 1024 - 180.5)  # 348.83
    wide = depth_intrinsics(shared_data / FOLDER / "calibration.json", "WFOV_UNBINNED")
    assert (wide.width, wide.cx) == (1024, pytest.approx(K.cx + 192))


@pytest.mark.parametrize("keep", [3, 200, 8000, 500_000, 1_699_250])
def test_a_truncated_capture_is_a_clear_error(shared_data, tmp_path, keep):
    path = tmp_path / "cut.mkv"
    path.write_bytes((shared_data / FOLDER / "recording.mkv").read_bytes()[:keep])
    with pytest.raises(MkvError, match=f"{path}: not a readable Azure Kinect recording"):
        read_depth_frames(path)


def test_a_foreign_file_is_a_clear_error(shared_data, tmp_path):
    calibration = shared_data / FOLDER / "calibration.json"
    with pytest.raises(MkvError, match=f"{calibration}.*no EBML header"):
        read_depth_frames(calibration)
    with pytest.raises(MkvError, match="not an Azure Kinect calibration"):
        depth_intrinsics(shared_data / FOLDER / "README.md")
    with pytest.raises(ValueError, match="unknown depth mode"):
        depth_intrinsics(calibration, "NFOV_3X3")
