"""robot_change.service.systemd: sd_notify datagrams on a real unix socket, the watchdog interval,
and the unit and udev files under systemd/ (systemd-analyze verify must print nothing
unexpected)."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import uuid

import pytest
from conftest import REPO

from robot_change.errors import InputError
from robot_change.service import systemd

UNIT = REPO / "systemd" / "robot-change.service"
RULES = REPO / "systemd" / "99-robot-change.rules"


@pytest.fixture
def notify_socket(tmp_path, monkeypatch):
    """A datagram socket bound in tmp_path, named by $NOTIFY_SOCKET, as systemd provides it."""
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    yield sock
    sock.close()


def received(sock) -> list[str]:
    data = sock.recv(4096)
    assert data.endswith(b"\n")
    return data.decode().splitlines()


def test_each_call_sends_its_message(notify_socket):
    assert systemd.ready() is True
    assert received(notify_socket) == ["READY=1"]
    assert systemd.watchdog() is True
    assert received(notify_socket) == ["WATCHDOG=1"]
    assert systemd.status("watching station dock") is True
    assert received(notify_socket) == ["STATUS=watching station dock"]
    assert systemd.stopping() is True
    assert received(notify_socket) == ["STOPPING=1"]


def test_ready_with_status_and_generic_fields_in_one_datagram(notify_socket):
    systemd.ready(status="kernels loaded\nfrom cache")
    assert received(notify_socket) == ["READY=1", "STATUS=kernels loaded from cache"]
    systemd.notify(errno=5, buserror=True)
    assert received(notify_socket) == ["ERRNO=5", "BUSERROR=1"]
    systemd.extend_timeout(2.5)
    assert received(notify_socket) == ["EXTEND_TIMEOUT_USEC=2500000"]


def test_reloading_carries_a_monotonic_timestamp(notify_socket):
    systemd.reloading()
    lines = received(notify_socket)
    assert lines[0] == "RELOADING=1"
    key, value = lines[1].split("=")
    assert key == "MONOTONIC_USEC" and int(value) > 0


def test_abstract_namespace_socket(monkeypatch):
    name = f"robot-change-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
    try:
        assert systemd.ready() is True
        assert received(sock) == ["READY=1"]
    finally:
        sock.close()


def test_without_systemd_every_call_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert systemd.ready() is False
    assert systemd.watchdog() is False
    assert systemd.status("x") is False
    assert systemd.stopping() is False


def test_a_vanished_socket_is_logged_not_raised(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone"))
    assert systemd.watchdog() is False
    assert "sd_notify" in caplog.text
    monkeypatch.setenv("NOTIFY_SOCKET", "vsock:2:1234")
    assert systemd.ready() is False


def test_fields_that_would_break_the_datagram_are_refused(notify_socket):
    with pytest.raises(InputError, match="newline"):
        systemd.notify(STATUS="two\nlines")
    with pytest.raises(InputError, match="keys"):
        systemd.notify(**{"BAD KEY": 1})
    with pytest.raises(InputError, match="at least one field"):
        systemd.notify()
    with pytest.raises(InputError, match="seconds > 0"):
        systemd.extend_timeout(0)


@pytest.mark.parametrize("usec, pid, expected", [
    ("10000000", None, 5.0),
    ("10000000", "self", 5.0),
    ("10000000", "other", None),
    (None, None, None),
    ("0", None, None),
    ("ten", None, None),
])
def test_watchdog_interval_is_half_of_watchdog_usec(monkeypatch, usec, pid, expected):
    for name, value in (("WATCHDOG_USEC", usec),
                        ("WATCHDOG_PID", {"self": str(os.getpid()),
                                          "other": str(os.getpid() + 1)}.get(pid))):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    assert systemd.watchdog_interval() == expected


# ---------------------------------------------------------------------------------------------
# the unit file


def unit_settings() -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    return settings


def test_unit_keeps_usb_serial_and_the_jit_working():
    s = unit_settings()
    assert s["Type"] == ["notify"]
    assert s["Restart"] == ["on-failure"]
    from robot_change.service.config import EXIT_CONFIG
    assert s["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]
    assert "PrivateDevices" not in s and "MemoryDenyWriteExecute" not in s
    assert s["DevicePolicy"] == ["closed"]
    allowed = {v.split()[0] for v in s["DeviceAllow"]}
    assert {"char-usb_device", "char-ttyUSB", "char-ttyACM"} <= allowed
    assert set(s["SupplementaryGroups"][0].split()) == {"dialout", "plugdev"}
    assert "Environment" in s and "NUMBA_CACHE_DIR=%C/robot-change/numba" in s["Environment"]
    assert "MALLOC_ARENA_MAX=2" in s["Environment"]  # the soak's level RSS (benchmarks.md)
    assert s["ExecStart"][0].startswith("/opt/robot-change/.venv/bin/robot-change run --config "
                                        "/etc/robot-change/robot-change.toml")
    assert int(s["TimeoutStartSec"][0]) >= 120
    assert int(s["WatchdogSec"][0]) > 2 * 1  # more than two camera read timeouts


def _size_mb(value: str) -> float:
    units = {"K": 1 / 1024, "M": 1.0, "G": 1024.0}
    return float(value[:-1]) * units[value[-1]] if value[-1] in units else float(value) / 2**20


def test_unit_limits_fit_the_soak_and_stop_a_leak():
    s = unit_settings()
    high, top = _size_mb(s["MemoryHigh"][0]), _size_mb(s["MemoryMax"][0])
    assert 2 * (214 + 102) <= high < top <= 1024  # the soak's RSS (daemon + reader), with room
    assert high >= 660 + 40  # a cold compile: the daemon and its two helpers (PSS), with room
    assert 16 <= int(s["TasksMax"][0]) <= 128
    assert s["PrivateMounts"] == ["yes"]
    # the stall bound is half of WatchdogSec: captures and checks must fit in it
    assert int(s["WatchdogSec"][0]) / 2 >= 5


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_security_is_no_worse_than_1_5():
    done = subprocess.run(["systemd-analyze", "security", "--offline=true", str(UNIT)],
                          capture_output=True, text=True, timeout=60)
    match = re.search(r"Overall exposure level for robot-change\.service: ([0-9.]+)", done.stdout)
    assert match, done.stdout[-2000:] + done.stderr
    assert float(match.group(1)) <= 1.5


def _verify(path) -> list[str]:
    done = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True,
                          text=True, timeout=60)
    return [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify_prints_nothing_unexpected(tmp_path):
    # its exit status is 1 for the missing ExecStart binary of a dev machine: read the output
    expected = re.compile(r"robot-change\.service: Command /opt/robot-change/\.venv/bin/"
                          r"robot-change is not executable: No such file or directory")
    lines = _verify(UNIT)
    assert [line for line in lines if not expected.fullmatch(line)] == []
    # the same unit with ExecStart pointing to an executable stub: not one line of output
    stub = tmp_path / "bin" / "robot-change"
    stub.parent.mkdir()
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    copy = tmp_path / "robot-change.service"
    copy.write_text(UNIT.read_text().replace("/opt/robot-change/.venv/bin/robot-change",
                                             str(stub)))
    assert _verify(copy) == []
    # and verify does see mistakes: a misspelt key is reported
    broken = tmp_path / "broken" / "robot-change.service"
    broken.parent.mkdir()
    broken.write_text(copy.read_text().replace("NoNewPrivileges=", "NoNewPrivilege="))
    assert any("Unknown key 'NoNewPrivilege'" in line for line in _verify(broken))


# ---------------------------------------------------------------------------------------------
# the udev rules

_RULE_PAIR = re.compile(r'\s*([A-Z_]+(?:\{[A-Za-z0-9_]+\})?)\s*(==|!=|\+=|:=|=)\s*'
                        r'"([^"]*)"\s*(?:,|$)')


def rules() -> list[dict[str, tuple[str, str]]]:
    parsed = []
    for number, line in enumerate(RULES.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        pairs, pos = {}, 0
        while pos < len(line):
            match = _RULE_PAIR.match(line, pos)
            assert match, f"{RULES.name}:{number}: cannot parse from column {pos + 1}: {line[pos:]}"
            pairs[match.group(1)] = (match.group(2), match.group(3))
            pos = match.end()
        parsed.append(pairs)
    return parsed


def test_udev_rules_name_the_base_and_open_the_cameras_to_plugdev():
    parsed = rules()
    base = [r for r in parsed if r.get("SUBSYSTEM") == ("==", "tty")]
    assert len(base) == 1
    assert base[0]["SYMLINK"] == ("+=", "robot-base")
    assert {"ATTRS{idVendor}", "ATTRS{idProduct}", "ATTRS{serial}"} <= set(base[0])
    cameras = {(r["ATTR{idVendor}"][1], r.get("ATTR{idProduct}", ("==", "*"))[1])
               for r in parsed if r.get("SUBSYSTEM") == ("==", "usb")}
    assert ("1d27", "*") in cameras and ("045e", "02ae") in cameras
    for r in parsed:
        if r.get("SUBSYSTEM") == ("==", "usb"):
            assert r["GROUP"] == ("=", "plugdev") and r["MODE"] == ("=", "0660")


def test_notify_never_blocks_on_a_socket_nobody_reads(tmp_path, monkeypatch):
    import socket as socket_module
    import time

    path = tmp_path / "full.sock"
    server = socket_module.socket(socket_module.AF_UNIX, socket_module.SOCK_DGRAM)
    server.bind(str(path))
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        started = time.monotonic()
        results = [systemd.notify(STATUS="x" * 1000) for _ in range(2000)]
        assert time.monotonic() - started < 5.0
        assert results[0] is True and results[-1] is False  # the queue filled up: dropped
    finally:
        server.close()
