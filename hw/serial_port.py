"""Serial ports by URL over pyserial's ``serial_for_url``: bytes in, bytes out, nothing more.

``open_port(url)`` opens a device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``, a pty's
``/dev/pts/N``) or a pyserial URL (``loop://``, ``socket://host:port``, ``rfc2217://...``) and turns
every failure into :class:`hw.errors.PortError` (or :class:`hw.errors.UriError` for an unknown
scheme) whose message says what to do.  :class:`ReopeningPort` keeps a port usable across the
device vanishing (a USB serial adapter unplugged): reads return nothing and writes are dropped
while it is gone, and it is reopened with backoff.  Framing and sessions live elsewhere
(robot_change.link.protocol, robot_change.link.session); this module imports nothing from
robot_change.
"""

from __future__ import annotations

import errno
import logging
import os
import time
import urllib.parse
from collections.abc import Callable
from typing import Any

import serial

from hw.backoff import Backoff
from hw.errors import PortError, UriError

log = logging.getLogger(__name__)

#: The longest a ReopeningPort's write waits for room in the port's buffer, seconds: a peer
#: that takes no bytes (a base that stopped reading, flow control held) costs the writer this,
#: not its life.
WRITE_TIMEOUT_S = 0.2
#: What open_port() accepts, for error messages.
SCHEMES = ("a device path (/dev/ttyUSB0, /dev/serial/by-id/..., /dev/pts/N)", "loop://",
           "socket://HOST:PORT", "rfc2217://HOST:PORT")


def _explain(url: str, exc: BaseException) -> str:
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code == errno.ENOENT or "No such file" in text:
        return (f"serial port {url} does not exist: is the USB serial adapter plugged in? "
                "List the adapters with `ls -l /dev/serial/by-id/` and use that path, or install "
                "the udev rule in systemd/ for a stable name")
    if code in (errno.EACCES, errno.EPERM) or "Permission denied" in text:
        return (f"permission denied on serial port {url}: add the user to the 'dialout' group "
                "(`sudo usermod -aG dialout $USER`, then log in again), or run the service with "
                "SupplementaryGroups=dialout")
    if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK) or "lock" in text.lower():
        return (f"serial port {url} is in use by another process: find it with `fuser {url}` "
                "(is another robot-change or a terminal program running?)")
    if code in (errno.ENXIO, errno.ENODEV, errno.EIO):
        return (f"serial port {url} exists but has no device behind it (unplugged, or a pty whose "
                f"other end is closed): {text}")
    if "refused" in text.lower() or "timed out" in text.lower():
        return f"cannot connect to {url}: {text}; is the server listening on that host and port?"
    return f"cannot open serial port {url}: {text}"


#: The URL schemes open_port() takes, and whether the scheme needs HOST:PORT.
_URL_SCHEMES = {"loop": False, "socket": True, "rfc2217": True}


def check_port_url(url: str) -> None:
    """A port as :func:`open_port` takes it, checked without opening it: a device path, or a
    URL of a scheme it knows, with HOST:PORT where the scheme needs them.  Raises
    :class:`UriError` saying what to give."""
    if not isinstance(url, str) or not url.strip():
        raise UriError(f"serial port {url!r}: give {', '.join(SCHEMES)}")
    if "://" not in url:
        return
    scheme = url.split("://", 1)[0].lower()
    if scheme not in _URL_SCHEMES:
        raise UriError(f"serial port {url}: unknown scheme {scheme!r}; use {', '.join(SCHEMES)}")
    if _URL_SCHEMES[scheme]:
        parts = urllib.parse.urlsplit(url)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None or port == 0:
            raise UriError(f"serial port {url}: {scheme}:// needs HOST:PORT (a port in 1..65535), "
                           f"e.g. {scheme}://192.168.1.20:4001")


def open_port(url: str, baudrate: int = 115200, timeout: float | None = 0.02,
              **options: Any) -> serial.SerialBase:
    """Open ``url`` (path or pyserial URL) at ``baudrate``, 8N1, raw; reads wait <= ``timeout`` s.

    Device paths are locked exclusively (two processes on one port garble each other).  Extra
    ``options`` go to pyserial (``write_timeout``, ``rtscts``...).  Raises PortError / UriError.
    """
    check_port_url(url)
    if "://" not in url:
        options.setdefault("exclusive", True)
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, **options)
    except ValueError as exc:
        raise PortError(f"serial port {url}: {exc} (check --baud and the port options)") from exc
    except (serial.SerialException, OSError) as exc:
        raise PortError(_explain(url, exc)) from exc


