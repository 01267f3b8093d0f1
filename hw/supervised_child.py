"""The reader process's side of :mod:`hw.supervised`: a backend's :class:`FrameFeed` (its
camera or recording) served into the parent's shared-memory ring.

Messages to the parent: ``("ready", info)``, ``("frame", slot, index, timestamp_us)``,
``("end",)``, ``("lost", text)``, ``("error", kind, text)``, ``("devices", list)``.  From the
parent: ``("shm", name, slots)``, ``("free", slot)``, ``("stop",)``, ``("simulate_loss",)``.
A recording is served in lockstep (a frame only into a free slot); a live camera's frames are
dropped while the parent is behind (it counts them from the gaps in the indices).
"""

from __future__ import annotations

import abc
import contextlib
import mmap
import multiprocessing.connection
import os
import signal
import time
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["ChildFailure", "FrameFeed", "reader_main"]


class ChildFailure(Exception):
    """Raised in the reader: ``kind`` ``not_found``, ``file``, ``backend`` or ``internal``."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind, self.text = kind, text


class FrameFeed(abc.ABC):
    """A backend's camera or recording, inside the reader process."""

    #: a recording (lockstep, may end) rather than a live camera
    is_file: bool = False

    @abc.abstractmethod
    def open(self) -> dict[str, Any]:
        """Open it; the info for the parent: ``width``, ``height``, ``fps``, ``frames`` (a
        recording's count, 0 unknown) and what the backend's source needs (intrinsics, uri,
        name, serial, ``mode_note``).  Raises :class:`ChildFailure`."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start streaming."""

    @abc.abstractmethod
    def next_frame(self, timeout: float) -> tuple[np.ndarray, int, int] | None:
        """The next frame within ``timeout`` s: ((H, W) uint16 mm, valid until the next call;
        frame index; timestamp µs), or ``None``."""

    @abc.abstractmethod
    def simulate_loss(self) -> None:
        """Test hook: stop the stream as an unplugged camera would."""

    @abc.abstractmethod
    def shutdown(self) -> None:
        """Release the camera (a recording may be left to the OS)."""


