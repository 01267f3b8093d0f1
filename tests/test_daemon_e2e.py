"""``robot-change run`` as a real subprocess: a .oni fixture as the camera, the scripted base
(robot_change.tools.basesim) on the other end of a pty pair, systemd's notify socket played by a
test socket.  Plus the configuration errors (exit 78) and ``robot-change demo``.

Every wait is bounded: basesim's expect timeouts, ``subprocess`` timeouts, socket timeouts.
"""

from __future__ import annotations

import importlib.util
import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import pytest
from conftest import REPO, SIM_FIXTURES

from hw.serial_port import FdPort
from robot_change.tools.basesim import run_base_sim

SCENE = SIM_FIXTURES / "scenes" / "office_box_added"


def toml(source: Path, port: str, state: Path, watchdog: bool = True) -> str:
    return (f'[camera]\nsource = {json.dumps(f"oni:{source}?loop=1&rate=auto")}\n'
            f'[serial]\nport = {json.dumps(port)}\n'
            f'[store]\nstate_dir = {json.dumps(str(state))}\n'
            f'[service]\nwatchdog = {"true" if watchdog else "false"}\n')


class Notes:
    """The test's notify socket, read all along by a thread (as systemd reads its own: a full
    datagram queue would block the daemon's sd_notify), KEY=value lines collected (and in
    ``stamped`` with the monotonic time they arrived)."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.lines: list[str] = []
        self.stamped: list[tuple[float, str]] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self.done.is_set():
            try:
                lines = self.sock.recv(4096).decode().splitlines()
            except (TimeoutError, OSError):
                continue
            now = time.monotonic()
            self.stamped += [(now, line) for line in lines]
            self.lines += lines

    def close(self) -> None:
        self.done.set()
        self.thread.join(2)
        self.sock.close()


def script(tmp: Path, name: str, text: str) -> Path:
    path = tmp / name
    path.write_text("\n".join(line.strip() for line in text.strip().splitlines()) + "\n")
    return path


def test_daemon_end_to_end_over_a_pty_with_systemd_notify(tmp_path: Path) -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    state = tmp_path / "state"
    # a corrupt reference waiting for station "kitchen": a FAULT, never a crash
    (state / "references").mkdir(parents=True)
    (state / "references" / "kitchen.scene.npz").write_bytes(b"PK\x03\x04 not a scene" * 10)
    config = tmp_path / "robot-change.toml"
    config.write_text(toml(SCENE / "reference.oni", os.ttyname(slave), state))
    notify = Notes(tmp_path / "notify.sock")
    env = dict(os.environ, NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC="1000000")
    env.pop("WATCHDOG_PID", None)
    log = open(tmp_path / "daemon.log", "w+")
    started = time.monotonic()
    daemon = subprocess.Popen([sys.executable, "-m", "robot_change.cli", "run", "--config",
                               str(config)], cwd=REPO, env=env, stdout=log,
                              stderr=subprocess.STDOUT)
    out = io.StringIO()
    try:
        # READY=1 comes once the kernels are loaded and the threads run
        while "READY=1" not in notify.lines and time.monotonic() - started < 30:
            assert daemon.poll() is None, (tmp_path / "daemon.log").read_text()
            time.sleep(0.05)
        assert "READY=1" in notify.lines, notify.lines
        code = run_base_sim(FdPort(master), script(tmp_path, "one.script", """
            capture office
            expect CAPTURED station=office 10
            check office
            expect CLEAR station=office 5
            check kitchen
            expect FAULT code=REFERENCE_MISSING 5
            status
            expect STATUS state=IDLE fault=0 station=kitchen
        """), out=out, connect_timeout=10)
        assert code == 0, out.getvalue()
        quarantined = list((state / "references" / "quarantine").glob("kitchen.scene.npz.*"))
        assert quarantined, "the corrupt reference was not quarantined"
        # the room changes: the camera now plays the recording with the box; SIGHUP reloads
        config.write_text(toml(SCENE / "current.oni", os.ttyname(slave), state))
        daemon.send_signal(signal.SIGHUP)
        time.sleep(1.5)
        code = run_base_sim(FdPort(master), script(tmp_path, "two.script", """
            check office
            expect PAUSE cause=CHANGE_CHECK 10
            expect REPORT station=office regions=1 2
            expect BASE paused=1 1
            resume
            expect HEARTBEAT paused=0 2
            set check_interval_ms 100
            set watch_m 1
            set watch_n 1
            watch office
            expect PAUSE cause=CHANGE_WATCH 5
            garbage 2000
            raw 00
            wait 0.3
            status
            expect STATUS state=WATCHING paused=1 3
            stop
            expect HEARTBEAT state=PAUSED 2
            resume
            expect HEARTBEAT state=IDLE paused=0 2
        """), out=out, connect_timeout=10)
        assert code == 0, out.getvalue()
        got = list(notify.lines)
        assert got.count("WATCHDOG=1") >= 4, got  # every 0.5 s (WATCHDOG_USEC / 2)
        assert "RELOADING=1" in got and any(n.startswith("STATUS=") for n in got)
        # an emptied file on SIGHUP is refused: the camera does not fall back to openni2://
        config.write_text("")
        daemon.send_signal(signal.SIGHUP)
        # the reload is taken between the main loop's waits: wait for its answer before the
        # check and SIGTERM (a stop pending with it wins, and the reload is never read)
        log_file, deadline = tmp_path / "daemon.log", time.monotonic() + 20
        while "the old one stays" not in log_file.read_text() and time.monotonic() < deadline:
            time.sleep(0.05)
        code = run_base_sim(FdPort(master), script(tmp_path, "three.script", """
            check office
            expect PAUSE cause=CHANGE_CHECK 10
        """), out=out, connect_timeout=10)
        assert code == 0, out.getvalue()
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(15) == 0
        time.sleep(0.2)
        assert "STOPPING=1" in notify.lines
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(5)
        notify.close()
        os.close(master)
        os.close(slave)
    text = (tmp_path / "daemon.log").read_text()
    assert "Traceback" not in text, text
    assert "configuration reloaded; reopening the camera" in text
    assert "the new configuration is refused, the old one stays" in text
    assert "holds no key at all" in text
    assert "quarantine" in text


def run(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robot_change.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("content, message", [
    ("[watch]\nwatch_m = 11\n", "watch.watch_m = 11: must be a whole number in 1..10"),
    ("[watch]\nwatch_m = 4\nwatch_n = 3\n", "watch.watch_m = 4: must be <= watch.watch_n = 3"),
    ("[camera]\nsource = 'ftp://x'\n", "camera.source"),
    ("[camera]\nsource = 'openni2://?lopp=1'\n", "unknown OpenNI2 option 'lopp'"),
    ("[camera]\nsource = 'images:/data/run?rate=fast'\n", "rate='fast'"),
    ("[camera]\nsource = 'realsense://?preset=ultra'\n", "preset='ultra'"),
    ("[change]\nfree_space_sigmas = -1.0\n", "free_space_sigmas=-1.0"),
    ('[fleet]\nbroker = "mqtt://broker"\nspool_mb = -1\n', "fleet.spool_mb = -1: must be"),
    (None, "no such configuration file"),
])
def test_bad_config_exits_78_with_a_clear_message(tmp_path: Path, content: str | None,
                                                  message: str) -> None:
    path = tmp_path / "robot-change.toml"
    if content is not None:
        path.write_text(content
                        + f"[serial]\nport = 'loop://'\n[store]\nstate_dir = '{tmp_path}'\n")
    result = run("run", "--config", str(path))
    assert result.returncode == 78, result.stderr
    assert "configuration error" in result.stderr and message in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_demo_runs_the_daemon_and_shows_the_pause_and_the_report(tmp_path: Path) -> None:
    started = time.monotonic()
    result = run("demo", "--out", str(tmp_path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    text = result.stdout
    for line in ("base -> CAPTURE office", "base <- CAPTURED station=office",
                 "base -> CHECK office", "base <- PAUSE cause=CHANGE_CHECK",
                 "base <- CHANGE_REPORT", "appeared:", "daemon stopped by SIGTERM, exit status 0"):
        assert line in text, text
    assert text.index("PAUSE") < text.index("CHANGE_REPORT")
    # every reply came after the command it answers (a stale one would show a negative time)
    times = [int(t) for t in re.findall(r"\((-?\d+) ms\)", text)]
    assert times and min(times) >= 0, text
    assert "base <- HEARTBEAT" in text[text.index("base -> RESUME"):], text
    if importlib.util.find_spec("foxglove") is not None:  # the viz extra: the check as MCAP
        assert "the check in 3-D: open " in text and list(
            (tmp_path / "state" / "reports" / "checks").glob("*-office.mcap")), text
    picture = (tmp_path / "report.png").read_bytes()
    assert picture.startswith(b"\x89PNG\r\n\x1a\n") and len(picture) > 20_000
    assert time.monotonic() - started < 60
