"""Azure Kinect recordings as a depth source (``mkv:``, hw.azure_kinect over hw.mkv_format): the
real capture in ../shared/data decodes to what its README measured, with the intrinsics of its
attached factory calibration converted as the SDK converts them and its camera named for the
``auto`` noise profile; small recordings written here check the walk (unknown sizes,
BlockGroups, timestamps, looping, tags, attachments) where the shared data is absent; a file
that is not such a recording, cut or damaged anywhere, is a DepthFileError naming it, never
another exception."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hw.azure_kinect import (
    DEPTH_MODES,
    DepthCalibration,
    depth_calibration,
    undistort,
    undistortion_table,
)
from hw.depth import Intrinsics, open_depth, parse_uri
from hw.errors import DepthFileError, HwError, UriError
from hw.mkv_format import MkvFile

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


def _tags(**tags: str) -> bytes:
    simple = b"".join(_element(0x67C8, _element(0x45A3, k.encode()) + _element(0x4487, v.encode()))
                      for k, v in tags.items())
    return _element(0x1254C367, _element(0x7373, simple))


def _attachment(name: str, data: bytes) -> bytes:
    return _element(0x1941A469, _element(0x61A7, _element(0x466E, name.encode())
                                         + _element(0x4660, b"application/octet-stream")
                                         + _element(0x465C, data)))


def _calibration(cx=0.5, cy=0.5, fx=0.5, fy=0.5) -> bytes:
    camera = {"Location": "CALIBRATION_CameraLocationD0", "SensorWidth": 1024,
              "SensorHeight": 1024, "Intrinsics": {
                  "ModelType": "CALIBRATION_LensDistortionModelBrownConrady",
                  "ModelParameters": [cx, cy, fx, fy] + [0.0] * 10}}
    return json.dumps({"CalibrationInformation": {"Cameras": [camera]}}).encode()


def _recording(frames, doc_type=b"matroska", unknown=True, fourcc=b"b16g", extra=b"") -> bytes:
    """EBML header + a Segment (unknown size when ``unknown``): Info (1 ms timecodes), Tracks
    (DEPTH and IR of the frames' size), ``extra`` (tags, attachments), a Cluster at 10 with a
    SimpleBlock at +5, an unknown-size Cluster at 50 with a BlockGroup, Cues."""
    header = _element(0x1A45DFA3, _element(0x4282, doc_type))
    h, w = frames[0].shape
    tracks = _element(0x1654AE6B, _track(1, "DEPTH", w, h, fourcc) + _track(2, "IR", w, h,
                                                                             fourcc))
    info = _element(0x1549A966, _uint(0x2AD7B1, 1_000_000))
    ir = np.full((h, w), 7, np.uint16)
    first = _element(0x1F43B675, _uint(0xE7, 10) + _element(0xA3, _block(2, 5, ir))
                     + _element(0xA3, _block(1, 5, frames[0])))
    second = _element(0x1F43B675, _uint(0xE7, 50) + _element(0xA0, _element(
        0xA1, _block(1, 0, frames[1]))), unknown=unknown)
    cues = _element(0x1C53BB6B, b"")
    return header + _element(0x18538067, info + tracks + extra + first + second + cues,
                             unknown=unknown)


FRAMES = [np.array([[0, 1, 258], [1500, 65535, 3]], np.uint16),
          np.array([[9, 0, 0], [2000, 1, 2]], np.uint16)]
SMALL = "1.5,1.5,1,0.5"  # intrinsics for the 3 x 2 frames


@pytest.mark.parametrize("unknown", [False, True])
def test_a_recording_s_depth_frames_are_read_big_endian_with_their_times(tmp_path, unknown):
    path = tmp_path / "small.mkv"
    path.write_bytes(_recording(FRAMES, unknown=unknown))
    with MkvFile(path) as mkv:
        tracks = mkv.tracks()
        assert [t.name for t in tracks] == ["DEPTH", "IR"]
        assert [b.timestamp_us for b in mkv.blocks(tracks[0])] == [15_000, 50_000]
        (ir,) = list(mkv.blocks(tracks[1]))[:1]
        np.testing.assert_array_equal(mkv.frame(ir, tracks[1]), 7)
    assert parse_uri(str(path))[0] == "mkv"
    with open_depth(f"{path}?intrinsics={SMALL}") as source:
        frames = list(source)
        assert source.stats.delivered == 2 and source.stats.dropped == 0
    assert [(f.index, f.timestamp_us) for f in frames] == [(0, 15_000), (1, 50_000)]
    for frame, truth in zip(frames, FRAMES, strict=True):
        assert frame.depth.dtype == np.uint16
        np.testing.assert_array_equal(frame.depth, truth)
        assert frame.intrinsics == Intrinsics.parse(SMALL, 3, 2)


def test_a_looped_recording_keeps_time_increasing_and_starts_again_after_close(tmp_path):
    path = tmp_path / "small.mkv"
    path.write_bytes(_recording(FRAMES))
    source = open_depth(f"mkv:{path}?intrinsics={SMALL}&loop=1")
    with source:
        frames = [source.read() for _ in range(5)]
    # one lap: the span (35 ms) and one period (35 ms)
    assert [f.timestamp_us for f in frames] == [15_000, 50_000, 85_000, 120_000, 155_000]
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(frames[2].depth, FRAMES[0])
    with source:
        assert source.read().timestamp_us == 15_000


def test_the_intrinsics_come_from_the_attached_calibration_for_the_mode_the_tags_name(tmp_path):
    """3 x 2 frames are no Azure Kinect mode: told to give ?intrinsics=; a recording whose
    frames are a mode's size takes the attachment the tags name, converted for that mode."""
    path = tmp_path / "small.mkv"
    path.write_bytes(_recording(FRAMES))
    with pytest.raises(DepthFileError, match=r"none of the Azure Kinect's.*\?intrinsics="):
        open_depth(str(path)).open()
    w, h = DEPTH_MODES["NFOV_2X2BINNED"]["size"]
    frames = [np.arange(w * h, dtype=np.uint16).reshape(h, w), np.zeros((h, w), np.uint16)]
    plain = tmp_path / "binned.mkv"
    plain.write_bytes(_recording(frames))
    with pytest.raises(DepthFileError, match=r"no calibration.json attached.*\?intrinsics="):
        open_depth(str(plain)).open()
    extra = _tags(K4A_DEPTH_MODE="NFOV_2X2BINNED", K4A_CALIBRATION_FILE="cal.json",
                  K4A_DEVICE_SERIAL_NUMBER="000123") + _attachment("cal.json", _calibration())
    full = tmp_path / "full.mkv"
    full.write_bytes(_recording(frames, extra=extra))
    with open_depth(str(full)) as source:
        frame = source.read()
        assert source.info == {"name": "Azure Kinect", "serial": "000123",
                               "depth_mode": "NFOV_2X2BINNED"}
    # 0.5 of the 512-px binned sensor, less the (96, 90) crop and half a pixel
    assert frame.intrinsics == Intrinsics(w, h, 256.0, 256.0, 256 - 96.5, 256 - 90.5)
    np.testing.assert_array_equal(frame.depth, frames[0])


def test_not_a_depth_recording_is_a_clear_error(tmp_path):
    path = tmp_path / "other.mkv"
    cases = [(_recording(FRAMES, doc_type=b"dvdish"), "not matroska"),
             (_recording(FRAMES, fourcc=b"MJPG"), "not the 16-bit big-endian grey"),
             (_recording(FRAMES).replace(b"DEPTH", b"DEPTX"), "no DEPTH track"),
             (b"not a recording at all", "no EBML header")]
    for data, what in cases:
        path.write_bytes(data)
        with pytest.raises(DepthFileError, match=f"{path}.*{what}"):
            open_depth(f"{path}?intrinsics={SMALL}").open()
    with pytest.raises(DepthFileError, match="missing.mkv: no such file"):
        open_depth(str(tmp_path / "missing.mkv"))
    with pytest.raises(UriError, match="unknown; the mkv backend takes intrinsics, rate, loop"):
        open_depth(f"{path}?topic=/depth")
    with pytest.raises(UriError, match="intrinsics='1,2'"):
        open_depth(f"{path}?intrinsics=1,2")
    with pytest.raises(UriError, match="unknown depth mode"):
        depth_calibration(_calibration(), "NFOV_3X3", "x")
    with pytest.raises(DepthFileError, match="not an Azure Kinect calibration"):
        depth_calibration(b"[1, 2]", "NFOV_UNBINNED", "x")
    with pytest.raises(DepthFileError, match="not a number"):
        depth_calibration(_calibration(fx=float("nan")), "NFOV_UNBINNED", "x")


def test_damaged_recordings_give_frames_or_a_depth_file_error(tmp_path):
    """300 drawn damages (bytes changed, cut, spliced) of a small recording: every frame read,
    or an HwError (DepthFileError for the file) -- never another exception."""
    rng = np.random.default_rng(7)
    good = _recording(FRAMES, extra=_tags(K4A_DEPTH_MODE="NFOV_UNBINNED"))
    path = tmp_path / "damaged.mkv"
    outcomes = {"frames": 0, "error": 0}
    for _ in range(300):
        data = bytearray(good)
        kind = rng.integers(3)
        if kind == 0:
            for pos in rng.integers(0, len(data), rng.integers(1, 6)):
                data[pos] = rng.integers(256)
        elif kind == 1:
            data = data[:rng.integers(0, len(data))]
        else:
            at = rng.integers(0, len(data))
            data = data[:at] + bytes(rng.integers(0, 256, rng.integers(1, 40)).astype(np.uint8)) \
                + data[at:]
        path.write_bytes(bytes(data))
        try:
            with open_depth(f"{path}?intrinsics={SMALL}") as source:
                while True:
                    try:
                        if source.read() is None:
                            break
                    except DepthFileError:
                        continue
            outcomes["frames"] += 1
        except HwError:
            outcomes["error"] += 1
    assert outcomes["frames"] > 0 and outcomes["error"] > 0, outcomes


def test_the_capture_s_depth_frame_decodes_to_the_readme_statistics(shared_data):
    """README: valid 76.5 %, p1 / p50 / p99 0.18 / 1.49 / 2.19 m, max 3.69 m, 1873 distinct
    values 1 mm apart (no disparity steps); the block at 463,945 us; tracks as listed."""
    path = shared_data / FOLDER / "recording.mkv"
    with MkvFile(path) as mkv:
        tracks = mkv.tracks()
        assert [(t.name, t.fourcc, t.width, t.height) for t in tracks] == [
            ("COLOR", "MJPG", 1280, 720), ("DEPTH", "b16g", 640, 576),
            ("IR", "b16g", 640, 576), ("IMU", "", 0, 0)]
        assert mkv.tags()["K4A_DEPTH_MODE"] == "NFOV_UNBINNED"
        (block,) = list(mkv.blocks(tracks[1]))
        depth = mkv.frame(block, tracks[1])
    with open_depth(str(path)) as source:
        frames = list(source)
        assert source.info["name"] == "Azure Kinect"
        assert source.info["serial"] == "001514394512"
    (frame,) = frames
    assert frame.timestamp_us == block.timestamp_us == 463_945
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


def test_the_nfov_intrinsics_follow_the_sdk_mode_conversion(shared_data):
    """Normalised to the 1024 x 1024 sensor: x 1024, minus the NFOV crop (192, 180), minus
    half a pixel (pixel centres at integers); the attachment is calibration.json's."""
    calibration = (shared_data / FOLDER / "calibration.json").read_bytes()
    K = depth_calibration(calibration, "NFOV_UNBINNED", "calibration.json").intrinsics
    assert (K.width, K.height) == (640, 576)
    assert K.fx == pytest.approx(0.4927808940410614 * 1024)  # ~504.6, as the README says
    assert K.fy == pytest.approx(0.49290284514427185 * 1024)
    assert K.cx == pytest.approx(0.5129697918891907 * 1024 - 192.5)  # 332.78
    assert K.cy == pytest.approx(0.5169235467910767 * 1024 - 180.5)  # 348.83
    wide = depth_calibration(calibration, "WFOV_UNBINNED", "calibration.json").intrinsics
    assert (wide.width, wide.cx) == (1024, pytest.approx(K.cx + 192))
    with open_depth(str(shared_data / FOLDER / "recording.mkv")) as source:
        assert source.intrinsics == K


def test_without_distortion_the_undistortion_moves_no_pixel():
    camera = Intrinsics(64, 48, 50.0, 51.0, 31.5, 23.5)
    table = undistortion_table(DepthCalibration(camera, (0.0,) * 8, 1.74))
    np.testing.assert_array_equal(table, np.arange(64 * 48))
    depth = np.arange(64 * 48, dtype=np.uint16).reshape(48, 64)
    np.testing.assert_array_equal(undistort(depth, table), depth)
    # a metric radius inside the image: no reading beyond it
    small = undistortion_table(DepthCalibration(camera, (0.0,) * 8, 0.2))
    assert (small == 64 * 48).any() and small[24 * 64 + 32] == 24 * 64 + 32


def _plane_residuals_mm(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """|distance| (mm) to the largest plane of a depth image (RANSAC, 2 cm band, then a
    least-squares refit) of the points within 5 cm of it."""
    v, u = np.nonzero(depth)
    z = depth[v, u] / 1000.0
    points = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], 1)
    rng = np.random.default_rng(0)
    best = None
    for _ in range(300):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        if np.linalg.norm(normal) < 1e-9:
            continue
        normal /= np.linalg.norm(normal)
        inliers = np.abs((points - a) @ normal) < 0.02
        if best is None or inliers.sum() > best.sum():
            best = inliers
    centre = points[best].mean(axis=0)
    normal = np.linalg.svd(points[best] - centre, full_matrices=False)[2][2]
    distance = np.abs((points - centre) @ normal)
    return 1000.0 * distance[distance < 0.05]