class _ChildExit(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def reader_main(conn: multiprocessing.connection.Connection, spec: dict[str, Any],
                make_feed: Callable[[dict[str, Any]], FrameFeed],
                list_devices: Callable[[dict[str, Any]], list[dict[str, Any]]]) -> None:
    """Entry point of a reader process.  Messages to the parent: ``("ready", info)``,
    ``("frame", slot, index, timestamp_us)``, ``("end",)``, ``("lost", text)``,
    ``("error", kind, text)``, ``("devices", list)``.  From the parent: ``("shm", name, slots)``,
    ``("free", slot)``, ``("stop",)``, ``("simulate_loss",)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's business
    try:
        if spec["kind"] == "list":
            conn.send(("devices", list_devices(spec)))
            os._exit(0)
        _Server(conn, spec, make_feed(spec)).run()
    except ChildFailure as failure:
        with contextlib.suppress(Exception):
            conn.send(("error", failure.kind, failure.text))
        os._exit(3 if failure.kind == "backend" else 2)
    except _ChildExit as done:
        os._exit(done.code)
    except Exception as exc:  # noqa: BLE001 -- report, then leave without native teardown
        with contextlib.suppress(Exception):
            conn.send(("error", "internal", f"{spec.get('library', 'the')} reader failed: "
                                            f"{type(exc).__name__}: {exc}"))
        os._exit(4)
    os._exit(0)


def _attach_ring(name: str, size: int) -> mmap.mmap:
    """The parent's shared-memory ring, mapped without multiprocessing's resource tracker (which
    in a process not started by multiprocessing would unlink the parent's segment at exit)."""
    fd = os.open(os.path.join("/dev/shm", name.lstrip("/")), os.O_RDWR)
    try:
        return mmap.mmap(fd, size)
    finally:
        os.close(fd)


class _Server:
    """Opens the feed, then moves its frames into the shared ring while free slots last."""

    def __init__(self, conn: multiprocessing.connection.Connection, spec: dict[str, Any],
                 feed: FrameFeed) -> None:
        self.conn, self.spec, self.feed = conn, spec, feed
        self.free: set[int] = set()
        self.ring: np.ndarray | None = None

    def run(self) -> None:
        info = self.feed.open()
        self.conn.send(("ready", info))
        msg = self.conn.recv()
        if msg[0] != "shm":
            raise _ChildExit(0)
        _, name, slots = msg
        self.width, self.height = int(info["width"]), int(info["height"])
        self.shm = _attach_ring(name, slots * self.height * self.width * 2)
        self.ring = np.ndarray((slots, self.height, self.width), dtype=np.uint16,
                               buffer=self.shm)
        self.free = set(range(slots))
        self.frames_total = int(info.get("frames") or self.spec.get("frames") or 0)
        self.frame_us = round(1e6 / max(float(info.get("fps") or 30), 1.0))
        self.feed.start()
        self._loop()

    def _handle(self, msg: tuple) -> None:
        if msg[0] == "free":
            self.free.add(msg[1])
        elif msg[0] == "stop":
            self.feed.shutdown()
            raise _ChildExit(0)
        elif msg[0] == "simulate_loss":
            self.feed.simulate_loss()

    def _drain(self, wait: float = 0.0) -> None:
        if self.conn.poll(wait):
            while True:
                self._handle(self.conn.recv())
                if not self.conn.poll(0):
                    break

    def _loop(self) -> None:
        is_file = self.feed.is_file
        skip = int(self.spec.get("skip", 0))  # frames a previous reader already delivered
        loop = bool(self.spec.get("loop")) and is_file
        first_us = last_us = 0  # the first lap's first and last timestamps
        played = 0
        silence_limit = float(self.spec["stall_timeout" if is_file else "lost_after"])
        # a camera may take a few seconds for its first frame
        last_frame = time.monotonic() + (0.0 if is_file else max(0.0, 5.0 - silence_limit))
        while True:
            self._drain(0.0 if (self.free or not is_file) else 0.1)
            if is_file and not self.free:
                last_frame = time.monotonic()  # waiting for the consumer is not a stall
                continue
            got = self.feed.next_frame(0.05)
            now = time.monotonic()
            if got is None:
                if now - last_frame > silence_limit:
                    if is_file:
                        raise ChildFailure("file", f"the {self.spec['library']} player delivered "
                                                   f"no frame for {silence_limit:.1f} s (the "
                                                   "recording may be corrupt)")
                    self.conn.send(("lost", f"the camera sent no frame for {silence_limit:.1f} "
                                            "s (unplugged or USB reset?)"))
                    raise _ChildExit(5)
                continue
            last_frame = now
            depth, index, stamp = got
            played += 1
            if loop and self.frames_total:  # later laps continue the count and the clock
                lap = (played - 1) // self.frames_total
                if lap == 0:
                    first_us = stamp if played == 1 else first_us
                    last_us = stamp
                lap_us = last_us - first_us + self.frame_us
                index, stamp = played, stamp + lap * lap_us
            if is_file and played <= skip:
                continue
            if not self.free:
                continue  # live camera, consumer behind: this frame is dropped
            if depth.shape != (self.height, self.width):
                raise ChildFailure("file" if is_file else "internal",
                                   f"frame {index} is {depth.shape[1]}x{depth.shape[0]}, "
                                   f"expected {self.width}x{self.height}")
            slot = self.free.pop()
            assert self.ring is not None
            self.ring[slot] = depth
            self.conn.send(("frame", slot, index, stamp))
            if is_file and not loop and self.frames_total and played >= self.frames_total:
                self.conn.send(("end",))
                while True:  # wait for "stop"; frees are irrelevant now
                    try:
                        msg = self.conn.recv()
                    except EOFError:
                        raise _ChildExit(0) from None
                    self._handle(msg)
