"""robot_change.tools.basesim: scripted and interactive runs against a fake module over a pty
pair."""

from __future__ import annotations

import io
import os
import threading
import tty
from pathlib import Path

import pytest

from hw.serial_port import FdPort, open_port
from robot_change.errors import InputError
from robot_change.link import protocol as p
from robot_change.link.session import Link, LinkRunner, Received
from robot_change.tools.basesim import BaseSim, parse_command, run_base_sim


class FakeModule:
    """Just enough of the daemon to answer the base: a Link in MODULE role on a pty master."""

    def __init__(self, fd: int) -> None:
        self.runner = LinkRunner(Link(p.Role.MODULE, software="fake-module"), FdPort(fd))
        self.references: set[str] = set()
        self.latch = False
        self.params = {q.id: q.default for q in p.PARAMS}
        self.stop = threading.Event()
        self.beat()
        self.thread = threading.Thread(target=self.runner.run, args=(self.stop, self.handle),
                                       daemon=True)

    def beat(self) -> None:
        self.runner.set_heartbeat(p.Heartbeat(p.ModuleState.IDLE, paused=self.latch, armed=True,
                                              fps_x10=300))

    def handle(self, event) -> None:
        if not isinstance(event, Received):
            return
        m, send = event.message, self.runner.send
        if isinstance(m, p.CaptureReference):
            self.references.add(m.station)
            send(p.Captured(m.station))
        elif isinstance(m, p.Check) and m.station not in self.references:
            send(p.Fault(p.FaultCode.REFERENCE_MISSING, f"no reference for {m.station}"))
        elif isinstance(m, p.Check) and m.station == "kitchen":
            self.latch = True
            self.beat()
            send(p.Pause(p.PauseCause.CHANGE_CHECK))
            regions = [p.Region(p.RegionKind.APPEARED, (i, 0, 2000), (100, 100, 100), 500 + i)
                       for i in range(13)]
            for part in p.split_change_report(7, m.station, regions):
                send(part)
        elif isinstance(m, p.Check):
            send(p.Clear(m.station))
        elif isinstance(m, p.Resume):
            self.latch = False
            self.beat()
        elif isinstance(m, p.StatusQuery):
            send(p.Status(p.ModuleState.IDLE, self.latch, True, False, 300, 42, 0, 5, "kitchen"))
        elif isinstance(m, p.SetParam):
            self.params[m.param] = m.value
            send(p.ParamValue(m.param, m.value))
        elif isinstance(m, p.GetParam):
            send(p.ParamValue(m.param, self.params[m.param]))

    def __enter__(self) -> FakeModule:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)


