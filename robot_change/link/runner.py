"""Pumps a sans-IO :class:`~robot_change.link.session.Link` over a real byte port: the lock
for other threads, the wait for bytes (select or the port's read timeout), port failures as
events.

Part of :mod:`robot_change.link.session`, which re-exports :class:`LinkRunner`.
"""

from __future__ import annotations

import select
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from robot_change.link.port import BytePort
from robot_change.link.protocol import Message
from robot_change.link.session_types import Event, PortProblem

if TYPE_CHECKING:  # only an annotation: session imports this module, not the other way round
    from robot_change.link.session import Link


class LinkRunner:
    """Pumps a :class:`Link` over a byte port: ``step()`` writes, waits (select or the port's read
    timeout), reads, and returns the link's events.  ``send``/``set_heartbeat`` may be called from
    another thread; the Link itself is only touched under a lock.

    ``port`` is a pyserial port (``hw.serial_port.open_port``), a ``hw.serial_port.ReopeningPort``,
    or anything with ``read(n)``, ``write(b)`` and ``in_waiting``.
    """

    def __init__(self, link: Link, port: BytePort, *, max_wait: float = 0.01) -> None:
        self.link = link
        self.port = port
        self.max_wait = max_wait
        self._lock = threading.Lock()
        self._port_up = True

    def send(self, message: Message, *, coalesce: Any = None) -> int:
        """Thread-safe :meth:`Link.send`."""
        with self._lock:
            return self.link.send(message, coalesce=coalesce)

    def set_heartbeat(self, message: Message) -> None:
        """Thread-safe :meth:`Link.set_heartbeat`."""
        with self._lock:
            self.link.set_heartbeat(message)

    def step(self, max_wait: float | None = None) -> list[Event]:
        """One turn: timers, write, wait for bytes (at most ``max_wait`` s), read, events."""
        max_wait = self.max_wait if max_wait is None else max_wait
        with self._lock:
            self.link.poll()
            out = self.link.outgoing()
            wait = min(max_wait, max(0.0, self.link.next_deadline() - self.link.clock()))
        problems: list[Event] = []
        self._io(self._write, out, problems)
        data = self._io(self._read, wait, problems) or b""
        with self._lock:
            if data:
                self.link.receive(data)
            self.link.poll()
            out = self.link.outgoing()
            events: list[Event] = self.link.events()
        self._io(self._write, out, problems)
        return problems + events

    def run(self, stop: threading.Event, handle: Callable[[Event], None]) -> None:
        """Step until ``stop`` is set, handing every event to ``handle``."""
        while not stop.is_set():
            for event in self.step():
                handle(event)

    def _io(self, fn: Callable[[Any], Any], arg: Any, problems: list[Event]) -> Any:
        try:
            result = fn(arg)
        except OSError as exc:  # serial.SerialException and hw.errors.PortError are OSErrors
            self._port_state(False, str(exc), problems)
            time.sleep(self.max_wait)
            return None
        connected = getattr(self.port, "connected", True)  # hw.serial_port.ReopeningPort has it
        detail = str(getattr(self.port, "last_error", "") or "") if not connected else "port open"
        self._port_state(bool(connected), detail, problems)
        return result

    def _port_state(self, up: bool, detail: str, problems: list[Event]) -> None:
        if up != self._port_up:
            self._port_up = up
            problems.append(PortProblem(up, detail))

    def _write(self, data: bytes) -> None:
        if data:
            self.port.write(data)

    def _read(self, wait: float) -> bytes:
        try:
            fd = self.port.fileno()
        except (AttributeError, OSError, ValueError):
            fd = None
        if fd is not None:
            ready, _, _ = select.select([fd], [], [], wait)
            if not ready:
                return b""
        return self.port.read(max(1, self.port.in_waiting))
