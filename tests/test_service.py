"""robot_change.service.core in process: the real link over a pty pair, the simulated base, a real
images source paced like a camera, a real store.

The "camera" is a folder of 16-bit PNGs read at 30 fps in a loop; the scene changes when the
files are replaced in place by the frames of the changed scene (office_box_added), and the
camera is lost when the folder goes away.  Every wait is bounded (basesim's expect timeouts,
the service's own timeouts); the whole file runs in about half a minute.
"""

from __future__ import annotations

import collections
import concurrent.futures
import io
import json
import logging
import os
import shutil
import threading
import time
import tty
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from daemon_rig import WATCH_SETUP

from hw.depth import open_depth
from hw.serial_port import FdPort, open_port
from robot_change.errors import ConfigError
from robot_change.link import protocol as p
from robot_change.link.session import LinkState, SendFailed
from robot_change.service.camera import FrameQueue
from robot_change.service.config import Config, config_from_dict
from robot_change.service.core import Service, ServiceOptions, wire_text
from robot_change.service.daemon import _reload
from robot_change.service.store import ReferenceStore
from robot_change.service.warmup import warm_up
from robot_change.service.watch import StationWatch, depth_gate
from robot_change.tools.basesim import BaseSim

SCENE = "office_box_added"


@pytest.fixture(scope="module")
def scene_frames() -> dict[str, list[Path]]:
    """The PNG frames of both epochs (decoded once from the .oni fixtures), kernels warm."""
    from sim_fixtures import load_scene

    scene = load_scene(SCENE)
    out = {}
    for epoch in ("reference", "current"):
        folder = Path(scene.uri(epoch, "images").removeprefix("images:"))
        out[epoch] = sorted(folder.glob("*.png"))
    warm_up()
    return out


def show(scene_frames: dict[str, list[Path]], camera: Path, epoch: str) -> None:
    """Make the camera folder show ``epoch`` (files replaced in place, atomically)."""
    camera.mkdir(exist_ok=True)
    for i, src in enumerate(scene_frames[epoch]):
        tmp = camera / f".{i:03d}.tmp"
        shutil.copyfile(src, tmp)
        os.replace(tmp, camera / f"{i:03d}.png")


class Rig:
    """A service and a simulated base on the two ends of a pty pair."""

    def __init__(self, tmp: Path, scene_frames: dict[str, list[Path]], camera: Any = None,
                 options: ServiceOptions | None = None, config: Config | None = None,
                 proto_max: int = p.VERSION) -> None:
        self.tmp, self.frames = tmp, scene_frames
        self.camera_dir = tmp / "camera"
        show(scene_frames, self.camera_dir, "reference")
        master, slave = os.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        self.master, self.slave = master, slave
        self.port = open_port(os.ttyname(slave), timeout=0.01)
        self.store = ReferenceStore(tmp / "state" / "references")
        uri = f"images:{self.camera_dir}?rate=30&loop=1"
        camera = camera if camera is not None else (lambda: open_depth(uri))
        options = options or ServiceOptions(report_dir=tmp / "reports")
        self.service = Service(config or Config(), camera, self.port, self.store, options)
        self.out = io.StringIO()
        self.sim = BaseSim(FdPort(master), out=self.out, proto_max=proto_max)

    def __enter__(self) -> Rig:
        self.service.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.service.close()
        self.port.close()
        os.close(self.slave)
        os.close(self.master)

    def show(self, epoch: str) -> None:
        show(self.frames, self.camera_dir, epoch)

    def run(self, text: str) -> None:
        """Run basesim script lines; fail with the transcript when one does not hold."""
        lines = [(n, line) for n, line in enumerate(text.strip().splitlines(), 1) if line.strip()]
        code = self.sim.run_script(lines)
        assert code == 0, self.out.getvalue()[-4000:]


@pytest.fixture
def rig(tmp_path: Path, scene_frames):
    with Rig(tmp_path, scene_frames) as r:
        yield r


# --- units --------------------------------------------------------------------------------------


def test_fault_texts_name_the_thing_without_the_machines_paths() -> None:
    """Issue 44: a missing image folder was "the module's state folder", /dev/ttyUSB0 too."""
    cases = {
        "cannot open the camera: /data/runs/kitchen_frames: no such file or folder":
            "cannot open the camera: kitchen_frames: no such file or folder",
        "serial port /dev/ttyUSB0 lost": "serial port ttyUSB0 lost",
        "reference /var/lib/robot-change/references/dock.scene.npz is damaged; moved to "
        "/var/lib/robot-change/references/quarantine/": "reference dock.scene.npz is damaged; "
        "moved to quarantine",
        "disk full at / (5 MB free)": "disk full at / (5 MB free)",
        "station dock: no reference": "station dock: no reference",
    }
    for text, wire in cases.items():
        assert wire_text(text) == wire, text


def test_frame_queue_drops_the_oldest_and_accounts_for_every_frame(scene_frames) -> None:
    with open_depth(str(scene_frames["reference"][0])) as source:
        frame = source.read()
    q = FrameQueue(size=3)
    for _ in range(10):
        q.put(frame)
    assert q.counts() == {"received": 10, "processed": 0, "dropped": 7, "queued": 3}
    _, _, seq = q.get()
    assert seq == 7  # the newest three were kept, in order
    assert len(q.drain()) == 2 and q.get(0.01) is None
    counts = q.counts()
    assert counts["received"] == counts["processed"] + counts["dropped"] + counts["queued"]


