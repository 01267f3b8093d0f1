"""hw.serial_port: loop://, real pty pairs, actionable errors, reopening after the port vanished."""

from __future__ import annotations

import errno
import os
import socket
import subprocess
import sys
import time
import tty
from pathlib import Path

import pytest
import serial

from hw.errors import PortError, UriError
from hw.serial_port import ReopeningPort, open_port


def pty_pair() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


def read_for(read, want: int, seconds: float = 2.0) -> bytes:
    got = b""
    deadline = time.monotonic() + seconds
    while len(got) < want and time.monotonic() < deadline:
        got += read()
    return got


def test_loop_url_round_trip():
    port = open_port("loop://", timeout=0.05)
    try:
        port.write(b"\x04\x01\x02\x05\x01\x03\xbd\xc5\x00")
        assert port.read(9) == b"\x04\x01\x02\x05\x01\x03\xbd\xc5\x00"
        assert port.baudrate == 115200
    finally:
        port.close()


def test_pty_path_carries_bytes_both_ways_untouched():
    master, slave, path = pty_pair()
    port = open_port(path, baudrate=115200, timeout=0.05)
    os.close(slave)
    try:
        everything = bytes(range(256))  # raw: no echo, no CR/LF mangling, 0x03 is not ^C
        port.write(everything)
        assert read_for(lambda: os.read(master, 4096), 256) == everything
        os.write(master, everything[::-1])
        assert read_for(lambda: port.read(256), 256) == everything[::-1]
    finally:
        port.close()
        os.close(master)


def test_missing_device_says_to_plug_it_in():
    with pytest.raises(PortError,
                       match="does not exist: is the USB serial adapter plugged in") as info:
        open_port("/dev/ttyUSB_robot_change_missing")
    assert "/dev/serial/by-id/" in str(info.value)


def test_unknown_scheme_is_a_uri_error_listing_the_schemes():
    with pytest.raises(UriError, match="unknown scheme 'kinect'.*loop://"):
        open_port("kinect://0")
    with pytest.raises(UriError):
        open_port("")


def test_permission_denied_names_the_dialout_group(monkeypatch):
    def refuse(url, **kwargs):
        raise serial.SerialException(errno.EACCES,
                                     f"could not open port {url}: [Errno 13] Permission denied")

    monkeypatch.setattr(serial, "serial_for_url", refuse)
    with pytest.raises(PortError, match="dialout"):
        open_port("/dev/ttyUSB0")


def test_a_port_in_use_is_refused_with_a_hint():
    master, slave, path = pty_pair()
    first = open_port(path)
    try:
        with pytest.raises(PortError, match="in use by another process"):
            open_port(path)
    finally:
        first.close()
        os.close(slave)
        os.close(master)


def test_socket_refused_says_to_check_the_server():
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port_number = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(PortError, match="is the server listening"):
        open_port(f"socket://127.0.0.1:{port_number}")


def test_reopening_port_survives_the_device_vanishing(tmp_path: Path):
    link = tmp_path / "ttyBASE"  # like the udev symlink /dev/robot-base
    master1, slave1, path1 = pty_pair()
    link.symlink_to(path1)
    changes = []
    port = ReopeningPort(str(link), timeout=0.02, backoff=(0.01, 0.05),
                         on_change=lambda up, err: changes.append((up, err)))
    os.close(slave1)
    try:
        assert port.connected
        os.write(master1, b"hello\x00")
        assert read_for(lambda: port.read(64), 6) == b"hello\x00"
        os.close(master1)  # the adapter is unplugged
        link.unlink()
        assert read_for(lambda: port.read(64), 1, seconds=0.3) == b""
        assert not port.connected and port.losses == 1
        assert changes[1][0] is False and "vanished" in str(changes[1][1])
        assert isinstance(port.last_error, PortError)  # now: the latest reopen attempt's reason
        assert port.write(b"lost") == 0 and port.dropped_bytes == 4
        with pytest.raises(OSError):
            port.fileno()
        master2, slave2, path2 = pty_pair()  # plugged in again, maybe a new /dev/pts number
        link.symlink_to(path2)
        deadline = time.monotonic() + 2.0
        while not port.connected and time.monotonic() < deadline:
            port.read(1)
        os.close(slave2)
        assert port.connected and port.opens == 2
        os.write(master2, b"again\x00")
        assert read_for(lambda: port.read(64), 6) == b"again\x00"
        port.write(b"out")
        assert read_for(lambda: os.read(master2, 64), 3) == b"out"
        assert [up for up, _ in changes] == [True, False, True]
        os.close(master2)
    finally:
        port.close()