def test_the_capture_undistorted_by_its_lens_model_has_flatter_planes(shared_data):
    """The NFOV lens moves readings up to ~80 px from where a pinhole puts them: read as
    pinhole, the capture's largest plane bends (p90 11.4 mm off it); undistorted, 5.0 mm, and
    a quarter more of its points lie on it.  A wrong model (sign, order) would not flatten
    it."""
    path = shared_data / FOLDER / "recording.mkv"
    with MkvFile(path) as mkv:
        track = mkv.tracks()[1]
        raw = mkv.frame(next(mkv.blocks(track)), track)
    with open_depth(str(path)) as source:
        frame = source.read()
    before = _plane_residuals_mm(raw, frame.intrinsics)
    after = _plane_residuals_mm(frame.depth, frame.intrinsics)
    assert np.percentile(after, 90) < 0.6 * np.percentile(before, 90), (
        np.percentile(before, 90), np.percentile(after, 90))
    assert len(after) > 1.15 * len(before)


@pytest.mark.parametrize("keep", [3, 200, 8000, 500_000, 1_699_250])
def test_a_truncated_capture_is_a_clear_error(shared_data, tmp_path, keep):
    path = tmp_path / "cut.mkv"
    path.write_bytes((shared_data / FOLDER / "recording.mkv").read_bytes()[:keep])
    with pytest.raises(DepthFileError, match=f"{path}: not a readable Azure Kinect recording"):
        with open_depth(str(path)) as source:
            list(source)


