"""hw.openni2 through the real libOpenNI2: .oni playback, the DummyDevice live path, and the
reader child process failing in every way we can make it fail (killed, stopped, device lost).

Every wait is bounded by the backend's own timeouts; no test needs a pytest timeout plugin.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from hw.depth import Intrinsics, open_depth
from hw.errors import (
    DepthFileError,
    DeviceError,
    DeviceLost,
    DeviceNotFound,
    FrameTimeout,
)
from hw.oni import read_oni_header, write_oni
from hw.openni2 import OpenNI2Source, list_devices, open_device, open_recording
from hw.record import record

DUMMY = "openni2://Oz"  # OpenNI's DummyDevice driver: a synthetic live 320x240 stream


def images(count: int, height: int = 120, width: int = 160) -> list[np.ndarray]:
    yy, xx = np.mgrid[0:height, 0:width]
    return [(1000 + 3 * xx + 2 * yy + 11 * i).astype(np.uint16) for i in range(count)]


@pytest.fixture()
def recording(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    frames = images(12)
    path = tmp_path / "twelve.oni"
    write_oni(path, frames, codec="16z")
    return path, frames


def read_all(source: OpenNI2Source, timeout: float = 5.0) -> list:
    out = []
    while (frame := source.read(timeout)) is not None:
        out.append(frame)
    return out


def read_live(source: OpenNI2Source, count: int, budget: float = 8.0) -> list:
    """``count`` frames from a live source, riding out DeviceLost / FrameTimeout while it
    reconnects, within ``budget`` seconds."""
    frames, errors = [], []
    end = time.monotonic() + budget
    while len(frames) < count:
        assert time.monotonic() < end, f"no recovery within {budget} s: {errors[-3:]}"
        try:
            frames.append(source.read(1.0))
        except (DeviceLost, FrameTimeout) as exc:
            errors.append(exc)
    return frames


# --- recordings ------------------------------------------------------------------------------
def test_playback_delivers_every_frame_then_ends(recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    with open_depth(f"oni:{path}") as source:
        assert source.intrinsics == Intrinsics.openni_default(160, 120)
        start = time.monotonic()
        frames = read_all(source)
        assert source.read(0.1) is None and source.read(0.1) is None  # ended, no hang
        assert time.monotonic() - start < 5.0
        assert source.stats.delivered == 12 and source.stats.dropped == 0
    assert [f.index for f in frames] == list(range(1, 13))
    assert [f.timestamp_us for f in frames] == [round(i * 1e6 / 30) for i in range(12)]
    for frame, original in zip(frames, originals, strict=True):
        np.testing.assert_array_equal(frame.depth, original)


def test_a_bare_oni_path_and_iteration_work(recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    with open_depth(str(path)) as source:
        assert len(list(source)) == 12


def test_slow_consumer_loses_no_frame(recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    with open_recording(str(path), slots=1) as source:
        indices = []
        while (frame := source.read(5.0)) is not None:
            indices.append(frame.index)
            time.sleep(0.02)
    assert indices == list(range(1, 13))


@pytest.mark.parametrize("content", ["missing", "garbage", "truncated", "empty"])
def test_bad_recordings_raise_depth_file_error(tmp_path: Path,
                                               recording: tuple[Path, list[np.ndarray]],
                                               content: str) -> None:
    path = tmp_path / f"{content}.oni"
    if content == "garbage":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, 100_000, dtype=np.uint8)
                         .tobytes())
    elif content == "truncated":
        data = recording[0].read_bytes()
        path.write_bytes(data[: len(data) * 2 // 3])
    elif content == "empty":
        path.write_bytes(b"")
    with pytest.raises(DepthFileError, match=str(path.name)):
        open_depth(f"oni:{path}")


def test_recording_damaged_after_opening_is_caught_on_open(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    source = open_recording(str(path))
    path.write_bytes(path.read_bytes()[:500])
    with pytest.raises(DepthFileError, match="truncated"):
        source.open()
    source.close()


def test_reader_killed_mid_recording_is_restarted_without_losing_frames(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    with open_recording(str(path), slots=2) as source:
        frames = [source.read(5.0) for _ in range(4)]
        first_pid = source.pid
        os.kill(first_pid, signal.SIGKILL)
        frames += read_all(source)
        assert source.pid != first_pid
        assert source.stats.restarts == 1
    assert [f.index for f in frames] == list(range(1, 13))  # none lost, none twice
    for frame, original in zip(frames, originals, strict=True):
        np.testing.assert_array_equal(frame.depth, original)


def test_a_reader_that_keeps_crashing_means_a_corrupt_recording(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    with open_recording(str(path), max_restarts=0) as source:
        source.read(5.0)
        os.kill(source.pid, signal.SIGKILL)
        with pytest.raises(DepthFileError, match="crashed"):
            read_all(source)


def test_hung_reader_gives_frame_timeout_then_is_replaced(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    with open_recording(str(path), slots=1, stall_timeout=1.0) as source:
        first = source.read(5.0)
        os.kill(source.pid, signal.SIGSTOP)
        time.sleep(0.2)  # let the frame already in flight arrive
        with pytest.raises(FrameTimeout):
            while True:  # drains at most the frames sent before the stop
                start = time.monotonic()
                source.read(0.3)
        assert time.monotonic() - start < 1.0  # the read gave up on time, it did not hang
        rest = []
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                frame = source.read(0.5)
            except FrameTimeout:
                continue
            if frame is None:
                break
            rest.append(frame)
        assert source.stats.restarts == 1
    indices = [first.index] + [f.index for f in rest]
    assert indices[-1] == 12 and indices == sorted(set(indices))
    np.testing.assert_array_equal(rest[-1].depth, originals[-1])


def test_unbounded_read_replaces_a_hung_reader_in_place(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    with open_recording(str(path), slots=1, stall_timeout=0.8) as source:
        first = source.read(5.0)
        os.kill(source.pid, signal.SIGSTOP)
        start = time.monotonic()
        rest = list(source)  # read(timeout=None): waits, kills the hung reader, carries on
        assert time.monotonic() - start < 8.0
        assert source.stats.restarts == 1
    assert [first.index] + [f.index for f in rest] == list(range(1, 13))
    for frame, original in zip([first] + rest, originals, strict=True):
        np.testing.assert_array_equal(frame.depth, original)


def test_read_needs_an_open_source(recording: tuple[Path, list[np.ndarray]]) -> None:
    source = open_recording(str(recording[0]))
    with pytest.raises(DeviceError, match="not open"):
        source.read(0.1)
    source.close()  # closing an unopened source is harmless
    with pytest.raises(ValueError, match="unknown OpenNI2 option"):
        open_depth(f"oni:{recording[0]}?speed=2")


# --- live cameras ------------------------------------------------------------------------------
def test_no_camera_gives_a_clear_device_not_found() -> None:
    if list_devices():
        pytest.skip("a real OpenNI2 camera is connected")
    with pytest.raises(DeviceNotFound) as info:
        with open_depth("openni2://"):
            pass
    text = str(info.value)
    assert "no OpenNI2 depth camera" in text and "Kinect" in text and "libfreenect" in text
    with pytest.raises(DeviceNotFound, match="'A00366A12345'"):
        with open_device("A00366A12345"):
            pass


def test_dummy_device_streams_frames_with_increasing_indices_and_timestamps() -> None:
    with open_depth(DUMMY) as source:
        frames = [source.read(2.0) for _ in range(6)]
        assert source.info["uri"] == "Oz"
        assert "320x240" in source.info["mode_note"]  # not 640x480: the nearest mode, and says so
        assert source.stats.delivered == 6
    assert all(f.shape == (240, 320) and f.depth.dtype == np.uint16 for f in frames)
    assert frames[0].intrinsics == Intrinsics.openni_default(320, 240)
    indices = [f.index for f in frames]
    stamps = [f.timestamp_us for f in frames]
    assert indices == sorted(indices) and len(set(indices)) == 6
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    # DummyDevice runs at 30 fps: 33 ms per frame index
    assert (stamps[-1] - stamps[0]) == pytest.approx(33_000 * (indices[-1] - indices[0]), rel=0.05)


def test_dropped_frames_are_counted_from_index_gaps() -> None:
    with open_device("Oz", slots=1) as source:
        first = source.read(2.0)
        time.sleep(0.4)  # ~12 frames pass while nobody reads; the single slot holds one
        frames = [source.read(2.0) for _ in range(3)]
        gaps = sum(b.index - a.index - 1 for a, b in zip([first] + frames, frames, strict=False))
        assert gaps > 0 and source.stats.dropped == gaps


def test_lost_camera_raises_device_lost_then_reconnects() -> None:
    with open_device("Oz", lost_after=0.5) as source:
        read_live(source, 2)
        source.simulate_device_loss()
        start = time.monotonic()
        with pytest.raises(DeviceLost, match="no frame for 0.5 s"):
            while True:
                source.read(1.0)  # the frames still in the ring come first
        assert time.monotonic() - start < 3.0
        frames = read_live(source, 3)
        assert source.stats.restarts == 1
        assert [f.index for f in frames] == sorted(f.index for f in frames)


def test_reader_killed_mid_stream_is_detected_and_restarted() -> None:
    with open_device("Oz") as source:
        read_live(source, 2)
        first_pid = source.pid
        os.kill(first_pid, signal.SIGKILL)
        with pytest.raises(DeviceLost, match="SIGKILL"):
            for _ in range(10):  # at most the frames already in the ring
                source.read(2.0)
        frames = read_live(source, 3)
        assert source.pid not in (None, first_pid)
        assert source.stats.restarts == 1 and len(frames) == 3


def test_hung_live_reader_times_out_then_reconnects() -> None:
    with open_device("Oz", slots=1, stall_timeout=0.8) as source:
        read_live(source, 1)
        os.kill(source.pid, signal.SIGSTOP)
        time.sleep(0.1)
        errors = []
        end = time.monotonic() + 5.0
        while time.monotonic() < end and not any(isinstance(e, DeviceLost) for e in errors):
            try:
                source.read(0.3)
            except (FrameTimeout, DeviceLost) as exc:
                errors.append(exc)
        assert isinstance(errors[0], FrameTimeout) and isinstance(errors[-1], DeviceLost)
        assert "stopped answering" in str(errors[-1])
        read_live(source, 2)
        assert source.stats.restarts == 1


def test_list_devices_returns_dicts() -> None:
    devices = list_devices()
    assert isinstance(devices, list)
    for device in devices:
        assert {"uri", "vendor", "name"} <= set(device)


# --- recording ---------------------------------------------------------------------------------
def test_record_copies_a_recording_exactly(tmp_path: Path,
                                           recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    out = tmp_path / "copy.oni"
    with open_recording(str(path)) as source:
        assert record(source, out) == 12
    with open_recording(str(out)) as copy:
        frames = read_all(copy)
    assert [f.timestamp_us for f in frames] == [round(i * 1e6 / 30) for i in range(12)]
    for frame, original in zip(frames, originals, strict=True):
        np.testing.assert_array_equal(frame.depth, original)


def test_an_oni_keeps_the_intrinsics_and_the_camera_s_name(tmp_path: Path) -> None:
    """OpenNI's own properties keep only the field of view (a principal point off the centre
    came back centred: an Azure Kinect's cy 348.8 as 287.5); robot_change's beside them keep
    all four and the camera's name, read back through libOpenNI2's player, which passes over
    them; record() refuses to write over an existing file."""
    off_centre = Intrinsics(640, 576, 504.608, 504.7, 332.8, 348.8)
    path = tmp_path / "azure.oni"
    frames = [np.full((576, 640), 1500 + k, np.uint16) for k in range(3)]
    write_oni(path, frames, intrinsics=off_centre, camera="Azure Kinect")
    assert read_oni_header(path).intrinsics() == off_centre
    with open_depth(str(path)) as source:
        got = read_all(source)
        assert source.info["name"] == "Azure Kinect"
    assert [f.intrinsics for f in got] == [off_centre] * 3
    assert [f.depth.tolist() for f in got] == [d.tolist() for d in frames]
    copy = tmp_path / "copy.oni"
    with open_depth(str(path)) as source:
        assert record(source, copy) == 3
    assert read_oni_header(copy).intrinsics() == off_centre
    assert read_oni_header(copy).camera == "Azure Kinect"
    with open_depth(str(path)) as source, pytest.raises(DepthFileError, match="exists"):
        record(source, copy)
    assert read_oni_header(copy).frames == 3


def test_record_a_live_camera_for_n_frames(tmp_path: Path) -> None:
    out = tmp_path / "live.oni"
    with open_depth(DUMMY) as source:
        assert record(source, out, frames=5) == 5
    info = read_oni_header(out)
    assert (info.width, info.height, info.frames, info.first_timestamp_us) == (320, 240, 5, 0)
    assert info.codec == "16zT"  # record() defaults to 16zt


# --- loop and rate: a recording played like a camera (the daemon's demo and tests) -----------
def test_looped_recording_keeps_counting_indices_and_time(
        recording: tuple[Path, list[np.ndarray]]) -> None:
    path, originals = recording
    with open_depth(f"oni:{path}?loop=1") as source:
        frames = [source.read(5.0) for _ in range(30)]  # two and a half laps, never None
    assert [f.index for f in frames] == list(range(1, 31))
    stamps = [f.timestamp_us for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    assert stamps[12] == round(12 * 1e6 / 30)  # the second lap follows one frame period on
    for i, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.depth, originals[i % 12])


def test_rate_paces_delivery_like_a_camera(recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    with open_recording(str(path), rate="auto", loop=True) as source:
        source.read(5.0)  # the first frame comes at once
        start = time.monotonic()
        for _ in range(15):
            source.read(1.0)
        elapsed = time.monotonic() - start
    assert 0.4 < elapsed < 2.0  # 15 frames at 30 fps = 0.5 s, not as fast as possible


def test_rate_shorter_timeout_gives_frame_timeout(recording: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = recording
    with open_depth(f"oni:{path}?rate=2") as source:
        first = source.read(5.0)
        with pytest.raises(FrameTimeout, match="paced at 2 fps"):
            source.read(0.05)
        assert source.read(1.0).index == first.index + 1  # the frame stayed next


@pytest.mark.parametrize("option, match", [("loop=maybe", "loop"), ("rate=-3", "rate"),
                                           ("rate=fast", "rate")])
def test_bad_loop_and_rate_options_are_uri_errors(recording: tuple[Path, list[np.ndarray]],
                                                  option: str, match: str) -> None:
    from hw.errors import UriError

    path, _ = recording
    with pytest.raises(UriError, match=match):
        open_depth(f"oni:{path}?{option}")


def test_loop_and_rate_are_refused_for_a_live_camera() -> None:
    from hw.errors import UriError

    with pytest.raises(UriError, match="for recordings"):
        open_device("Oz", loop="1")


# --------------------------------------------------------------------------------------------
# the reader starts the same way whatever the caller is

_CALLER = """\
from hw.depth import open_depth
with open_depth({uri!r}) as source:
    print(sum(1 for _ in source))