def test_depth_gate_sees_the_box_and_not_the_noise(scene_frames) -> None:
    from hw.imagefile import read_image

    ref = [read_image(f) for f in scene_frames["reference"]]
    cur = [read_image(f) for f in scene_frames["current"]]
    from robot_change.cloud.fusion import fuse_depth

    fused = fuse_depth(np.stack(ref), 2)  # the gate compares with the reference's fused depth
    from robot_change.change.params import ChangeParams
    from robot_change.noise.profile import DEFAULT_PROFILE, builtin_profile

    params = ChangeParams()
    margins = (builtin_profile(DEFAULT_PROFILE), params.free_space_sigmas, params.free_space_pose_m)
    quiet = max(depth_gate(fused, f, *margins) for f in ref)
    moved = min(depth_gate(fused, f, *margins) for f in cur)
    options = ServiceOptions()
    assert moved - quiet > 4 * (options.gate_pixels + options.gate_fraction * quiet)


# --- commands -----------------------------------------------------------------------------------


def test_capture_then_check_without_change_answers_clear(rig: Rig) -> None:
    rig.run("""
        capture office
        expect CAPTURED station=office 5
        check office
        expect CLEAR station=office 5
        expect-none PAUSE 0.3
        status
        expect STATUS state=IDLE paused=0 armed=1 fault=0 station=office
    """)
    assert rig.store.stations() == ["office"]
    assert (rig.tmp / "reports" / "office.last-check.npz").is_file()
    # the reference records the camera's mounting of the configuration it was captured with
    assert rig.store.load("office").mount == rig.service.config.camera.mount()
    # version 4: CAPTURED tells what the station can see and the camera's noise profile
    captured = next(e.obj for e in rig.sim.log if e.name == "CAPTURED")
    assert rig.sim.link.version == p.VERSION
    assert captured.noise == rig.store.load("office").noise.name
    assert 50 < captured.smallest_change_mm < 200


def test_check_with_a_change_pauses_reports_and_resume_clears_the_latch(rig: Rig) -> None:
    # the check's files (two compressed VGA depth images, fsynced) take tens of ms: they are
    # written after the PAUSE has gone out, before the report
    latched_when_writing = []
    write_check = rig.service._write_check

    def noting_write_check(*args):
        latched_when_writing.append(rig.service.state_fields()["paused"])
        write_check(*args)

    rig.service._write_check = noting_write_check
    rig.run("""
        capture office
        expect CAPTURED 5
    """)
    rig.show("current")
    rig.run("""
        check office
        expect PAUSE cause=CHANGE_CHECK 5
        expect REPORT station=office regions=1 2
        expect CHECK_RESULT outcome=CHANGED 2
        expect HEARTBEAT state=PAUSED paused=1 1
        expect BASE paused=1 1
        resume
        expect HEARTBEAT state=IDLE paused=0 1
        expect BASE paused=0 1
    """)
    # CHECK_RESULT is sent first, but messages of different seqs may arrive in any order
    # (docs/protocol.md 7.1): in PARTs the one-region report often completes first
    report = next(e.obj for e in rig.sim.log if e.name == "REPORT")
    region = report.regions[0]
    assert region.kind == p.RegionKind.APPEARED
    # protocol 2: base_link (x forward, y left, z up); the box stands about 2.2 m ahead, on
    # the floor below the camera
    assert 1800 < region.centroid_mm[0] < 2700 and region.centroid_mm[2] < 0
    assert 300 < max(region.extent_mm) < 700
    result = next(e.obj for e in rig.sim.log if e.name == "CHECK_RESULT")
    assert result.outcome == p.CheckOutcome.CHANGED and result.report_id == report.report_id
    assert result.fitness_permille > 800 and max(map(abs, result.offset_mm)) < 20
    assert latched_when_writing == [True]
    saved = np.load(rig.tmp / "reports" / "office.last-check.npz")
    assert saved["appeared_mask"].sum() > 500 and saved["region_kinds"].tolist() == [1]
    summary = json.loads((rig.tmp / "reports" / "office.last-check.json").read_text())
    assert summary["outcome"] == "changed" and summary["station"] == "office"
    assert summary["registration"]["fitness"] > 0.8 and "offset_base" in summary


def test_an_older_base_gets_version_1_answers(tmp_path: Path, scene_frames) -> None:
    with Rig(tmp_path, scene_frames, proto_max=1) as rig:
        rig.run("capture office\nexpect CAPTURED 5")
        rig.show("current")
        rig.run("""
            check office
            expect PAUSE cause=CHANGE_CHECK 5
            expect REPORT station=office regions=1 2
        """)
        assert rig.sim.link.version == rig.service.link.version == 1
        assert not [e for e in rig.sim.log if e.name == "CHECK_RESULT"]
        # CAPTURED as version 1 has it: the station alone
        captured = next(e.obj for e in rig.sim.log if e.name == "CAPTURED")
        assert captured.smallest_change_mm is None and captured.noise is None
        region = next(e.obj for e in rig.sim.log if e.name == "REPORT").regions[0]
        assert 1800 < region.centroid_mm[2] < 2700  # camera optical frame, as version 1 says


def test_disarmed_check_reports_without_pause(rig: Rig) -> None:
    rig.run("capture office\nexpect CAPTURED 5")
    rig.show("current")
    rig.run("""
        disarm
        expect HEARTBEAT armed=0 1
        check office
        expect REPORT regions=1 5
        expect-none PAUSE 0.3
        set pause_on_change 0
        expect PARAM_VALUE value=0
        arm
        check office
        expect REPORT regions=1 5
        expect-none PAUSE 0.3
    """)


def test_check_without_a_reference_is_a_fault(rig: Rig) -> None:
    rig.run("""
        check nowhere
        expect FAULT code=REFERENCE_MISSING 5
        expect HEARTBEAT state=IDLE 1
    """)


def test_corrupt_reference_is_quarantined_and_reported_not_a_crash(rig: Rig) -> None:
    rig.run("capture office\nexpect CAPTURED 5")
    path = rig.store.path("office")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    rig.run("""
        check office
        expect FAULT code=REFERENCE_MISSING 5
        watch office
        expect FAULT code=REFERENCE_MISSING 5
        status
        expect STATUS state=IDLE
        capture office
        expect CAPTURED 5
        check office
        expect CLEAR 5
    """)
    assert len(list(rig.store.quarantine_dir.glob("office.scene.npz.*"))) == 2  # file + note


