"""sd_notify(3) in pure Python: tell systemd the daemon is ready, alive, busy or stopping.

    systemd.extend_timeout(120)        # still compiling numba kernels
    systemd.ready(status="watching")   # READY=1 once the kernels are compiled or loaded
    interval = systemd.watchdog_interval()   # seconds between WATCHDOG=1, or None
    systemd.watchdog()                 # from the frame loop, every `interval` seconds
    systemd.stopping()                 # on SIGTERM

Messages are datagrams of ``KEY=value`` lines sent to the unix socket named by
``$NOTIFY_SOCKET`` (a path, or ``@name`` in the abstract namespace).  Without that variable
(not started by systemd, or a unit that is not Type=notify) every call is a no-op that
returns False, so the daemon runs the same way from a terminal or a test.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import time

from robot_change import validate
from robot_change.errors import InputError

__all__ = [
    "extend_timeout",
    "notify",
    "ready",
    "reloading",
    "status",
    "stopping",
    "watchdog",
    "watchdog_interval",
]

log = logging.getLogger(__name__)

_KEY = re.compile(r"[A-Z][A-Z0-9_]*\Z")


def _address(value: str) -> str | bytes | None:
    """The socket address $NOTIFY_SOCKET names, or None for a form this module cannot use."""
    if value.startswith("/"):
        return value
    if value.startswith("@") and len(value) > 1:
        return b"\0" + value[1:].encode()  # abstract namespace: a leading NUL byte
    return None


def notify(**fields: object) -> bool:
    """Send ``KEY=value`` lines to systemd, e.g. ``notify(READY=1, STATUS="watching")``.

    Keys are upper-cased; ``True``/``False`` become 1/0.  Returns True when the message was
    sent, False without ``$NOTIFY_SOCKET`` or when sending failed (logged: a daemon must not
    die because its supervisor's socket is gone).  Raises InputError for an empty call, a
    key that is not ``[A-Z][A-Z0-9_]*`` or a value with a newline (it would end the field).
    """
    if not fields:
        raise InputError("notify() needs at least one field, e.g. READY=1")
    lines = []
    for key, value in fields.items():
        key = key.upper()
        if not _KEY.match(key):
            raise InputError(f"notify field {key!r}: keys are upper-case letters, digits and '_'")
        if isinstance(value, bool):
            value = int(value)
        text = str(value)
        if "\n" in text or "\0" in text:
            raise InputError(f"notify field {key}={text!r}: a value cannot hold a newline or NUL")
        lines.append(f"{key}={text}")
    target = os.environ.get("NOTIFY_SOCKET", "")
    if not target:
        return False
    address = _address(target)
    if address is None:
        log.warning("NOTIFY_SOCKET=%r: not a path or @abstract name; systemd is not told",
                    target)
        return False
    message = ("\n".join(lines) + "\n").encode("utf-8")
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            # never block the daemon on a manager that does not read its socket
            sock.sendto(message, socket.MSG_DONTWAIT, address)
    except OSError as exc:
        log.warning("sd_notify to %s failed: %s", target, exc)
        return False
    return True


def ready(status: str | None = None) -> bool:
    """READY=1 (with an optional STATUS=): start-up is done, systemd starts the dependents."""
    if status is None:
        return notify(READY=1)
    return notify(READY=1, STATUS=_one_line(status))


def reloading() -> bool:
    """RELOADING=1 with MONOTONIC_USEC (systemd >= 253 checks it); send :func:`ready` after."""
    return notify(RELOADING=1, MONOTONIC_USEC=time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000)


def watchdog() -> bool:
    """WATCHDOG=1: the daemon is alive (send every :func:`watchdog_interval` seconds)."""
    return notify(WATCHDOG=1)


def status(text: str) -> bool:
    """STATUS=text, shown by ``systemctl status`` (newlines become spaces)."""
    return notify(STATUS=_one_line(text))


def stopping() -> bool:
    """STOPPING=1: the daemon is shutting down cleanly."""
    return notify(STOPPING=1)


def extend_timeout(seconds: float) -> bool:
    """EXTEND_TIMEOUT_USEC: ask for ``seconds`` more of the start (or stop) timeout, e.g.
    while numba compiles its kernels on a cold cache."""
    seconds = validate.positive("extend_timeout", "seconds", seconds, unit=" seconds")
    return notify(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))


def watchdog_interval() -> float | None:
    """Seconds between two :func:`watchdog` calls: half of ``$WATCHDOG_USEC``.

    None when systemd runs no watchdog for this process: the variable is unset, not a
    positive integer, or ``$WATCHDOG_PID`` names another process (a child that inherited
    the environment).
    """
    usec = os.environ.get("WATCHDOG_USEC", "")
    if not usec.isdigit() or int(usec) <= 0:
        return None
    pid = os.environ.get("WATCHDOG_PID", "")
    if pid and (not pid.isdigit() or int(pid) != os.getpid()):
        return None
    return int(usec) / 2e6


def _one_line(text: str) -> str:
    return " ".join(str(text).splitlines()).replace("\0", " ")