def test_a_peer_that_takes_no_bytes_does_not_hold_the_writer():
    """A base that stopped reading: the pty's buffer fills, each write gives up after its
    timeout and drops what did not fit (counted; the port is not taken for lost), and once the
    peer reads again the next write starts with a lone 0x00 that ends the cut frame."""
    master, slave, path = pty_pair()
    os.close(slave)
    os.set_blocking(master, False)
    port = ReopeningPort(path, timeout=0.01, write_timeout=0.05)
    try:
        for _ in range(4096):  # 4 MB: more than a pty holds
            port.write(b"\x01" * 1024)
            if port.full_writes:
                break
        assert port.full_writes == 1 and port.dropped_bytes >= 1024
        assert port.write(b"\x01" * 1024) == 0 and port.full_writes == 2  # not waited for long
        drained = b""
        while chunk := read_for(lambda: _read_some(master), 1, seconds=0.2):
            drained += chunk
        assert drained and set(drained) <= {0, 1}  # a cut write may have begun with its 0x00
        assert port.write(b"\x02\x00") == 3
        assert read_for(lambda: _read_some(master), 3) == b"\x00\x02\x00"
        assert port.connected and port.losses == 0
    finally:
        port.close()
        os.close(master)


def _read_some(fd: int) -> bytes:
    try:
        return os.read(fd, 65536)
    except BlockingIOError:
        return b""


def test_a_network_port_that_drops_names_the_network():
    """socket://: a peer that closes is a loss like an unplugged adapter, told as a network's
    (the operator's look: it said "check the USB cable")."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = ReopeningPort(f"socket://127.0.0.1:{server.getsockname()[1]}", timeout=0.02,
                         backoff=(0.05, 0.1))
    try:
        peer, _ = server.accept()
        peer.close()
        deadline = time.monotonic() + 2.0
        while port.connected and time.monotonic() < deadline:
            port.read(16)
        assert not port.connected and port.losses == 1
        assert "check the network and the bridge" in str(port.last_error)
    finally:
        port.close()
        server.close()


def test_reopening_port_waits_for_a_device_that_is_not_there_yet(tmp_path: Path):
    link = tmp_path / "ttyLATE"
    with pytest.raises(PortError, match="does not exist"):
        ReopeningPort(str(link), wait=False)
    port = ReopeningPort(str(link), timeout=0.01, backoff=(0.01, 0.02))
    try:
        assert not port.connected and "does not exist" in str(port.last_error)
        assert port.read(1) == b""
        master, slave, path = pty_pair()
        link.symlink_to(path)
        deadline = time.monotonic() + 2.0
        while not port.connected and time.monotonic() < deadline:
            port.read(1)
        assert port.connected
        os.close(slave)
        os.close(master)
    finally:
        port.close()


def test_hw_stays_a_leaf():
    code = ("import sys, hw.serial_port; "
            "bad = [m for m in sys.modules if m.startswith('robot_change')]; "
            "sys.exit(1 if bad else 0)")
    root = Path(__file__).resolve().parents[1]
    assert subprocess.run([sys.executable, "-c", code], cwd=root).returncode == 0


def test_fd_port_carries_bytes_over_a_pty_pair_and_reads_nothing_once_the_other_end_closes():
    import os
    import tty

    from hw.serial_port import FdPort, open_port

    master, slave = os.openpty()
    tty.setraw(slave)
    far = open_port(os.ttyname(slave), timeout=0.5)
    os.close(slave)
    near = FdPort(master)
    try:
        assert near.read(16) == b""  # nothing waiting: no exception, no block
        assert near.write(b"\x01\x02\x00") == 3
        assert far.read(3) == b"\x01\x02\x00"
        far.write(b"pong")
        far.flush()
        deadline = 50
        got = b""
        while len(got) < 4 and deadline:
            got += near.read(16)
            deadline -= 1
            if len(got) < 4:
                import time

                time.sleep(0.01)
        assert got == b"pong"
        far.close()
        assert near.read(16) == b""  # EIO from a closed pty is "nothing", not a crash
    finally:
        os.close(master)