def test_the_auto_profile_of_a_recording_is_the_azure_kinect_s(shared_data):
    from robot_change.noise.profile import resolve_profile

    with open_depth(str(shared_data / FOLDER / "recording.mkv")) as source:
        name = source.info["name"]
    assert resolve_profile("auto", camera=name).name == "azure_kinect"


def test_an_azure_kinect_recording_copied_to_an_oni_stays_an_azure_kinect_s(tmp_path,
                                                                           shared_data):
    """record --out X.oni kept neither its principal point (cy 348.8 came back 287.5: the
    cloud's plane 5 cm off) nor its camera (read as a Kinect v1): now both."""
    from hw.record import record
    from robot_change.noise.profile import resolve_profile

    out = tmp_path / "azure.oni"
    with open_depth(str(shared_data / FOLDER / "recording.mkv")) as source:
        record(source, out)
        intrinsics = source.intrinsics
    with open_depth(str(out)) as copy:
        frame = copy.read()
        name = copy.info["name"]
    assert frame.intrinsics == intrinsics and resolve_profile("auto", camera=name).name == \
        "azure_kinect"


def test_the_daemon_reads_an_azure_kinect_recording_as_its_camera(tmp_path, shared_data):
    """A real ``robot-change run`` subprocess with the capture looped as its camera: CAPTURED
    names the Azure Kinect's noise profile (``auto``), and the unchanged room is CLEAR."""
    from daemon_rig import Daemon

    source = f"mkv:{shared_data / FOLDER / 'recording.mkv'}?loop=1&rate=15"
    with Daemon(tmp_path, source=source) as d:
        d.wait_for("READY=1")
        script = ("capture desk\nexpect CAPTURED station=desk 20\n"
                  "check desk\nexpect CLEAR station=desk 20\n")
        assert d.base(script, connect_timeout=20) == 0, d.transcript.getvalue()[-3000:]
        got = [e for sim in d.sims for e in sim.log]
        captured = next(e.obj for e in got if e.name == "CAPTURED")
        assert captured.noise.startswith("azure_kinect") and captured.smallest_change_mm > 0