@pytest.fixture
def pty_line():
    """(module master fd, base slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    os.close(slave)
    os.close(master)


def script(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "base.script"
    path.write_text(text)
    return path


def test_scripted_capture_check_pause_report_resume(tmp_path, pty_line):
    master, path = pty_line
    out = io.StringIO()
    with FakeModule(master):
        code = run_base_sim(path, script(tmp_path, """
            # a whole round: reference, change, pause, report, resume, parameters
            capture kitchen
            expect CAPTURED station=kitchen
            check kitchen
            expect PAUSE cause=CHANGE_CHECK 2.0
            expect REPORT station=kitchen regions=13
            expect BASE paused=1
            resume
            expect HEARTBEAT paused=0
            expect BASE paused=0 1.0
            set watch_m 4
            expect PARAM_VALUE param=1 value=4
            get watch_m
            expect PARAM_VALUE value=4
            status
            expect STATUS frame_index=42
            """), out=out)
    text = out.getvalue()
    assert code == 0, text
    assert "<- PAUSE cause=CHANGE_CHECK" in text
    assert "report 7 for kitchen: 13 region(s)" in text
    assert ("appeared    at (12, 0, 2000) mm (forward, left, up), 100 x 100 x 100 mm, 512 points"
            in text)
    assert "** base PAUSED: the module's pause latch is set" in text


def test_unmet_expectation_fails_with_the_line(tmp_path, pty_line):
    master, path = pty_line
    out = io.StringIO()
    with FakeModule(master):
        code = run_base_sim(path, script(tmp_path, "check hall\nexpect PAUSE 0.3\n"), out=out)
    assert code == 1
    assert "FAIL line 2: `expect PAUSE 0.3` not met within 0.3 s" in out.getvalue()
    assert "FAULT" in out.getvalue()  # what did arrive is shown


def test_expect_none(tmp_path, pty_line):
    master, path = pty_line
    out = io.StringIO()
    with FakeModule(master):
        ok = run_base_sim(path, script(tmp_path, "capture hall\ncheck hall\nexpect CLEAR\n"
                                                 "expect-none PAUSE 0.3\n"), out=out)
        bad = run_base_sim(path, script(tmp_path, "capture kitchen\ncheck kitchen\n"
                                                  "expect-none PAUSE 1.0\n"), out=out)
    assert ok == 0, out.getvalue()
    assert bad == 1 and "`expect-none PAUSE 1.0`: got PAUSE" in out.getvalue()


def test_no_module_means_exit_1_with_a_hint(tmp_path, pty_line):
    _, path = pty_line
    out = io.StringIO()
    code = run_base_sim(path, script(tmp_path, "status\n"), out=out, connect_timeout=0.3)
    assert code == 1 and "no answer from the module" in out.getvalue()


def test_bad_script_is_refused_before_the_port_is_opened(tmp_path):
    with pytest.raises(InputError, match=r"base.script:2: unknown parameter 'watch_x'"):
        run_base_sim("/dev/does-not-matter", script(tmp_path, "status\nset watch_x 3\n"))
    with pytest.raises(InputError, match="cannot read the script"):
        run_base_sim("loop://", tmp_path / "missing.script")


def test_interactive_reads_stdin_and_survives_typos(pty_line):
    master, path = pty_line
    out = io.StringIO()
    with FakeModule(master):
        code = run_base_sim(path, stdin=io.StringIO("status\nbogus\ncheck ../x\ncapture dock\n"),
                            out=out)
    text = out.getvalue()
    assert code == 0
    assert "-> STATUS_QUERY" in text and "-> CAPTURE_REFERENCE station=dock" in text
    assert "error: unknown command 'bogus'" in text
    assert "error: CHECK.station='../x'" in text
    assert "ok CAPTURE_REFERENCE" in text


@pytest.mark.parametrize("line,needle", [
    ("check", "one station name"),
    ("check a b", "one station name"),
    ("set watch_m 11", "whole number in 1..10"),
    ("set watch_m x", "not an integer"),
    ("get nope", "unknown parameter"),
    ("wait soon", "not a number"),
    ("expect PAUSE 1 2", "unexpected"),
    ("expect NOTHING", "expect a message type"),
    ("expect-none PAUSE", "needs the seconds"),
    ("motion flying", "parked, moving or unknown"),
    ("raw zz", "hex bytes"),
    ("stop now", "takes no argument"),
])
def test_command_errors_say_what_to_type(line, needle):
    with pytest.raises(InputError, match=needle):
        parse_command(line)


def test_commands_become_messages():
    assert parse_command("watch kitchen")[2] == p.Watch("kitchen")
    assert parse_command("set check_interval_ms 250")[2] == p.SetParam(3, 250)
    assert parse_command("resume  # lift the latch")[2] == p.Resume()
    assert parse_command("   # only a comment")[0] == ""


def test_expect_takes_the_replies_to_one_command_in_any_order_and_never_twice():
    import io

    from hw.serial_port import open_port
    from robot_change.tools.basesim import BaseSim, BaseState

    sim = BaseSim(open_port("loop://"), out=io.StringIO())
    sim._record("PAUSE", p.Pause(p.PauseCause.CHANGE_CHECK))
    sim._record("BASE", BaseState(True, "latch"))  # arrives before the heartbeat ...
    sim._record("HEARTBEAT", p.Heartbeat(p.ModuleState.PAUSED, paused=True))
    assert sim.expect("PAUSE", {}, 0.0) is not None
    assert sim.expect("HEARTBEAT", {"paused": "1"}, 0.0) is not None
    assert sim.expect("BASE", {"paused": "1"}, 0.0) is not None  # ... and is still found
    assert sim.expect("BASE", {"paused": "1"}, 0.0) is None  # but only once
    assert sim.expect("PAUSE", {}, 0.0) is None


def test_expect_after_a_programmatic_command_ignores_what_came_before_it():
    """BaseSim.command (as robot-change demo sends) marks the log like a script line does: an
    old heartbeat that matches must not answer for the command sent after it."""
    import io

    from hw.serial_port import open_port
    from robot_change.tools.basesim import BaseSim

    sim = BaseSim(open_port("loop://"), out=io.StringIO())
    sim._record("HEARTBEAT", p.Heartbeat(p.ModuleState.IDLE, paused=False))  # long ago
    sim._record("PAUSE", p.Pause(p.PauseCause.CHANGE_CHECK))
    assert sim.expect("PAUSE", {}, 0.0) is not None
    sim.command("resume")
    assert sim.expect("HEARTBEAT", {"paused": "0"}, 0.0) is None
    sim._record("HEARTBEAT", p.Heartbeat(p.ModuleState.IDLE, paused=False))
    assert sim.expect("HEARTBEAT", {"paused": "0"}, 0.0) is sim.log[-1]


def test_the_base_may_not_move_before_the_module_was_heard(pty_line):
    master, path = pty_line
    port = open_port(path, timeout=0.01)
    try:
        out = io.StringIO()
        sim = BaseSim(port, out=out)
        sim.pump(0.8)  # nobody on the other end
        assert sim.paused and "may move" not in out.getvalue()
        # a module frame that is not a HEARTBEAT with paused = 0 is not enough either (7.6)
        os.write(master, p.encode(p.Hello(p.Role.MODULE, 3), 1))
        sim.pump(0.2)
        assert sim.paused and "may move" not in out.getvalue()
        os.write(master, p.encode(p.Heartbeat(p.ModuleState.IDLE), version=1))
        sim.pump(0.1)
        assert not sim.paused and "may move" in out.getvalue()
    finally:
        port.close()


def test_loop_port_is_refused_with_what_to_give_instead():
    with pytest.raises(InputError, match="loop://.*own frames"):
        run_base_sim("loop://")