class ReopeningPort:
    """A port that reopens itself after it vanished, with backoff (``backoff`` s, doubling).

    ``read`` returns ``b""`` and ``write`` drops the bytes while the port is away (the link's
    retries and heartbeats cover the gap); ``connected`` and ``last_error`` (a PortError with an
    actionable message) say how it is; ``on_change(connected, error)`` is called on each change.
    ``wait=False`` makes the first open raise PortError instead of retrying.  A write the peer
    takes no room for within ``write_timeout`` s drops what did not fit (``full_writes``
    counts them) and the next write starts with a lone 0x00, which ends the cut frame
    (docs/protocol.md 3): the port is there, its reader is not keeping up.
    """

    def __init__(self, url: str, baudrate: int = 115200, timeout: float = 0.02, *,
                 backoff: tuple[float, float] = (0.1, 2.0), wait: bool = True,
                 write_timeout: float = WRITE_TIMEOUT_S,
                 opener: Callable[..., Any] = open_port,
                 on_change: Callable[[bool, PortError | None], None] | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.url, self.baudrate, self.timeout = url, baudrate, timeout
        self.write_timeout = write_timeout
        self.backoff = backoff
        self.on_change = on_change
        self._opener, self._clock, self._sleep = opener, clock, sleep
        self._port: Any = None
        self._wait = Backoff(*backoff)
        self._retry_at = 0.0
        self.last_error: PortError | None = None
        self.opens = 0
        self.losses = 0
        self.dropped_bytes = 0
        self.full_writes = 0
        self._cut = False  # the last write was cut short: start the next with 0x00
        if not wait:
            self._port = self._open()
            self.opens = 1
        else:
            self._try_open()

    @property
    def connected(self) -> bool:
        """True while the underlying port is open."""
        return self._port is not None

    def _try_open(self) -> bool:
        now = self._clock()
        if now < self._retry_at:
            return False
        try:
            self._port = self._open()
        except PortError as exc:
            self.last_error = exc
            self._retry_at = now + self._wait.next()
            return False
        self.opens += 1
        self._wait.reset()
        self.last_error = None
        if self.on_change:
            self.on_change(True, None)
        return True

    def _open(self) -> Any:
        return self._opener(self.url, self.baudrate, self.timeout,
                            write_timeout=self.write_timeout)

    def _lost(self, exc: BaseException) -> None:
        port, self._port = self._port, None
        try:
            port.close()
        except Exception:  # noqa: BLE001 - the device is gone; closing may fail any way it likes
            pass
        self.losses += 1
        what = "the network and the bridge" if "://" in self.url else "the USB cable and adapter"
        self.last_error = PortError(
            f"serial port {self.url} vanished ({exc}); reopening every {self.backoff[1]:g} s at "
            f"most: check {what}")
        self._retry_at = self._clock() + self._wait.current
        if self.on_change:
            self.on_change(False, self.last_error)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most the timeout; b"" while the port is away."""
        if self._port is None and not self._try_open():
            self._sleep(max(0.0, min(self.timeout, self._retry_at - self._clock())))
            return b""
        try:
            return self._port.read(size)
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            return b""

    def write(self, data: bytes) -> int:
        """Write ``data``; while the port is away, or the peer takes no bytes for
        ``write_timeout`` s, the bytes are dropped (and counted)."""
        if self._port is None and not self._try_open():
            self.dropped_bytes += len(data)
            return 0
        if self._cut:
            data = b"\x00" + data
        try:
            written = self._port.write(data) or 0
            self._cut = False
            return written
        except serial.SerialTimeoutException:
            self.full_writes += 1
            self.dropped_bytes += len(data)
            self._cut = True
            if self.full_writes in (1, 10) or self.full_writes % 1000 == 0:
                log.warning("serial port %s takes no bytes: a write waited %g s for room "
                            "(%d such writes, %d bytes dropped): is the other end reading?",
                            self.url, self.write_timeout, self.full_writes, self.dropped_bytes)
            return 0
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            self.dropped_bytes += len(data)
            return 0

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read (0 while the port is away)."""
        if self._port is None:
            return 0
        try:
            return self._port.in_waiting
        except (serial.SerialException, OSError) as exc:
            self._lost(exc)
            return 0

    def fileno(self) -> int:
        """The open port's descriptor, for select(); OSError while it is away."""
        if self._port is None:
            raise OSError(errno.ENODEV, f"serial port {self.url} is not open")
        return self._port.fileno()

    def close(self) -> None:
        """Close for good (no reopening after this)."""
        port, self._port = self._port, None
        self._retry_at = float("inf")
        if port is not None:
            port.close()

    def __enter__(self) -> ReopeningPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FdPort:
    """A raw, non-blocking file descriptor as a port: the master end of a pseudo-terminal pair
    (``os.openpty()``), as the demo, the benchmarks and the tests hand one end of a pty to the
    simulated base while the daemon opens the other end by its path.

    Offers what the link runner uses: ``read(n)`` (``b""`` when nothing is waiting, or once
    the other end has closed), ``write(data)`` (bytes written; 0 when the pty buffer is full),
    ``in_waiting`` and ``fileno()``.  The caller owns the descriptor and closes it.
    """

    #: Upper bound of one read; the runner waits on fileno() before it reads.
    in_waiting = 4096

    def __init__(self, fd: int) -> None:
        self.fd = fd
        os.set_blocking(fd, False)

    def fileno(self) -> int:
        return self.fd

    def read(self, n: int) -> bytes:
        try:
            return os.read(self.fd, n)
        except (BlockingIOError, OSError):  # OSError (EIO): the other end has gone
            return b""

    def write(self, data: bytes) -> int:
        try:
            return os.write(self.fd, data)
        except BlockingIOError:
            return 0