def test_exception_inside_a_command_is_internal_error_and_the_service_goes_on(
        rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    import robot_change.change.scene

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(robot_change.change.scene, "build_scene", broken)
    rig.run("capture office\nexpect FAULT code=INTERNAL_ERROR 5")
    monkeypatch.undo()
    rig.run("capture office\nexpect CAPTURED 5\nstatus\nexpect STATUS state=IDLE")


def test_parameters_get_set_bounds_and_the_refused_cross_check(rig: Rig) -> None:
    rig.run("""
        get watch_m
        expect PARAM_VALUE param=1 value=3
        set watch_n 2
        expect FAULT code=COMMAND_REFUSED 1
        expect PARAM_VALUE param=2 value=5 1
        set watch_m 2
        expect PARAM_VALUE param=1 value=2
        set watch_n 2
        expect PARAM_VALUE param=2 value=2
        set check_interval_ms 100
        expect PARAM_VALUE param=3 value=100
    """)
    assert rig.service.params["watch_m"] == 2 and rig.service.params["watch_n"] == 2
    # out of bounds and unknown ids never reach the service: the link NAKs them
    body = bytes([1, 0x49, 0x70, 0, 0]) + bytes([3]) + (50).to_bytes(4, "little", signed=True)
    out_of_range = p.cobs_encode(body + p.crc16(body).to_bytes(2, "big")) + b"\0"
    body = bytes([1, 0x4A, 0x71, 0, 0, 99])
    unknown = p.cobs_encode(body + p.crc16(body).to_bytes(2, "big")) + b"\0"
    rig.run(f"raw {out_of_range.hex(' ')}\nraw {unknown.hex(' ')}\nwait 0.3")
    assert rig.service.link.stats.naks_sent >= 2
    assert rig.service.params["check_interval_ms"] == 100


def test_watch_pauses_only_when_the_change_persists_then_clears(tmp_path: Path,
                                                                 scene_frames) -> None:
    with Rig(tmp_path, scene_frames) as rig:
        rig.run("""
            capture office
            expect CAPTURED 5
            set check_interval_ms 100
            expect PARAM_VALUE value=100
            watch office
            expect HEARTBEAT state=WATCHING 1
            expect-none PAUSE 0.8
        """)
        # it keeps checking and finds nothing: at least 3 checks without a PAUSE (polled, so
        # that a loaded machine's slower checks only make the wait longer, up to 10 s)
        deadline = time.monotonic() + 10.0
        while rig.service.counters["watch_checks"] < 3 and time.monotonic() < deadline:
            rig.run("expect-none PAUSE 0.3")
        assert rig.service.counters["watch_checks"] >= 3
        rig.show("current")
        shown = time.monotonic()
        rig.run("""
            expect PAUSE cause=CHANGE_WATCH 5
            expect REPORT regions=1 2
            expect HEARTBEAT state=WATCHING paused=1 1
        """)
        paused_at = next(e.t for e in rig.sim.log if e.name == "PAUSE")
        log = [e for e in rig.service.watch_log if e["t"] >= shown]
        changed_before_pause = [e for e in log if e["changed"] and e["t"] <= paused_at]
        assert len(changed_before_pause) >= 3, log  # watch_m = 3 of watch_n = 5
        assert next(e for e in log if e.get("action") == "pause")["changed_in_window"] >= 3
        rig.show("reference")
        rig.run("""
            expect CLEAR station=office 5
            expect HEARTBEAT state=WATCHING paused=1 1
            stop
            expect HEARTBEAT state=PAUSED paused=1 1
            resume
            expect HEARTBEAT state=IDLE paused=0 1
        """)
        counts = rig.service.frame_counts()
        assert counts["received"] == counts["processed"] + counts["dropped"] + counts["queued"]


def _second_object(scene_frames: dict[str, list[Path]], folder: Path) -> list[Path]:
    """The current epoch's frames with a second object: a 70 x 70 pixel block standing 40 cm
    nearer, in the half of the image away from the box that was added."""
    from hw.imagefile import read_image, write_png

    folder.mkdir(exist_ok=True)
    reference = read_image(scene_frames["reference"][0]).astype(np.int32)
    current = read_image(scene_frames["current"][0]).astype(np.int32)
    box_columns = np.nonzero(np.abs(current - reference).max(axis=0) > 50)[0]
    width = current.shape[1]
    left = 40 if box_columns.mean() > width / 2 else width - 110
    out = []
    for i, path in enumerate(scene_frames["current"]):
        depth = read_image(path).copy()
        block = depth[200:270, left:left + 70]
        depth[200:270, left:left + 70] = np.where(block > 0, block - 400, 0)
        out.append(folder / f"{i:03d}.png")
        write_png(out[-1], depth)
    return out


def test_a_watch_pauses_again_for_a_new_change_and_once_it_may(tmp_path: Path,
                                                                 scene_frames) -> None:
    """Once per change, but not once per watch: after RESUME the change reported stays
    accepted, a second object beside it raises PAUSE and its own report; a change reported
    while disarmed pauses when ARM comes and it is still there (it never did: the watch
    paused once until a CLEAR)."""
    frames = dict(scene_frames, second=_second_object(scene_frames, tmp_path / "second"))
    with Rig(tmp_path, frames) as rig:
        rig.run(WATCH_SETUP)
        rig.show("current")
        rig.run("""
            expect PAUSE cause=CHANGE_WATCH 5
            expect REPORT regions=1 2
            resume
            expect HEARTBEAT state=WATCHING paused=0 2
            expect-none PAUSE 1.5
        """)
        rig.show("second")
        rig.run("""
            expect PAUSE cause=CHANGE_WATCH 5
            expect REPORT 2
            expect HEARTBEAT state=WATCHING paused=1 1
            stop
            resume
            expect HEARTBEAT state=IDLE paused=0 2
            disarm
            watch office
            expect REPORT 5
            expect-none PAUSE 1.0
            arm
            expect PAUSE cause=CHANGE_WATCH 5
        """)


def test_a_refused_command_leaves_a_watch_running(rig: Rig) -> None:
    """A WATCH or CHECK of a station without a reference is refused (FAULT) and changes
    nothing: the watch in progress goes on and still pauses for a change (it ended in
    silence, the base believing its station watched)."""
    rig.run(WATCH_SETUP)
    rig.run("""
        watch kitchen
        expect FAULT code=REFERENCE_MISSING 5
        check kitchen
        expect FAULT code=REFERENCE_MISSING 5
        expect-none HEARTBEAT state=IDLE 0.5
        expect HEARTBEAT state=WATCHING 1
    """)
    assert rig.service.station == "office"
    rig.show("current")
    rig.run("expect PAUSE cause=CHANGE_WATCH 5")


def test_camera_loss_faults_pauses_a_watch_and_recovers(rig: Rig) -> None:
    rig.run("""
        capture office
        expect CAPTURED 5
        watch office
        expect HEARTBEAT state=WATCHING 1
    """)
    away = rig.tmp / "camera-away"
    rig.camera_dir.rename(away)
    rig.run("""
        expect FAULT code=CAMERA_LOST 5
        expect PAUSE cause=CAMERA_LOST 2
        expect HEARTBEAT state=FAULT fault=1 1
        check office
        expect FAULT code=CAMERA_LOST 5
    """)
    away.rename(rig.camera_dir)
    rig.run("""
        expect FAULT code=CLEARED 15
        expect HEARTBEAT fault=0 1
        resume
        capture office
        expect CAPTURED 5
    """)
    assert rig.service.camera_losses == 1


def test_a_watch_without_its_camera_pauses_once_it_may(rig: Rig) -> None:
    """A camera lost while disarmed pauses the watch at ARM; a WATCH begun while the camera
    is lost is told (FAULT CAMERA_LOST naming it) and pauses (both went on in silence: the
    PAUSE came only at the moment of the loss)."""
    rig.run(WATCH_SETUP + "disarm\nexpect HEARTBEAT armed=0 1")
    away = rig.tmp / "camera-away"
    rig.camera_dir.rename(away)
    rig.run("""
        expect FAULT code=CAMERA_LOST 5
        expect-none PAUSE 1.0
        arm
        expect PAUSE cause=CAMERA_LOST 2
        resume
        expect HEARTBEAT paused=0 2
        expect-none PAUSE 1.0
        stop
        expect HEARTBEAT state=FAULT 2
        watch office
        expect FAULT code=CAMERA_LOST 3
        expect PAUSE cause=CAMERA_LOST 2
    """)
    away.rename(rig.camera_dir)
    rig.run("expect FAULT code=CLEARED 15\nexpect HEARTBEAT state=WATCHING 2")


def test_a_blind_view_in_a_watch_is_told_and_cleared(tmp_path: Path, scene_frames) -> None:
    """Frames without a reading during a watch: FAULT CAMERA_LOST ("sees nothing") and PAUSE;
    when the room is seen again, FAULT CLEARED (the base kept "camera lost" for ever)."""
    from hw.imagefile import read_image, write_png

    folder = tmp_path / "blind"
    folder.mkdir()
    blind = []
    for i, path in enumerate(scene_frames["reference"]):
        blind.append(folder / f"{i:03d}.png")
        write_png(blind[-1], np.zeros_like(read_image(path)))
    with Rig(tmp_path, dict(scene_frames, blind=blind)) as rig:
        rig.run(WATCH_SETUP)
        rig.show("blind")
        rig.run("expect FAULT code=CAMERA_LOST 5\nexpect PAUSE cause=CAMERA_LOST 3")
        rig.show("reference")
        rig.run("expect FAULT code=CLEARED 5\nexpect CLEAR 5")
        assert "sees the room again" in rig.out.getvalue()


def test_dummy_device_loss_and_recovery(tmp_path: Path, scene_frames) -> None:
    from hw.openni2 import open_device

    source = open_device("Oz", lost_after=0.5)
    with Rig(tmp_path, scene_frames, camera=source) as rig:
        rig.run("expect HEARTBEAT fault=0 5")
        seen = rig.service.last_frame_index
        source.simulate_device_loss()
        rig.run("""
            expect FAULT code=CAMERA_LOST 5
            expect FAULT code=CLEARED 10
            status
            expect STATUS state=IDLE fault=0
        """)
        assert rig.service.camera_losses == 1 and seen > 0


def test_a_busy_controller_drops_frames_and_counts_them(tmp_path: Path, scene_frames) -> None:
    rig = Rig(tmp_path, scene_frames, options=ServiceOptions(queue_frames=2))
    # unpaced: the camera delivers as fast as PNGs decode, faster than captures consume
    rig.service.camera.replace_factory(lambda: open_depth(f"images:{rig.camera_dir}?loop=1"))
    with rig:
        rig.run("""
            capture office
            expect CAPTURED 5
            capture office
            expect CAPTURED 5
            status
            expect STATUS
        """)
        counts = rig.service.frame_counts()
        assert counts["dropped"] > 0
        assert counts["received"] == counts["processed"] + counts["dropped"] + counts["queued"]
        status = next(e.obj for e in rig.sim.log if e.name == "STATUS")
        assert 0 < status.frames_dropped <= counts["dropped"]


def test_garbage_on_the_line_while_watching(rig: Rig) -> None:
    rig.run("""
        capture office
        expect CAPTURED 5
        set check_interval_ms 100
        set watch_m 1
        set watch_n 1
        watch office
        expect HEARTBEAT state=WATCHING 1
        garbage 3000
        raw 04 01 7f 05 01 03 00 00 00
        raw 03 02 7f 01 01 00
        garbage 500
        raw 00
        wait 0.5
        status
        expect STATUS state=WATCHING 2
    """)
    link = rig.service.link.counters()
    assert link["bytes_in"] > 3500
    assert sum(v for k, v in link.items() if k.startswith("decode_")) > 0
    rig.show("current")
    rig.run("expect PAUSE cause=CHANGE_WATCH 5")


def test_reload_takes_a_new_camera_and_keeps_the_old_config_when_the_new_one_fails(
        rig: Rig, tmp_path: Path) -> None:
    rig.run("capture office\nexpect CAPTURED 5\nset watch_m 2\nexpect PARAM_VALUE value=2")
    old = rig.service.config

    def bad() -> Config:
        raise ConfigError("x.toml: watch.watch_m = 11: must be a whole number in 1..10")

    _reload(rig.service, bad, None, threading.Event())
    assert rig.service.config is old and rig.service.params["watch_m"] == 2
    other = tmp_path / "other"
    show(rig.frames, other, "current")
    new = config_from_dict({"camera": {"source": f"images:{other}?rate=30&loop=1"},
                            "watch": {"watch_m": 1, "watch_n": 4, "check_interval_ms": 900}})
    _reload(rig.service, lambda: new, lambda c: (lambda: open_depth(c.camera.source)),
            threading.Event())
    # the table is reseeded from the new file, but for what the base set (until a restart)
    assert (rig.service.params["watch_m"], rig.service.params["watch_n"],
            rig.service.params["check_interval_ms"]) == (2, 4, 900)
    rig.run("check office\nexpect PAUSE 5\nexpect REPORT regions=1")


def test_a_reload_keeps_what_the_base_set_with_set_param(rig: Rig, caplog) -> None:
    """A file that says pause_on_change = false, the base's SET_PARAM 1, then a reload: a
    change still pauses (the reload used to put the file's 0 back, in silence)."""
    assert (rig.service.params["watch_m"], rig.service.params["watch_n"]) == (3, 5)
    rig.run("capture office\nexpect CAPTURED 5\nset pause_on_change 1\nexpect PARAM_VALUE "
            "value=1\nset watch_n 3\nexpect PARAM_VALUE value=3")
    quiet = config_from_dict({"camera": {"source": rig.service.config.camera.source},
                              "change": {"pause_on_change": False},
                              "watch": {"watch_m": 4, "watch_n": 5, "check_interval_ms": 700}})
    with caplog.at_level(logging.WARNING, logger="robot_change.service.core"):
        _reload(rig.service, lambda: quiet, None, threading.Event())
    params = rig.service.params
    assert params["pause_on_change"] == 1 and params["check_interval_ms"] == 700
    # the file's watch_m 4 against the base's watch_n 3: neither taken, and said
    assert (params["watch_m"], params["watch_n"]) == (3, 3)
    assert "watch_m 4 > watch_n 3" in caplog.text
    rig.run("get pause_on_change\nexpect PARAM_VALUE value=1")
    rig.show("current")
    rig.run("check office\nexpect PAUSE 5\nexpect REPORT regions=1")


def test_stop_during_a_capture_refuses_it(tmp_path: Path, scene_frames) -> None:
    rig = Rig(tmp_path, scene_frames)
    rig.service.camera.replace_factory(
        lambda: open_depth(f"images:{rig.camera_dir}?rate=5&loop=1"))
    with rig:
        rig.run("""
            set fuse_frames 30
            expect PARAM_VALUE value=30
            capture office
            expect HEARTBEAT state=CAPTURING 2
            stop
            expect FAULT code=COMMAND_REFUSED 3
            expect HEARTBEAT state=IDLE 1
        """)
    assert rig.store.stations() == []


def test_threads_stop_cleanly(rig: Rig) -> None:
    rig.run("status\nexpect STATUS")
    assert rig.service.healthy() == (True, "ok")
    rig.service.close()
    assert not any(t.is_alive() for t in rig.service._threads)
    assert threading.active_count() < 20


def test_watch_checks_only_while_the_base_is_parked(rig: Rig) -> None:
    rig.run("""
        capture office
        expect CAPTURED 5
        set check_interval_ms 100
        set watch_m 1
        set watch_n 1
        watch office
        expect HEARTBEAT state=WATCHING 1
        motion moving
        wait 0.3
    """)
    checks = rig.service.counters["watch_checks"]
    rig.show("current")
    rig.run("""
        expect-none PAUSE 0.8
        motion parked
        expect PAUSE cause=CHANGE_WATCH 5
    """)
    assert rig.service.counters["watch_checks"] <= checks + 2  # nothing ran while it moved


def _frames_of(name: str, epoch: str) -> list[Path]:
    from sim_fixtures import load_scene

    folder = Path(load_scene(name).uri(epoch, "images").removeprefix("images:"))
    return sorted(folder.glob("*.png"))


def test_a_revisit_off_by_centimetres_is_no_change_and_says_how_far_off(tmp_path: Path,
                                                                          scene_frames) -> None:
    frames = {"reference": _frames_of("office_no_change", "reference"),
              "current": _frames_of("office_no_change_pose_5cm", "current"),
              "elsewhere": _frames_of("office_far_offset", "current")}
    with Rig(tmp_path, frames) as rig:
        rig.run("capture office\nexpect CAPTURED 5")
        rig.show("current")
        rig.run("""
            check office
            expect CHECK_RESULT outcome=NO_CHANGE 5
            expect CLEAR station=office 2
            expect-none PAUSE 0.3
        """)
        result = next(e.obj for e in rig.sim.log if e.name == "CHECK_RESULT")
        # the truth: 5 cm / 2 deg; the base frame turns it, the length stays
        assert 40 <= np.linalg.norm(result.offset_mm) <= 60
        assert result.fitness_permille > 700 and result.weak == 0
        rig.show("elsewhere")
        rig.run("""
            check office
            expect CHECK_RESULT outcome=NOT_AT_STATION 5
            expect-none PAUSE 0.3
            expect-none CLEAR 0.1
        """)
        saved = json.loads((tmp_path / "reports" / "office.last-check.json").read_text())
        assert saved["outcome"] == "not_at_station" and saved["not_at_station_reason"]


# --- liveness: injected hangs -------------------------------------------------------------------


#: Capture station "office" and watch it, checking every 100 ms.
WATCH_SCRIPT = """
    capture office
    expect CAPTURED 5
    set check_interval_ms 100
    expect PARAM_VALUE value=100
    watch office
    expect HEARTBEAT state=WATCHING 1
"""


class Hang:
    """Once armed, a wrapped function blocks (as a kernel stuck in native code would) until
    released; ``entered`` says a call is stuck."""

    def __init__(self) -> None:
        self.armed, self.entered, self.release = (threading.Event(), threading.Event(),
                                                  threading.Event())

    def wrap(self, fn: Any) -> Any:
        def hung(*args: Any, **kwargs: Any) -> Any:
            if self.armed.is_set():
                self.entered.set()
                self.release.wait(60)
            return fn(*args, **kwargs)
        return hung


def _hang_target(where: str) -> tuple[Any, str]:
    import hw.images
    import robot_change.change.detect
    import robot_change.change.scene

    return {"detector": (robot_change.change.detect, "detect_changes"),
            "check": (robot_change.change.detect, "detect_changes"),
            "capture": (robot_change.change.scene, "build_scene"),
            "camera": (hw.images.ImageFolderSource, "read")}[where]


@pytest.mark.parametrize("where", ["detector", "check", "capture", "camera"])
def test_a_hang_is_told_to_the_base_as_a_stall(tmp_path: Path, scene_frames, monkeypatch,
                                               where: str) -> None:
    """A detector, check, capture or camera read that makes no progress within the bound is a
    stall: FAULT STALLED on the wire, PAUSE when armed and watching, the heartbeat's state
    FAULT, and healthy() false from then on (the daemon stops feeding the watchdog)."""
    hang = Hang()
    owner, name = _hang_target(where)
    monkeypatch.setattr(owner, name, hang.wrap(getattr(owner, name)))
    options = ServiceOptions(report_dir=tmp_path / "reports", stall_after_s=1.0,
                             command_allowance_s=1.0)
    with Rig(tmp_path, scene_frames, options=options) as rig:
        try:
            watching = where in ("detector", "camera")
            if watching:
                rig.run(WATCH_SCRIPT + "wait 0.5")
            elif where == "check":
                rig.run("capture office\nexpect CAPTURED 5")
            assert rig.service.healthy() == (True, "ok")
            hang.armed.set()
            armed = time.monotonic()
            if where in ("check", "capture"):
                rig.run(f"{'check' if where == 'check' else 'capture'} office")
            rig.run("expect FAULT code=STALLED 6")
            told = time.monotonic() - armed
            if watching:
                rig.run("expect PAUSE cause=INTERNAL_ERROR 2")
            else:
                rig.run("expect-none PAUSE 0.3")
            rig.run("expect HEARTBEAT state=FAULT fault=1 1")
            assert hang.entered.is_set()
            ok, why = rig.service.healthy()
            part = {"detector": "detector", "check": "CHECK office",
                    "capture": "CAPTURE_REFERENCE office", "camera": "watch"}[where]
            assert not ok and part in why, why
            # within the bound (the camera's: its read timeout + 2 s), plus the monitor's turn
            limit = 3.0 if where == "camera" else 1.0
            assert told < limit + 1.5, told
        finally:
            hang.release.set()


class ParkedHost:
    """A WatchHost whose base is parked with the camera delivering; what the watch sends is
    kept in ``sent``."""

    parked = True
    camera_ok = True

    def __init__(self) -> None:
        self.sent: list[tuple[str, Any]] = []

    def may_pause(self) -> bool:
        return False

    def send_fault(self, code, text) -> None:
        self.sent.append(("fault", code))

    def send_pause(self, cause) -> None:
        self.sent.append(("pause", cause))

    def send_report(self, station, changes) -> int:
        self.sent.append(("report", station))
        return 1

    def send_no_change(self, station, changes) -> None:
        self.sent.append(("no_change", station))


class FirstCheckOnly(concurrent.futures.Executor):
    """Runs the first check at once, in the caller's thread; every later one never starts
    (a check stuck in native code)."""

    def __init__(self) -> None:
        self.ran = False
        self.stuck: list[concurrent.futures.Future] = []

    def submit(self, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        future: concurrent.futures.Future = concurrent.futures.Future()
        if self.ran:
            self.stuck.append(future)
            return future
        self.ran = True
        future.set_result(fn(*args, **kwargs))
        return future


def test_a_watch_check_that_hangs_is_named_as_the_detectors_stall(scene_frames) -> None:
    """The watch part beats when a check starts, not only when a result comes: a check that
    hangs is the detector's stall, told when that check is past the bound, whatever the
    check interval left between the last result and the hung check's start (a race that made
    the watch's silence fire first, 'watch: no progress', when checks were quick)."""
    from hw.depth import DepthFrame
    from robot_change.change.params import ChangeParams
    from robot_change.change.scene import build_scene
    from robot_change.service.liveness import Progress
    from robot_change.service.watch import GateOptions
    from sim_fixtures import load_scene

    sc = load_scene(SCENE)
    depth = sc.reference_frames()
    reference = build_scene(depth, intrinsics=sc.intrinsics)
    clock = [100.0]
    progress = Progress(1.0, clock=lambda: clock[0])
    pool, host = FirstCheckOnly(), ParkedHost()
    watch = StationWatch("office", reference, host,
                         {"watch_m": 3, "watch_n": 5, "check_interval_ms": 100}, ChangeParams(),
                         GateOptions(), pool, progress, collections.Counter(),
                         collections.deque(maxlen=10), lambda: None)
    watch.frame(DepthFrame(depth[0], 0, 0, sc.intrinsics), 0)
    assert watch.step()  # the first check: done at once
    clock[0] += 0.05
    watch.frame(DepthFrame(depth[1], 33_333, 1, sc.intrinsics), 1)
    assert watch.step()  # its result taken (the watch beats at 100.05); the next not due yet
    assert watch.checks == 1 and not pool.stuck and host.sent == []  # no change, no fault
    time.sleep(0.15)  # the check interval, in real time
    clock[0] += 0.45
    assert watch.step()  # the second check starts at 100.5 and hangs
    assert len(pool.stuck) == 1
    clock[0] += 0.8  # 1.25 s since the last result (past the watch's 1.1 s), 0.8 s into it
    assert progress.stalled() == ""
    clock[0] += 0.25  # 1.05 s into the hung check
    assert progress.stalled().startswith("detector: WATCH office: the check of frame 1 has "
                                         "not finished"), progress.stalled()


def test_a_watch_that_stops_checking_is_a_stall_even_with_frames_arriving(
        tmp_path: Path, scene_frames, monkeypatch) -> None:
    """Frames must be checked, not only received: the detector pool refusing work (here: a
    submit that does nothing) leaves no check in flight, and the watch still stalls."""
    options = ServiceOptions(report_dir=tmp_path / "reports", stall_after_s=1.0)
    with Rig(tmp_path, scene_frames, options=options) as rig:
        rig.run(WATCH_SCRIPT + "wait 0.3")
        assert rig.service.healthy()[0]
        monkeypatch.setattr(StationWatch, "_submit", lambda *args: None)
        rig.run("expect FAULT code=STALLED 4\nexpect PAUSE cause=INTERNAL_ERROR 2")
        assert "watch: no progress" in rig.service.healthy()[1]
        assert rig.service.frame_counts()["received"] > 0


def test_a_watch_suspended_while_the_base_moves_is_not_a_stall(rig: Rig) -> None:
    rig.run(WATCH_SCRIPT + "motion moving\nwait 1.5")
    # the default bound is 5 s; force a short one to make the point quickly
    rig.service.progress.bound_s = 0.5
    time.sleep(1.0)
    assert rig.service.healthy() == (True, "ok")
    rig.run("motion parked\nwait 0.5")
    assert rig.service.healthy() == (True, "ok")


def test_a_flaky_camera_reports_fault_and_cleared_at_most_once_per_backoff(
        tmp_path: Path, scene_frames) -> None:
    """A looped folder with one corrupt image: without hysteresis FAULT / CLEARED alternated
    every ~0.5 s.  Now a reopened camera counts as back after 5 good frames, and the back-off
    (0.5 s, doubling) is not reset by them: the gaps between losses grow."""
    from robot_change.service.camera import CAMERA_HEALTHY_FRAMES

    folder = tmp_path / "flaky"
    folder.mkdir()
    good = 2 * CAMERA_HEALTHY_FRAMES
    for i in range(good):
        shutil.copyfile(scene_frames["reference"][i % len(scene_frames["reference"])],
                        folder / f"{i:03d}.png")
    (folder / f"{good:03d}.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    camera = lambda: open_depth(f"images:{folder}?rate=30&loop=1")  # noqa: E731
    with Rig(tmp_path, scene_frames, camera=camera) as rig:
        rig.run("expect FAULT code=CAMERA_LOST 3\nwait 6")
        lost = [e.t for e in rig.sim.log
                if e.name == "FAULT" and e.obj.code == p.FaultCode.CAMERA_LOST]
        cleared = [e.t for e in rig.sim.log
                   if e.name == "FAULT" and e.obj.code == p.FaultCode.CLEARED]
    assert 2 <= len(lost) <= 5, lost  # was ~9 in 6 s
    assert len(cleared) <= len(lost)
    gaps = np.diff(lost)
    assert (gaps[1:] > 1.3 * gaps[:-1]).all(), gaps  # the back-off doubles


def test_a_lost_camera_says_so_again_when_the_reason_changes(tmp_path: Path, caplog) -> None:
    """A reload from one broken source to another left the journal naming the first alone."""
    from robot_change.service.camera import CameraThread
    from robot_change.service.liveness import Progress

    stop, wake = threading.Event(), threading.Event()
    camera = CameraThread(lambda: open_depth(f"oni:{tmp_path / 'first.oni'}"), FrameQueue(),
                          Progress(10.0), stop, wake, lambda: 1.0)
    thread = threading.Thread(target=camera.run, daemon=True)
    with caplog.at_level(logging.ERROR, "robot_change.service.camera"):
        thread.start()
        try:
            _until(lambda: "first.oni" in camera.error)
            camera.swap(lambda: open_depth(f"images:{tmp_path / 'second'}"))
            _until(lambda: "second" in camera.error)
            time.sleep(1.5)  # retries of the same reason: not said again
        finally:
            stop.set()
            thread.join(5)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and "first.oni" in said[0], said
    assert said[1].startswith("camera still lost, now: ") and "second" in said[1], said
    assert camera.losses == 1


def _until(condition, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


def test_a_camera_never_healthy_for_long_enough_stays_lost(tmp_path: Path, scene_frames) -> None:
    from robot_change.service.camera import CAMERA_HEALTHY_FRAMES

    folder = tmp_path / "flaky"
    folder.mkdir()
    for i in range(CAMERA_HEALTHY_FRAMES - 2):
        shutil.copyfile(scene_frames["reference"][i], folder / f"{i:03d}.png")
    (folder / "099.png").write_bytes(b"garbage")
    camera = lambda: open_depth(f"images:{folder}?rate=30&loop=1")  # noqa: E731
    with Rig(tmp_path, scene_frames, camera=camera) as rig:
        rig.run("expect FAULT code=CAMERA_LOST 3\nexpect-none FAULT 3")
        assert not rig.service.camera_ok


def test_a_capture_beyond_the_station_limit_is_a_storage_fault_on_the_wire(
        tmp_path: Path, scene_frames) -> None:
    """Names come from the serial line: a new station past [store] max_stations is refused
    with FAULT STORAGE_ERROR (and logged); capturing a known station again still works."""
    rig = Rig(tmp_path, scene_frames)
    rig.store.max_stations = 1
    with rig:
        rig.run("""
            capture dock
            expect CAPTURED station=dock 10
            capture kitchen
            expect FAULT code=STORAGE_ERROR 10
            capture dock
            expect CAPTURED station=dock 10
        """)
    assert rig.store.stations() == ["dock"]
    assert "max_stations" in rig.out.getvalue()


# -- floods, BUSY, the wire's FAULT texts, the latch after a link fault (issue 16) -----------------


def test_a_status_flood_is_answered_coalesced_and_nothing_is_dropped(rig: Rig, caplog) -> None:
    rig.run("expect HEARTBEAT 1")
    sim = rig.sim
    for _ in range(250):
        sim.runner.send(p.StatusQuery())
    sim.pump(20.0, until=lambda: sim.link.in_flight == 0 and sim.link.queued == 0)
    sim.pump(1.0, until=lambda: rig.service.link.in_flight == 0 and rig.service.link.queued == 0)
    assert not sim.failed  # every query acknowledged
    statuses = [e for e in sim.log if e.name == "STATUS"]
    assert 1 <= len(statuses) <= 250
    assert rig.service.counters["send_failed"] == 0  # no answer dropped
    assert rig.service.link.stats.failed == 0
    assert not [r for r in caplog.records if "not delivered" in r.getMessage()]


def test_commands_beyond_the_queue_are_refused_with_nak_busy(rig: Rig) -> None:
    rig.run("expect HEARTBEAT 1")
    sim = rig.sim
    for _ in range(40):
        sim.runner.send(p.CaptureReference("office"))
    sim.pump(10.0, until=lambda: sim.link.in_flight == 0 and sim.link.queued == 0)
    busy = [f for f in sim.failed if f.nak == p.NakReason.BUSY]
    assert busy and len(busy) == len(sim.failed), [f.reason for f in sim.failed]
    assert rig.service.counters["commands_refused"] == len(busy)
    assert not [e for e in sim.log
                if e.name == "FAULT" and e.obj.code == p.FaultCode.COMMAND_REFUSED]


def test_a_version_2_base_gets_one_coalesced_fault_for_refused_commands(tmp_path: Path,
                                                                         scene_frames) -> None:
    with Rig(tmp_path, scene_frames, proto_max=2) as rig:
        rig.run("expect HEARTBEAT 1")
        sim = rig.sim
        for _ in range(40):
            sim.runner.send(p.CaptureReference("office"))
        sim.pump(10.0, until=lambda: sim.link.in_flight == 0 and sim.link.queued == 0)
        assert not sim.failed  # version 2 knows no BUSY: acknowledged ...
        refused = rig.service.counters["commands_refused"]
        faults = [e for e in sim.log
                  if e.name == "FAULT" and e.obj.code == p.FaultCode.COMMAND_REFUSED]
        assert refused > 0 and 1 <= len(faults) <= refused  # ... and told, coalesced
        assert all("busy" in e.obj.text for e in faults)


def test_fault_texts_carry_no_path_of_the_machine(rig: Rig) -> None:
    rig.run("""
        check nowhere
        expect FAULT code=REFERENCE_MISSING 3
    """)
    (fault,) = [e.obj for e in rig.sim.log if e.name == "FAULT"]
    assert "nowhere" in fault.text and "/" not in fault.text, fault.text
    assert str(rig.tmp) not in fault.text


def test_the_module_sends_pause_again_when_the_link_comes_back_with_the_latch_set(rig: Rig) -> None:
    rig.run("capture office\nexpect CAPTURED 5")
    rig.show("current")
    rig.run("check office\nexpect PAUSE cause=CHANGE_CHECK 5\nexpect REPORT 5")
    time.sleep(1.6)  # the base says nothing: the module's link goes FAULTY after 1 s
    assert rig.service.link.state == LinkState.FAULTY
    rig.run("expect PAUSE cause=CHANGE_CHECK 4")
    assert rig.service.latched


def test_a_pause_that_failed_while_the_link_stayed_up_is_sent_again(rig: Rig) -> None:
    """Version 5: a PAUSE unacknowledged for 10 s fails without the link going FAULTY when
    the base acknowledges the module's other messages; the latch set, it goes out again."""
    rig.run("capture office\nexpect CAPTURED 5")
    rig.show("current")
    rig.run("check office\nexpect PAUSE cause=CHANGE_CHECK 5\nexpect REPORT 5")
    assert rig.service.link.state == LinkState.UP and rig.service.latched
    rig.service._on_event(SendFailed(p.Pause(p.PauseCause.CHANGE_CHECK), 99, "no ACK", None))
    rig.run("expect PAUSE cause=CHANGE_CHECK 4")
    rig.run("resume\nwait 0.5")
    assert not rig.service.latched
    rig.service._on_event(SendFailed(p.Pause(p.PauseCause.CHANGE_CHECK), 99, "no ACK", None))
    rig.run("expect-none PAUSE 1.0")