"""


@pytest.mark.parametrize("how", ["stdin", "-c", "-m", "script"])
def test_the_reader_starts_whatever_the_callers_main_module_is(
        tmp_path: Path, recording: tuple[Path, list[np.ndarray]], how: str) -> None:
    """multiprocessing's spawn re-imported the caller's __main__ and died on standard input
    ("the file is probably corrupt"); the reader is now its own interpreter."""
    import subprocess
    import sys

    path, frames = recording
    code = _CALLER.format(uri=f"oni:{path}")
    (tmp_path / "caller_mod.py").write_text(code)
    args = {"stdin": ["-"], "-c": ["-c", code], "-m": ["-m", "caller_mod"],
            "script": [str(tmp_path / "caller_mod.py")]}[how]
    done = subprocess.run([sys.executable, *args], input=code if how == "stdin" else None,
                          capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == [str(len(frames))]
    assert "leaked" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_a_reader_that_dies_at_start_says_how_and_what_it_wrote_last(
        recording: tuple[Path, list[np.ndarray]], monkeypatch) -> None:
    """Not "the file is probably corrupt": its header was checked; the exit status and the
    reader's last stderr line say what happened."""
    import hw.supervised

    monkeypatch.setattr(hw.supervised, "_BOOT", "import sys\nsys.stderr.write('driver: cannot map "
                        "the device buffer\\n')\nsys.exit(3)\n")
    source = open_recording(str(recording[0]))
    with pytest.raises(DepthFileError) as info:
        source.open()
    text = str(info.value)
    assert "exited with status 3" in text and "cannot map the device buffer" in text
    assert "corrupt" not in text and "header was checked" in text
    source.close()
