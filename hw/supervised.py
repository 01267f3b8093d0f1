"""Depth read by a native library in a supervised child process: what the OpenNI2 and RealSense
backends share.

The native library runs in a **reader process** that hands frames to this process through a
shared-memory ring of a few frame slots and a control socket.  The reader is a fresh
interpreter started with :mod:`subprocess` (not multiprocessing, whose "spawn" re-imports the
caller's main module and dies when that is standard input, ``-c``, a notebook or an embedding
program): it is the same process whatever the caller is.  A crash, hang or deadlock inside the
native library therefore costs a restart of the reader, never the service:

* every :meth:`SupervisedSource.read` waits at most its timeout (:class:`FrameTimeout`);
* a reader that dies is seen at once (its pidfd, or its end of the socket closing), and what it
  wrote last on stderr is kept for the message; one that stops answering for
  ``stall_timeout`` seconds is killed.  Either way it is restarted (``stats.restarts``);
* a live camera that stops delivering frames for ``lost_after`` seconds, or whose reader died,
  raises :class:`DeviceLost` once; the following reads reconnect with exponential backoff
  (0.5 s doubling to 10 s) and raise :class:`DeviceLost` while the camera is still missing;
* a recording is resumed after a reader crash at the next frame (frames before it are skipped
  in the new reader, not delivered twice); a recording that crashes the reader three times
  without progress is reported as a corrupt file (:class:`DepthFileError`).

Recordings play frame by frame in lockstep: no frame is dropped however slow the consumer, and
``read`` returns ``None`` after the last one; ``loop=1`` plays one like a camera instead (again
from the start after the last frame, indices and timestamps increasing), ``rate=`` paces it.

A backend gives a :class:`FrameFeed` (what the reader process does: open, wait for a frame,
stop; :mod:`hw.supervised_child` serves it) and a :class:`SupervisedSource` subclass (how to
describe it, its intrinsics, its reader's spec); everything else is here.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import math
import multiprocessing.connection
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import weakref
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from hw.backoff import Backoff
from hw.depth import DepthFrame, DepthSource, Intrinsics
from hw.errors import (
    ArgumentError,
    BackendUnavailable,
    DepthFileError,
    DeviceError,
    DeviceLost,
    DeviceNotFound,
    FrameTimeout,
    HwError,
    UriError,
)
from hw.options import Pacer, flag, positive
from hw.supervised_child import ChildFailure, FrameFeed, reader_main

__all__ = ["ChildFailure", "FrameFeed", "ReaderProcess", "SupervisedSource", "ask_reader",
           "describe_exit", "reader_main", "source_options"]

log = logging.getLogger(__name__)


#: What the reader process runs: read sys.path and the spec from the socket, then the reader.
_BOOT = """\
import importlib, sys
from multiprocessing.connection import Connection
conn = Connection(int(sys.argv[1]))
path, spec = conn.recv()
sys.path[:0] = [p for p in path if p not in sys.path]
importlib.import_module(spec["module"]).reader_entry(conn, spec)
"""


class ReaderProcess:
    """A reader process: a fresh interpreter running ``reader_entry(conn, spec)`` of
    ``spec["module"]``, a connection to it, and what it wrote on stderr (kept in a temporary
    file, so a chatty driver never blocks it).  In its own session, so a Ctrl-C at the terminal
    goes to the caller, which stops it."""

    def __init__(self, spec: dict[str, Any]) -> None:
        ours, theirs = socket.socketpair()
        self._stderr = tempfile.TemporaryFile()
        try:
            self._popen = subprocess.Popen(
                [sys.executable, "-c", _BOOT, str(theirs.fileno())], pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr,
                start_new_session=True)
        except OSError as exc:
            self._stderr.close()
            ours.close()
            raise BackendUnavailable(f"cannot start the {spec.get('library')} reader "
                                     f"({sys.executable!r}: {exc.strerror or exc})") from None
        finally:
            theirs.close()
        self.pid = self._popen.pid
        self.conn = multiprocessing.connection.Connection(ours.detach())
        try:
            self._pidfd: int | None = os.pidfd_open(self.pid)
        except (AttributeError, OSError):  # not Linux >= 5.3: the socket closing tells
            self._pidfd = None
        # a reader outlives no caller that forgets to close its source
        self._finalizer = weakref.finalize(self, ReaderProcess._end, self._popen)
        self.conn.send((list(sys.path), spec))

    @staticmethod
    def _end(popen: subprocess.Popen) -> None:
        if popen.poll() is None:
            popen.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                popen.wait(2.0)

    def receive(self, timeout: float) -> tuple[tuple | None, bool]:
        """Wait up to ``timeout`` s: (message, False); (None, False) when nothing came; (None,
        True) when the reader died (its pidfd fired or the socket closed)."""
        waitables: list[Any] = [self.conn] + ([self._pidfd] if self._pidfd is not None else [])
        ready = multiprocessing.connection.wait(waitables, timeout)
        if self.conn in ready:
            try:
                return self.conn.recv(), False
            except (EOFError, OSError):
                pass
        return None, bool(ready)

    @property
    def exitcode(self) -> int | None:
        """Its exit status (negative: the signal that ended it); None while it runs."""
        return self._popen.poll()

    def join(self, timeout: float) -> None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._popen.wait(timeout)

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            self._popen.kill()

    def last_error(self) -> str:
        """The last line the reader wrote on stderr ("" when none)."""
        with contextlib.suppress(Exception):
            self._stderr.flush()
            self._stderr.seek(0, os.SEEK_END)
            size = self._stderr.tell()
            self._stderr.seek(max(0, size - 4096))
            lines = [line.strip() for line in
                     self._stderr.read().decode(errors="replace").splitlines() if line.strip()]
            return lines[-1][:300] if lines else ""
        return ""

    def describe_exit(self) -> str:
        """How it ended, with its last line on stderr when there is one."""
        self.join(0.5)
        how = describe_exit(self.exitcode)
        last = self.last_error()
        return f"{how} (its last error output: {last})" if last else how

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.close()
        if self._pidfd is not None:
            with contextlib.suppress(OSError):
                os.close(self._pidfd)
            self._pidfd = None
        with contextlib.suppress(Exception):
            self._stderr.close()
        self._finalizer.detach()

    def finish(self, timeout: float = 2.0) -> None:
        """Wait for it to end (kill it when it does not), then close."""
        self.join(timeout)
        if self.is_alive():
            self.kill()
            self.join(1.0)
        self.close()


def describe_exit(code: int | None) -> str:
    """How a reader with exit status ``code`` ended, in words."""
    if code is None:
        return "stopped answering"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"was killed by {name}"
    return f"exited with status {code}"


def ask_reader(spec: dict[str, Any], timeout: float, what: str) -> Any:
    """Run a reader for one answer (``kind: list``): the payload of its reply.  Raises
    :class:`DeviceError` when it hangs or dies, :class:`BackendUnavailable` when its library
    cannot be loaded."""
    proc = ReaderProcess(spec)
    try:
        msg, died = proc.receive(timeout)
        if msg is None and not died:
            raise DeviceError(f"{what} took more than {timeout:.0f} s (a driver hangs?)")
        if msg is None:
            raise DeviceError(f"the {spec['library']} reader {proc.describe_exit()} while {what}")
        if msg[0] == "error":
            raise BackendUnavailable(msg[2]) if msg[1] == "backend" else DeviceError(msg[2])
        return msg[1]
    finally:
        proc.finish()


# =================================================================================================
# the parent side
# =================================================================================================
class SupervisedSource(DepthSource):
    """A depth source read by a native library in a reader process (see the module).

    Options: ``slots`` (frames buffered ahead, default 4), ``start_timeout`` (s to open the
    device in the reader, 10), ``stall_timeout`` (s of silence from a reader before it is
    killed and restarted, 5), ``lost_after`` (s without a camera frame before the camera counts
    as lost, 2), ``max_restarts`` (reader crashes without progress before a recording counts as
    corrupt, 3).  Recordings only: ``loop`` (start again after the last frame, for ever; frame
    indices and timestamps keep increasing across laps, so a daemon fed by a recording runs like
    one fed by a camera) and ``rate`` (frames per second to pace delivery at, like a camera;
    ``"auto"`` for the recording's own fps; default: as fast as they are read).

    A backend sets ``library`` and ``reader_module`` (whose ``reader_entry(conn, spec)`` calls
    :func:`reader_main`) and implements :meth:`_check_file`, :meth:`_reader_spec`,
    :meth:`_intrinsics_from` and :meth:`_backend_hint`.
    """

    library = "native"
    reader_module = ""

    def __init__(self, kind: str, target: str, uri: str, *, slots: int = 4,
                 start_timeout: float = 10.0, stall_timeout: float = 5.0,
                 lost_after: float = 2.0, max_restarts: int = 3, loop: bool = False,
                 rate: float | str | None = None) -> None:
        super().__init__()
        if kind not in ("file", "device"):
            raise ArgumentError(f"kind must be 'file' or 'device', not {kind!r}")
        if kind != "file" and (loop or rate is not None):
            raise UriError("the loop and rate options are for recordings; a live camera runs at "
                           "its own rate")
        self.kind = kind
        self.target = target
        self.uri = uri
        self.slots = int(slots)
        self.start_timeout = float(start_timeout)
        self.stall_timeout = float(stall_timeout)
        self.lost_after = float(lost_after)
        self.max_restarts = int(max_restarts)
        if self.slots < 1 or min(self.start_timeout, self.stall_timeout, self.lost_after) <= 0:
            raise ArgumentError("slots must be >= 1 and the timeouts > 0")
        #: What the reader reported when it opened the source (uri, name, serial, mode, ...).
        self.info: dict[str, Any] = {}
        self._intrinsics: Intrinsics | None = None
        self._proc: ReaderProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._shm: shared_memory.SharedMemory | None = None
        self._ring: np.ndarray | None = None
        self._open = False
        self._ended = False
        self._last_index: int | None = None
        self._delivered = 0
        self._last_heard = 0.0
        self._restart_due: float | None = None  # live: when to try reconnecting
        self._backoff = Backoff(0.5, 10.0)
        self._failed_restarts = 0
        self.loop = bool(loop)
        if kind == "file":
            fps = self._check_file()
            if rate in ("auto", "fps"):
                rate = float(fps)
        if rate is not None and not (isinstance(rate, (int, float)) and math.isfinite(rate)
                                     and rate > 0):
            raise UriError(f"{self.library} option rate={rate!r}: frames per second > 0, or "
                           "'auto' for the recording's own fps")
        self.rate = None if rate is None else float(rate)
        self._pacer = Pacer(self.rate)

    # --- what a backend provides ---------------------------------------------------------------
    @abc.abstractmethod
    def _check_file(self) -> float:
        """Check the recording before the native player sees it (:class:`DepthFileError`);
        learn what is known without playing it; its fps."""

    @abc.abstractmethod
    def _reader_spec(self) -> dict[str, Any]:
        """The backend's part of the reader's spec (``frames`` and ``lap_us`` of a recording)."""

    @abc.abstractmethod
    def _intrinsics_from(self, info: dict[str, Any]) -> Intrinsics:
        """The frames' intrinsics from the reader's ``ready`` info."""

    @abc.abstractmethod
    def _backend_hint(self) -> str:
        """What to install when the library cannot be loaded."""

    # --- DepthSource ---------------------------------------------------------------------------
    @property
    def intrinsics(self) -> Intrinsics:
        """The frames' intrinsics: for a recording at once, for a camera once it is open."""
        if self._intrinsics is None:
            raise DeviceError(f"{self.uri}: open the camera before asking for its intrinsics")
        return self._intrinsics

    @property
    def pid(self) -> int | None:
        """Process id of the current reader (``None`` when none runs)."""
        return self._proc.pid if self._proc is not None else None

    def open(self) -> None:
        """Start the reader and open the camera or recording.  Raises :class:`DeviceNotFound`,
        :class:`DepthFileError` or :class:`BackendUnavailable` with what to do."""
        if self._open:
            return
        if self.kind == "file":
            self._check_file()
        self._ended = False
        self._last_index = None
        self._pacer.reset()
        self._delivered = 0  # frames of this opening (a restarted reader skips them)
        self._start_reader(skip=0)
        self._open = True

    def close(self) -> None:
        """Stop the reader and release the camera.  Safe to call more than once."""
        self._open = False
        self._stop_reader()
        if self._shm is not None:
            self._ring = None
            with contextlib.suppress(Exception):
                self._shm.close()
            with contextlib.suppress(Exception):
                self._shm.unlink()
            self._shm = None

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame, waiting at most ``timeout`` s (``None``: as long as it takes);
        ``None`` after a recording's last frame.

        Raises :class:`FrameTimeout` when no frame came in time, :class:`DeviceLost` when the
        camera (or its reader) is gone -- later reads reconnect -- and :class:`DepthFileError`
        when a recording cannot be played on.  A reader silent for ``stall_timeout`` s is
        killed: a recording's is replaced at once when ``timeout`` is ``None`` (else on the next
        read, after a :class:`FrameTimeout`); a camera's counts as a lost camera.
        """
        if not self._open:
            raise DeviceError(f"{self.uri}: the source is not open; use it in a 'with' block or "
                              "call open()")
        if self._ended:
            return None
        deadline = math.inf if timeout is None else time.monotonic() + max(0.0, float(timeout))
        self._pacer.wait(timeout, f"{self.uri} (option rate)")
        if self._proc is None:
            self._reconnect(deadline)
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            msg, died = self._receive(min(remaining, 0.25))
            if msg is not None:
                self._last_heard = time.monotonic()
                result = self._on_message(msg)
                if result is not None or self._ended:
                    return result
                continue
            if died:  # the reader died (sentinel fired or pipe closed)
                self._on_reader_death(self._describe_death())
                # a recording resumes in a new reader: give it a moment for the next frame
                deadline = max(deadline, time.monotonic() + 1.0)
                continue
            silent = time.monotonic() - self._last_heard
            if silent > self.stall_timeout:
                assert self._proc is not None
                why = f"(pid {self._proc.pid}) stopped answering for {silent:.1f} s"
                if self.kind == "file" and timeout is None:
                    self._on_reader_death(why)
                    continue
                self._stop_reader(kill=True)
                self._schedule_restart()
                if self.kind == "file":
                    raise FrameTimeout(f"{self.uri}: the {self.library} reader {why}; it was "
                                       "killed and will be restarted")
                raise DeviceLost(f"{self.uri}: the {self.library} reader {why}; it was killed, "
                                 "reconnecting")
            if time.monotonic() >= deadline:
                raise FrameTimeout(f"{self.uri}: no depth frame within {timeout:.2f} s")

    # --- test hooks ----------------------------------------------------------------------------
    def simulate_device_loss(self) -> None:
        """Make the reader stop the camera's stream, as if it had been unplugged (for tests of
        the recovery path)."""
        if self._conn is not None:
            self._conn.send(("simulate_loss",))

    # --- internals -----------------------------------------------------------------------------
    def _on_message(self, msg: tuple) -> DepthFrame | None:
        kind = msg[0]
        if kind == "frame":
            _, slot, index, stamp = msg
            assert self._ring is not None and self._conn is not None
            depth = self._ring[slot].copy()
            with contextlib.suppress(OSError):
                self._conn.send(("free", slot))
            if self._last_index is not None and index > self._last_index + 1:
                self.stats.dropped += index - self._last_index - 1
            self._last_index = index
            self._failed_restarts = 0
            self._delivered += 1
            self.stats.delivered += 1
            assert self._intrinsics is not None
            return DepthFrame(depth, int(stamp), int(index), self._intrinsics)
        if kind == "end":
            self._ended = True
            self._stop_reader()
            return None
        if kind == "lost":
            self._stop_reader(kill=True)
            self._schedule_restart()
            raise DeviceLost(f"{self.uri}: {msg[1]}; reconnecting")
        if kind == "error":
            self._stop_reader(kill=True)
            raise self._error(msg[1], msg[2])
        return None

    def _error(self, kind: str, text: str) -> HwError:
        if kind == "not_found":
            return DeviceNotFound(text)
        if kind == "file":
            return DepthFileError(text)
        if kind == "backend":
            return BackendUnavailable(f"{text}; {self._backend_hint()}")
        return DeviceError(f"{self.uri}: {text}")

    def _schedule_restart(self) -> None:
        self._restart_due = time.monotonic()

    def _describe_death(self) -> str:
        return self._proc.describe_exit() if self._proc is not None else describe_exit(None)

    def _on_reader_death(self, how: str) -> None:
        """The reader died or hung (``how``): a recording continues in a new reader, skipping
        the frames already delivered; a camera raises :class:`DeviceLost` and reconnects later."""
        self._stop_reader(kill=True)
        if self.kind == "file":
            self._failed_restarts += 1
            if self._failed_restarts > self.max_restarts:
                raise DepthFileError(
                    f"{self.uri}: the {self.library} player failed {self._failed_restarts} times "
                    f"after frame {self._last_index or 0} (its reader {how}); the recording is "
                    "probably corrupt (crashed player)")
            log.warning("%s: %s reader %s; restarting at frame %s", self.uri, self.library, how,
                        (self._last_index or 0) + 1)
            self.stats.restarts += 1
            self._start_reader(skip=self._delivered)
            return
        self._schedule_restart()
        raise DeviceLost(f"{self.uri}: the {self.library} reader {how}; reconnecting")

    def _reconnect(self, deadline: float) -> None:
        """Start a new reader after a loss (live: with backoff; file: at once)."""
        if self.kind == "file":
            self.stats.restarts += 1
            self._start_reader(skip=self._delivered)
            return
        due = self._restart_due if self._restart_due is not None else time.monotonic()
        wait = due - time.monotonic()
        if wait > 0:
            if wait > deadline - time.monotonic():
                time.sleep(max(0.0, deadline - time.monotonic()))
                raise DeviceLost(f"{self.uri}: camera lost; next reconnection attempt in "
                                 f"{max(0.0, due - time.monotonic()):.1f} s")
            time.sleep(wait)
        try:
            self._start_reader(skip=0)
        except (DeviceNotFound, DeviceError) as exc:
            self._restart_due = time.monotonic() + self._backoff.next()
            raise DeviceLost(f"{self.uri}: camera still missing ({exc}); next attempt in "
                             f"{self._restart_due - time.monotonic():.1f} s") from exc
        self.stats.restarts += 1
        self._backoff.reset()
        self._restart_due = None
        self._last_index = None  # a reconnected camera counts its frames from the start again

    def _start_reader(self, skip: int) -> None:
        """Start a reader process and wait until it has opened the source; ``skip``: frames of
        a recording to pass over (already delivered by a previous reader)."""
        spec = {"module": self.reader_module, "library": self.library, "kind": self.kind,
                "target": self.target, "skip": skip, "loop": self.loop,
                "stall_timeout": self.stall_timeout, "lost_after": self.lost_after,
                **self._reader_spec()}
        proc = ReaderProcess(spec)
        self._proc, self._conn = proc, proc.conn
        try:
            info = self._await_ready()
        except BaseException:
            self._stop_reader(kill=True)
            raise
        self.info = info
        width, height = int(info["width"]), int(info["height"])
        self._intrinsics = self._intrinsics_from(info)
        if info.get("mode_note"):
            log.warning("%s", info["mode_note"])
        need = self.slots * width * height * 2
        if self._shm is None or self._shm.size < need:
            if self._shm is not None:
                self._ring = None
                with contextlib.suppress(Exception):
                    self._shm.close()
                    self._shm.unlink()
            self._shm = shared_memory.SharedMemory(create=True, size=need)
        self._ring = np.ndarray((self.slots, height, width), dtype=np.uint16,
                                buffer=self._shm.buf)
        proc.conn.send(("shm", self._shm.name, self.slots))
        self._last_heard = time.monotonic()

    def _await_ready(self) -> dict[str, Any]:
        deadline = time.monotonic() + self.start_timeout
        what = "recording" if self.kind == "file" else "camera"
        while True:
            msg, died = self._receive(max(0.0, deadline - time.monotonic()))
            if msg is not None:
                if msg[0] == "ready":
                    return msg[1]
                if msg[0] == "error":
                    raise self._error(msg[1], msg[2])
                continue
            if died:
                assert self._proc is not None
                how = self._proc.describe_exit()
                if self.kind == "file":
                    raise DepthFileError(f"{self.uri}: the {self.library} player {how} while "
                                         "opening the recording (its header was checked and is "
                                         "valid)")
                raise DeviceError(f"{self.uri}: the {self.library} reader {how} while opening "
                                  "the camera")
            raise DeviceError(f"{self.uri}: the {self.library} reader did not open the {what} "
                              f"within {self.start_timeout:.0f} s")

    def _receive(self, timeout: float) -> tuple[tuple | None, bool]:
        assert self._proc is not None
        return self._proc.receive(timeout)

    def _stop_reader(self, kill: bool = False) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if conn is not None:
            if not kill:
                with contextlib.suppress(Exception):
                    conn.send(("stop",))
            with contextlib.suppress(Exception):
                conn.close()
        if proc is not None:
            if not kill:
                proc.join(1.0)
            if proc.is_alive():
                proc.kill()  # SIGKILL also ends a stopped (SIGSTOP) or hung reader
                proc.join(2.0)
            with contextlib.suppress(Exception):
                proc.close()


# =================================================================================================
# the options of a URI
# =================================================================================================
def source_options(backend: str, options: dict[str, Any],
                   extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The options of a :class:`SupervisedSource` from a URI's query (strings) or keyword
    arguments: ``slots``, ``start_timeout``, ``stall_timeout``, ``lost_after``,
    ``max_restarts``, ``loop``, ``rate``, and the backend's ``extra`` (name -> parser raising
    :class:`UriError`).  :class:`UriError` for an unknown option or a bad value."""
    numbers = {"slots": int, "start_timeout": float, "stall_timeout": float,
               "lost_after": float, "max_restarts": int}
    parsers = {"loop": lambda value: flag(backend, "loop", value),
               "rate": lambda value: _rate(backend, value), **(extra or {})}
    out = {}
    for key, value in options.items():
        if key in parsers:
            out[key] = parsers[key](value)
        elif key in numbers:
            try:
                out[key] = numbers[key](value)
            except (TypeError, ValueError):
                raise UriError(f"{backend} option {key}={value!r} must be a number") from None
        else:
            raise UriError(f"unknown {backend} option {key!r}; known: "
                           f"{', '.join(sorted([*numbers, *parsers]))}")
    return out


def _rate(backend: str, value: Any) -> float | str | None:
    if value is None or value == "":
        return None
    if isinstance(value, str) and value.strip().lower() in ("auto", "fps"):
        return "auto"
    return positive(backend, "rate", value, "frames per second, or 'auto' for the recording's "
                    "own fps")
