"""The RealSense backend (hw.realsense) and RealSense recordings (hw.realsense_record), against
the real librealsense: every recording here is written by librealsense's own recorder (a
software device, no camera) and played by librealsense's own player in the reader process, and
read again by the bag backend; no hardware is needed, so a live camera is only seen missing.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, SIM_FIXTURES

from hw.depth import DepthFrame, Intrinsics, open_depth
from hw.errors import DepthFileError, DeviceNotFound, FrameError, UriError
from hw.oni import read_oni_frames

pytest.importorskip("pyrealsense2", reason="librealsense's Python binding (the realsense extra, "
                    "in the test extra on x86_64): pip install pyrealsense2")
from hw.realsense import list_devices, open_realsense  # noqa: E402
from hw.realsense_record import write_realsense_recording  # noqa: E402

SCENE = SIM_FIXTURES / "scenes" / "office_box_added"
CAMERA = Intrinsics(640, 480, 612.4, 611.9, 321.3, 238.6)  # a D435's depth at 640x480


def frames_of(depths: list[np.ndarray], camera: Intrinsics = CAMERA) -> list[DepthFrame]:
    return [DepthFrame(depth, 1_000_000 + k * 33_333, k, camera) for k, depth in enumerate(depths)]


@pytest.fixture(scope="module")
def twelve() -> list[np.ndarray]:
    """Twelve different 640x480 depth frames (the fixture's six, then shifted copies)."""
    base = [f.depth for f in read_oni_frames(SCENE / "reference.oni")] + \
        [f.depth for f in read_oni_frames(SCENE / "current.oni")]
    return base + [np.roll(depth, 7, axis=1) for depth in base]


@pytest.fixture(scope="module")
def recording(tmp_path_factory, twelve) -> Path:
    path = tmp_path_factory.mktemp("rs") / "run.db3"
    assert write_realsense_recording(path, frames_of(twelve)) == len(twelve)
    return path


def test_a_recording_plays_in_librealsense_exactly_and_the_bag_backend_reads_the_same(
        recording, twelve):
    with open_depth(f"realsense:{recording}") as source:
        played = list(source)
        assert source.intrinsics == CAMERA
        assert source.info["serial"] == "000000000001"
        assert source.info["depth_units_m"] == pytest.approx(0.001)
    with open_depth(str(recording)) as source:  # a bare .db3: rosbag, no librealsense involved
        read = list(source)
        assert source.intrinsics.fx == pytest.approx(CAMERA.fx, abs=1e-4)
    assert len(played) == len(read) == len(twelve)
    for a, b, depth in zip(played, read, twelve, strict=True):
        assert np.array_equal(a.depth, depth) and np.array_equal(b.depth, depth)
    assert [f.index for f in played] == list(range(len(twelve)))
    assert [f.timestamp_us for f in played] == [1_000_000 + k * 33_333 for k in range(12)]


def test_a_ros1_recording_of_older_librealsense_plays_as_the_bag_backend_reads_it():
    """A .bag that librealsense 2.56 wrote (sim_fixtures/realsense) plays in librealsense 2.59
    and reads through the bag backend: the same frames, the same camera."""
    folder = SIM_FIXTURES / "realsense"
    expected = np.load(folder / "d435_ros1.npy")
    for uri in (f"realsense:{folder / 'd435_ros1.bag'}", f"rosbag:{folder / 'd435_ros1.bag'}"):
        with open_depth(uri) as source:
            frames = list(source)
            assert source.intrinsics == Intrinsics(64, 48, 57.6, 57.6, 31.5, 23.5), uri
            assert source.info["name"] == "Intel RealSense D435", uri  # the auto profile's key
            assert source.info["serial"] == "000000000002", uri
        assert [f.index for f in frames] == list(range(len(expected))), uri
        assert all(np.array_equal(f.depth, d) for f, d in zip(frames, expected, strict=True)), uri


def test_both_backends_name_the_camera_a_recording_names(tmp_path, twelve):
    """The bag backend reads the device a 2.59+ recording names, as librealsense's playback
    reports it, so that ``auto`` picks that camera's noise profile through either."""
    from robot_change.noise.profile import resolve_profile

    path = tmp_path / "d455.db3"
    write_realsense_recording(path, frames_of(twelve[:2]), name="Intel RealSense D455",
                              serial="123")
    for uri in (f"realsense:{path}", str(path)):
        with open_depth(uri) as source:
            assert (source.info["name"], source.info["serial"]) == (
                "Intel RealSense D455", "123"), uri
            assert resolve_profile("auto", camera=source.info["name"]).name == "realsense_d455"


def test_record_keeps_the_camera_a_recording_names(tmp_path):
    """``record --format realsense`` of a D435's recording (librealsense 2.56's ROS 1 bag)
    names that camera and its serial, as librealsense's playback reports them."""
    from hw.record import record

    out = tmp_path / "copy.db3"
    with open_depth(f"rosbag:{SIM_FIXTURES / 'realsense' / 'd435_ros1.bag'}") as source:
        record(source, out, format="realsense")
    with open_depth(f"realsense:{out}") as copy:
        assert (copy.info["name"], copy.info["serial"]) == ("Intel RealSense D435",
                                                            "000000000002")


@pytest.mark.parametrize("damage", [b"", b"\x00\x01\x00\x00\xff\xff\xff\x7f",
                                    b"\x00\x01\x00\x00\x05\x00\x00\x00Na"])
def test_the_bag_backend_reads_a_recording_whose_device_info_is_damaged(tmp_path, twelve,
                                                                        damage):
    """A damaged ``/device_0/info`` message (empty, a length past its end, cut short) names
    no camera (``auto`` then takes the default profile) and the frames still read."""
    import sqlite3

    path = tmp_path / "d455.db3"
    write_realsense_recording(path, frames_of(twelve[:2]), name="Intel RealSense D455",
                              serial="123")
    with contextlib.closing(sqlite3.connect(path)) as db, db:
        (topic,), = db.execute("SELECT id FROM topics WHERE name = '/device_0/info'")
        assert db.execute("UPDATE messages SET data = ? WHERE topic_id = ?",
                          (damage, topic)).rowcount >= 1
    with open_depth(str(path)) as source:
        assert source.info == {}
        frames = list(source)
    assert [f.depth.tolist() for f in frames] == [d.tolist() for d in twelve[:2]]


def test_a_raw_recording_plays_and_reads_the_same(tmp_path, twelve):
    """``compress=False`` (``record --codec none``): librealsense records raw Images, which both
    backends read as they read its PNGs."""
    path = tmp_path / "raw.db3"
    write_realsense_recording(path, frames_of(twelve[:4]), compress=False)
    for uri in (f"realsense:{path}", f"rosbag:{path}"):
        with open_depth(uri) as source:
            frames = list(source)
            assert source.intrinsics == CAMERA, uri
            if uri.startswith("rosbag"):
                assert source.topic == "/device_0/sensor_0/Depth_0/image/data"
        assert all(np.array_equal(f.depth, d) for f, d in zip(frames, twelve[:4], strict=True)), uri
        assert len(frames) == 4, uri


def test_depth_units_are_converted_to_millimetres(tmp_path, twelve):
    tenths = [np.minimum(d.astype(np.uint32) * 10, 65535).astype(np.uint16) for d in twelve[:2]]
    tenths[1] = np.minimum(tenths[1].astype(np.uint32) + 5, 65535).astype(np.uint16)  # x.5 mm
    path = tmp_path / "d405.db3"
    write_realsense_recording(path, frames_of(tenths), depth_units=0.0001)
    read = {}
    for uri in (f"realsense:{path}", f"rosbag:{path}"):
        with open_depth(uri) as source:
            read[uri] = [source.read().depth, source.read().depth]
        near = twelve[0] <= 6553
        assert np.array_equal(read[uri][0][near], twelve[0][near]), uri
    # half millimetres round as librealsense's float32 units round them (9.9999997e-05 m)
    assert all(np.array_equal(a, b) for a, b in zip(*read.values(), strict=True))


def test_both_backends_give_a_frames_own_number_and_time_and_count_the_gaps(tmp_path, twelve):
    numbers = [100, 101, 103, 104, 105, 109]
    path = tmp_path / "gaps.db3"
    write_realsense_recording(path, [DepthFrame(depth, 1_000_000 + (n - 100) * 33_333, n, CAMERA)
                                     for depth, n in zip(twelve[:6], numbers, strict=True)])
    seen = {}
    for uri in (f"realsense:{path}", str(path)):  # librealsense, and the bag backend
        with open_depth(uri) as source:
            seen[uri] = [(f.index, f.timestamp_us) for f in source]
            assert source.stats.dropped == 4, uri  # 102, 106, 107, 108
    assert seen[str(path)] == seen[f"realsense:{path}"]
    assert seen[str(path)] == [(n, 1_000_000 + (n - 100) * 33_333) for n in numbers]


def test_a_slow_consumer_loses_no_frame(recording, twelve):
    with open_depth(f"realsense:{recording}?slots=1") as source:
        got = []
        while (frame := source.read(5.0)) is not None:
            got.append(frame)
            time.sleep(0.05)
    assert [f.index for f in got] == list(range(len(twelve)))


def test_looped_and_paced_it_runs_like_a_camera(recording, twelve):
    with open_depth(f"realsense:{recording}?loop=1&rate=auto") as source:
        assert source.rate == 30.0  # the recording's own fps
        start = time.monotonic()
        got = [source.read(5.0) for _ in range(30)]
        took = time.monotonic() - start
    indices = [f.index for f in got]
    stamps = [f.timestamp_us for f in got]
    assert indices == list(range(30)) or np.all(np.diff(indices) > 0)
    assert np.all(np.diff(stamps) > 0) and np.ptp(np.diff(stamps)) <= 2  # one clock
    assert np.array_equal(got[len(twelve)].depth, twelve[0])
    assert 0.8 < took < 2.0  # 30 frames at 30 fps


def test_a_reader_killed_mid_recording_is_replaced_without_losing_a_frame(recording, twelve):
    with open_depth(f"realsense:{recording}") as source:
        got = [source.read(5.0) for _ in range(4)]
        first = source.pid
        os.kill(first, signal.SIGKILL)
        got += list(source)
        assert source.pid != first and source.stats.restarts == 1
    assert [f.index for f in got] == list(range(len(twelve)))
    assert all(np.array_equal(f.depth, d) for f, d in zip(got, twelve, strict=True))


def test_a_hung_reader_is_killed_and_replaced_in_place(recording, twelve):
    with open_depth(f"realsense:{recording}?slots=1&stall_timeout=0.8") as source:
        got = [source.read(5.0)]
        os.kill(source.pid, signal.SIGSTOP)
        start = time.monotonic()
        got += list(source)  # read(timeout=None): waits, kills the hung reader, carries on
        assert time.monotonic() - start < 8.0 and source.stats.restarts == 1
    assert [f.index for f in got] == list(range(len(twelve)))
    assert all(np.array_equal(f.depth, d) for f, d in zip(got, twelve, strict=True))


def test_bad_recordings_are_depth_file_errors_before_librealsense_sees_them(tmp_path, recording):
    cut = tmp_path / "cut.db3"
    cut.write_bytes(recording.read_bytes()[:4096])
    text = tmp_path / "notes.db3"
    text.write_text("not a bag")
    from test_rosbag import write_bag  # a ROS 2 bag, but not a RealSense recording
    plain = write_bag(tmp_path / "plain", "db3", [np.zeros((480, 640), np.uint16)])
    storage = next(plain.glob("*.db3"))
    cases = {cut: "not a readable ROS bag|RealSense", text: "not a readable ROS bag",
             storage: "not a RealSense recording with depth", tmp_path / "none.db3": "no such file",
             tmp_path / "x.mcap": "no such file|not a RealSense recording by its name"}
    for path, message in cases.items():
        with pytest.raises(DepthFileError, match=message):
            open_realsense(str(path)).open()


def test_a_recording_cut_short_ends_with_the_frames_it_has(tmp_path, twelve):
    """A recording stopped early (Ctrl-C in rs-record) is a shorter recording, not an error."""
    path = tmp_path / "short.db3"
    write_realsense_recording(path, frames_of(twelve[:3]))
    with open_depth(f"realsense:{path}") as source:
        assert len(list(source)) == 3
        assert source.read() is None


def test_no_camera_is_a_clear_device_not_found_and_options_are_checked(tmp_path,
                                                                       monkeypatch):
    if list_devices():
        pytest.skip("a RealSense camera is connected")
    with pytest.raises(DeviceNotFound, match="no RealSense camera is connected.*udev"):
        open_depth("realsense://").open()
    with pytest.raises(DeviceNotFound, match="serial number '123622270300' .none is connected; "
                                             r"a recording is named by its file, e\.g\. "
                                             r"realsense:123622270300\.db3"):
        open_depth("realsense://123622270300?resolution=848x480&fps=30&preset=high_accuracy").open()
    # a folder or file that is there is a recording's name, never a serial number
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run_bag").mkdir()
    with pytest.raises(DepthFileError, match="run_bag"):
        open_depth("realsense:run_bag").open()
    for uri, message in (("realsense://?resolution=big", "WIDTHxHEIGHT"),
                         ("realsense://?resolution=999x1", "each at least 16 pixels"),
                         ("realsense://?preset=ultra", "one of custom, default"),
                         ("realsense://?fps=0", "fps"), ("realsense://?lopp=1", "unknown"),
                         ("realsense://?loop=1", "for recordings"),
                         ("realsense:run.db3?resolution=848x480", "for a live camera")):
        with pytest.raises(UriError, match=message):
            open_depth(uri)


def test_the_writer_refuses_what_it_must_not_write_and_leaves_nothing(tmp_path, twelve):
    odd = frames_of(twelve[:2]) + frames_of([twelve[2][:240]],
                                            Intrinsics(640, 240, 600, 600, 320, 120))
    with pytest.raises(FrameError, match="another size"):
        write_realsense_recording(tmp_path / "odd.db3", odd)
    with pytest.raises(FrameError, match="no frames"):
        write_realsense_recording(tmp_path / "none.db3", [])
    with pytest.raises(DepthFileError, match=r"\.db3"):
        write_realsense_recording(tmp_path / "run.bag", frames_of(twelve[:1]))
    assert list(tmp_path.iterdir()) == []


def run(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robot_change.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def test_cli_record_to_db3_then_detect_gives_what_the_same_depth_as_png_gives(tmp_path):
    """``record --out X.db3`` writes through librealsense (PNG, or raw with ``--codec none``);
    ``detect`` on the two recordings answers as on the same frames as PNG files."""
    from sim_fixtures import load_scene

    scene = load_scene("office_box_added")
    for epoch, codec in (("reference", "png"), ("current", "none")):  # PNG and raw
        done = run("record", "--source", str(SCENE / f"{epoch}.oni"), "--out",
                   str(tmp_path / f"{epoch}.db3"), "--codec", codec)
        assert done.returncode == 0 and "RealSense recording" in done.stdout, done.stderr
    done = run("record", "--source", str(SCENE / "current.oni"), "--out",
               str(tmp_path / "x.db3"), "--codec", "16zt")
    assert done.returncode == 2 and "choose png or none" in done.stderr
    results = {}
    for kind, ref, cur in (
            ("realsense", f"realsense:{tmp_path / 'reference.db3'}",
             f"realsense:{tmp_path / 'current.db3'}"),
            ("bag", f"rosbag:{tmp_path / 'reference.db3'}", f"rosbag:{tmp_path / 'current.db3'}"),
            ("png", scene.uri("reference", "images"), scene.uri("current", "images"))):
        done = run("detect", "--reference", ref, "--current", cur, "--json")
        assert done.returncode in (0, 1), done.stderr
        summary = json.loads(done.stdout)
        results[kind] = {key: summary[key] for key in ("outcome", "regions", "n_appeared_points",
                                                       "n_disappeared_points")}
    assert results["realsense"] == results["png"] == results["bag"]
    assert results["png"]["outcome"] == "changed" and len(results["png"]["regions"]) == 1


def reader_pids(parent: int) -> list[int]:
    """The reader processes (hw.supervised) started by process ``parent``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and b"reader_entry" in command:
            found.append(int(entry.name))
    return found


def test_the_daemon_captures_checks_and_watches_on_a_looped_recording(tmp_path):
    """The daemon's camera is a RealSense recording played in a loop at 30 fps: CAPTURE (with
    the D435's noise profile, as the recording names its camera), CHECKs that are CLEAR (the
    same room), a WATCH that never pauses, and a reader killed mid-WATCH replaced without a
    FAULT (a recording resumes; only a camera that is gone is a fault)."""
    from daemon_rig import Daemon

    recording = tmp_path / "room.db3"  # the room as it stays: the fixture's reference frames
    write_realsense_recording(recording, read_oni_frames(SCENE / "reference.oni"),
                              name="Intel RealSense D435")
    with Daemon(tmp_path / "d", source=f"realsense:{recording}?loop=1&rate=30") as d:
        d.wait_for("READY=1")
        script = ("capture room\nexpect CAPTURED station=room 20\n"
                  + "check room\nexpect CLEAR station=room 20\n" * 3
                  + "set check_interval_ms 200\nexpect PARAM_VALUE value=200 5\n"
                  + "watch room\nexpect HEARTBEAT state=WATCHING 5\n")
        assert d.base(script, connect_timeout=20) == 0, d.transcript.getvalue()[-3000:]
        readers = reader_pids(d.proc.pid)
        assert len(readers) == 1, readers
        os.kill(readers[0], signal.SIGKILL)
        rest = "expect-none PAUSE 5\nstop\nexpect HEARTBEAT state=IDLE 5\n"
        assert d.base(rest, connect_timeout=20) == 0, d.transcript.getvalue()[-3000:]
        assert reader_pids(d.proc.pid) not in ([], readers)
        got = [e for sim in d.sims for e in sim.log]
        assert not [e for e in got if e.name in ("PAUSE", "REPORT", "FAULT")]
        results = [e.obj for e in got if e.name == "CHECK_RESULT"]
        assert len(results) == 3 and all(r.outcome.name == "NO_CHANGE" for r in results)
        captured = next(e.obj for e in got if e.name == "CAPTURED")
        assert captured.noise.startswith("realsense_d435")  # [camera] profile = auto
