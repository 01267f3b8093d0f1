"""The daemon's views of its checks for Foxglove (robot_change.service.views, [viz]): an MCAP
file per CHECK beside the last check, the newest keep_checks kept, a failure to write only a
warning; and the live view: the real daemon (a subprocess) serving the Foxglove WebSocket
protocol, a real client receiving every channel after a CHECK.  Files are read back with the
mcap library; messages decoded from their own schemas."""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk (the viz extra) is not installed")
mcap_reader = pytest.importorskip("mcap.reader", reason="mcap (the test extra) is not installed")
pytest.importorskip("mcap_protobuf", reason="mcap-protobuf-support (the test extra) is missing")
pytest.importorskip("websockets", reason="websockets (the test extra) is not installed")

from daemon_rig import Daemon  # noqa: E402
from foxglove_client import FoxgloveClient, mcap_decoders  # noqa: E402
from test_service import Rig, scene_frames  # noqa: E402,F401 -- the fixture, shared

from robot_change.export.foxglove import POINT_DTYPE, TOPICS  # noqa: E402
from robot_change.service.config import Config, VizConfig  # noqa: E402
from robot_change.service.views import check_file_name, prune_checks  # noqa: E402


def read_check(path: Path) -> dict[str, object]:
    """topic -> decoded message of one check file (exactly one message per topic)."""
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(f, decoder_factories=mcap_decoders())
        got: dict[str, object] = {}
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            assert channel.topic not in got
            got[channel.topic] = decoded
    assert set(got) == set(TOPICS)
    return got


def wait_written(service, count: int, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while service.counters["views_written"] + service.counters["views_failed"] < count:
        assert time.monotonic() < end, dict(service.counters)
        time.sleep(0.02)


def test_every_check_is_a_file_and_the_newest_keep_checks_stay(tmp_path: Path,
                                                               scene_frames) -> None:  # noqa: F811
    config = Config(viz=VizConfig(keep_checks=2))
    with Rig(tmp_path, scene_frames, config=config) as rig:
        assert rig.service.views.live is None  # live is off by default
        rig.run("""
            capture office
            expect CAPTURED 5
            check office
            expect CLEAR station=office 5
        """)
        rig.show("current")
        for _ in range(2):
            rig.run("""
                check office
                expect REPORT station=office 5
                resume
            """)
        wait_written(rig.service, 3)
        folder = tmp_path / "reports" / "checks"
        files = sorted(folder.iterdir())
        assert len(files) == 2 and rig.service.counters["views_failed"] == 0
        assert all(re.fullmatch(r"\d{8}T\d{6}\.\d{6}Z-office\.mcap", f.name) for f in files)
        newest = read_check(files[-1])
        # the file's report is the last check's, as last-check.json has it
        saved = json.loads((tmp_path / "reports" / "office.last-check.json").read_text())
        assert newest["/check/report"] == saved and saved["outcome"] == "changed"
        appeared = np.frombuffer(newest["/change/appeared"].data, POINT_DTYPE)
        assert len(appeared) == sum(r["n_points"] for r in saved["regions"]
                                    if r["kind"] == "appeared")
        assert rig.service.views.last["path"] == files[-1]
        assert rig.service.views.last["bytes"] == files[-1].stat().st_size


def test_a_check_file_that_cannot_be_written_is_a_warning_and_the_check_goes_on(
        tmp_path: Path, scene_frames, caplog) -> None:  # noqa: F811
    with Rig(tmp_path, scene_frames, config=Config(viz=VizConfig(keep_checks=5))) as rig:
        rig.run("""
            capture office
            expect CAPTURED 5
        """)
        folder = tmp_path / "reports" / "checks"
        folder.rmdir()
        folder.write_text("not a folder")  # the disk changed under the daemon
        with caplog.at_level(logging.WARNING, logger="robot_change.service.views"):
            rig.run("""
                check office
                expect CLEAR station=office 5
            """)
            wait_written(rig.service, 1)
            assert rig.service.counters["views_failed"] == 1
            rig.run("""
                check office
                expect CLEAR station=office 5
                status
                expect STATUS state=IDLE fault=0
            """)
        assert "view of the check of office not written" in caplog.text


def test_a_full_disk_is_two_lines_per_check_and_leaves_no_temp_file(
        tmp_path: Path, scene_frames, small_tmpfs, caplog, capfd) -> None:  # noqa: F811
    """Issue 44: on a full disk foxglove-sdk's MCAP writer logged 14 McapError lines per
    view, and the view's own warning a traceback; now two lines: the SDK's first error and
    the view's warning with the free space; no temp file stays."""
    full = small_tmpfs("256k")
    with Rig(tmp_path, scene_frames, config=Config(viz=VizConfig(keep_checks=5))) as rig:
        rig.run("""
            capture office
            expect CAPTURED 5
        """)
        folder = tmp_path / "reports" / "checks"
        folder.rmdir()
        folder.symlink_to(full)
        with open(full / "filler", "wb", buffering=0) as filler, pytest.raises(OSError):
            while True:
                filler.write(b"x" * 4096)
        with caplog.at_level(logging.WARNING):
            for n in (1, 2, 3):
                rig.run("""
                    check office
                    expect CLEAR station=office 5
                """)
                wait_written(rig.service, n)
        assert rig.service.counters["views_failed"] == 3
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) <= 6, lines
    assert sum("MB free in" in line for line in lines) == 3, lines
    assert "Traceback" not in caplog.text + capfd.readouterr().err
    assert sorted(p.name for p in full.iterdir()) == ["filler"]


