"""What the link needs of a serial port: the typing of ``LinkRunner(port=...)`` and
``Service(port=...)``.  A pyserial port, ``hw.serial_port.ReopeningPort`` and
``hw.serial_port.FdPort`` all fit; ``fileno`` is optional (without it the link polls)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

__all__ = ["BytePort"]


@runtime_checkable
class BytePort(Protocol):
    """A byte stream to the other end: ``write`` all of ``data``; ``read`` at most ``size``
    bytes, waiting at most the port's timeout (b"" when none came); ``in_waiting`` bytes that
    can be read without waiting."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...