def check_without_views(tmp_path: Path, scene_frames, caplog) -> str:  # noqa: F811
    """Capture and CHECK with a service whose views could not start; returns its warnings."""
    with caplog.at_level(logging.WARNING, logger="robot_change.service.views"):
        with Rig(tmp_path, scene_frames) as rig:
            assert not rig.service.views.enabled
            rig.run("""
                capture office
                expect CAPTURED 5
                check office
                expect CLEAR station=office 5
            """)
    return caplog.text


def test_a_folder_that_is_a_file_at_start_skips_the_files_with_a_warning(
        tmp_path: Path, scene_frames, caplog) -> None:  # noqa: F811
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "checks").write_text("in the way")
    assert "check files skipped: cannot use the folder" in check_without_views(
        tmp_path, scene_frames, caplog)


def test_without_foxglove_sdk_the_daemon_checks_and_says_the_views_are_skipped(
        tmp_path: Path, scene_frames, caplog, monkeypatch) -> None:  # noqa: F811
    import sys

    monkeypatch.setitem(sys.modules, "foxglove", None)  # as on a robot without the viz extra
    assert ("check views for Foxglove skipped: Foxglove views of a check need foxglove-sdk: "
            "install the 'viz' extra") in check_without_views(tmp_path, scene_frames, caplog)
    assert not (tmp_path / "reports" / "checks").exists()
    assert (tmp_path / "reports" / "office.last-check.json").is_file()


def test_pruning_keeps_the_newest_and_only_touches_check_files(tmp_path: Path) -> None:
    stamps = [1_796_000_000_123_456_789 + k * 1_500_000_000 for k in range(5)]
    names = [check_file_name("dock-2", s) for s in stamps]
    assert names == sorted(names) and names[0] == "20261130T005320.123456Z-dock-2.mcap"
    for name in names + ["notes.txt", "office.last-check.json"]:
        (tmp_path / name).write_text("x")
    gone = prune_checks(tmp_path, 2)
    assert [p.name for p in gone] == names[:3]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        names[3:] + ["notes.txt", "office.last-check.json"])
    assert prune_checks(tmp_path, 0) and not list(tmp_path.glob("*.mcap"))


def test_checks_written_before_the_clock_was_set_back_go_first(tmp_path: Path) -> None:
    """Files named a day ahead (the clock set back since): pruned as the oldest; they were
    kept as the newest, and every check written after them was deleted at once."""
    now = 1_796_000_000_000_000_000
    ahead = [check_file_name("dock", now + 86_400_000_000_000 + k * 10**9) for k in range(3)]
    written = [check_file_name("dock", now - 2_000_000_000 + k * 1_000_000_000) for k in range(2)]
    for name in ahead + written:
        (tmp_path / name).write_text("x")
    assert sorted(p.name for p in prune_checks(tmp_path, 2, now_ns=now)) == ahead
    assert sorted(p.name for p in tmp_path.iterdir()) == written


def test_the_real_daemon_serves_a_check_live_to_a_websocket_client(tmp_path: Path) -> None:
    with Daemon(tmp_path, config="[viz]\nlive = true\nlive_port = 0\nkeep_checks = 1\n") as d:
        d.wait_for("READY=1")
        found = re.search(r"live view for Foxglove on ws://127\.0\.0\.1:(\d+)", d.log())
        assert found, d.log()
        with FoxgloveClient("127.0.0.1", int(found.group(1))) as client:
            client.wait_for_channels(set(TOPICS))
            client.subscribe_all()
            code = d.base("""
                capture office
                expect CAPTURED station=office 10
                check office
                expect CLEAR station=office 5
            """)
            assert code == 0, d.transcript.getvalue()[-3000:]
            got = client.receive(set(TOPICS))
        report = got["/check/report"][1]
        assert report["station"] == "office" and report["outcome"] == "no_change"
        assert {stamp for stamp, _d, _p in got.values()} == {got["/tf"][0]}
        cloud = np.frombuffer(got["/current/cloud"][1].data, POINT_DTYPE)
        assert len(cloud) > 1000 and got["/current/cloud"][1].frame_id == "camera_optical"
        # and the same check as a file
        end = time.monotonic() + 10
        while not list((tmp_path / "state" / "reports" / "checks").glob("*.mcap")):
            assert time.monotonic() < end, d.log()
            time.sleep(0.05)
        [path] = (tmp_path / "state" / "reports" / "checks").glob("*.mcap")
        assert read_check(path)["/check/report"] == report
        code, _seconds = d.terminate()
        assert code == 0, d.log()
    assert "Traceback" not in d.log()
