"""The fleet's on-disk spool: a bounded first-in first-out queue of MQTT messages that survives a
restart of the daemon (and a kill -9, and a power cut).

One file per message, ``<seq>.msg`` (12 digits, in order), holding the topic, a newline and the
payload, each written atomically (:mod:`hw.atomic`: a reader or a crash sees the whole file or
none).  A message leaves the spool when the broker has acknowledged it (QoS 1 PUBACK).  When a
new message would take the spool past ``max_bytes`` on the disk (each file counted in whole
blocks of the file system: a 900-byte message takes 4 KiB), the oldest ones are dropped and
counted;
the count (of messages: a report with a change is two, its check's and its change's) is kept
in ``dropped.count`` (atomically too), so it outlives restarts, and shows in the robot's
status; a drop is logged (at most once a minute).  A file that cannot be read back is moved
to ``bad/`` and counted, never sent and never deleted.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import threading
from pathlib import Path

from hw.atomic import remove_temp_files, write_atomically
from robot_change.throttle import Throttled

__all__ = ["Spool"]

log = logging.getLogger(__name__)

_NAME = re.compile(r"(\d{12})\.msg\Z")
_DROPPED = "dropped.count"


class Spool:
    """A bounded on-disk queue of (topic, payload) messages in ``folder`` (module docstring).

    Thread-safe: one writer appends while another thread reads and removes.  ``block_bytes``:
    the file system's block (its ``f_frsize`` by default).  Raises ``OSError`` when the folder
    cannot be made.
    """

    def __init__(self, folder: str | os.PathLike, max_bytes: int,
                 block_bytes: int | None = None) -> None:
        self.folder = Path(folder)
        self.max_bytes = int(max_bytes)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.block_bytes = max(1, int(block_bytes or os.statvfs(self.folder).f_frsize or 4096))
        self._lock = threading.Lock()
        self._throttled = Throttled(log, every=60.0)
        self._sizes: collections.OrderedDict[int, int] = collections.OrderedDict()
        self.bad = 0
        remove_temp_files(self.folder)  # an interrupted write: never a message
        found = []
        for path in self.folder.iterdir():
            match = _NAME.match(path.name)
            if match:
                found.append((int(match.group(1)), self._on_disk(path.stat().st_size)))
        for seq, size in sorted(found):
            self._sizes[seq] = size
        self._bytes = sum(self._sizes.values())
        self._next = (max(self._sizes) + 1) if self._sizes else 1
        self.dropped = self._read_dropped()

    # -- writing --------------------------------------------------------------------------------

    def append(self, topic: str, payload: bytes) -> int:
        """Keep a message; returns its sequence number (-1 when it is larger than the whole
        spool and was dropped).  The oldest messages make room (dropped and counted)."""
        data = topic.encode("utf-8") + b"\n" + payload
        size = self._on_disk(len(data))
        with self._lock:
            if size > self.max_bytes:
                self._count_dropped(1)
                log.warning("fleet spool: a message of %d bytes is larger than the spool "
                            "(%d bytes) and was dropped; raise fleet.spool_mb", len(data),
                            self.max_bytes)
                return -1
            victims = []
            while self._sizes and self._bytes + size > self.max_bytes:
                old, old_size = self._sizes.popitem(last=False)
                self._bytes -= old_size
                victims.append(old)
            seq = self._next
            self._next += 1
        for old in victims:
            self._path(old).unlink(missing_ok=True)
        if victims:
            with self._lock:
                self._count_dropped(len(victims))
                dropped = self.dropped
            self._throttled("full", logging.WARNING, "fleet spool: full (%d bytes): the oldest "
                            "%d message(s) dropped, %d in all; the broker is not taking them "
                            "(see the fleet's last error) or fleet.spool_mb is too small",
                            self.max_bytes, len(victims), dropped)
        write_atomically(self._path(seq), data)
        with self._lock:
            self._sizes[seq] = size
            self._bytes += size
        return seq

    def _on_disk(self, n: int) -> int:
        """Bytes a file of ``n`` bytes takes on the disk: whole blocks."""
        return -(-n // self.block_bytes) * self.block_bytes

    def remove(self, seq: int) -> None:
        """The broker has the message: forget it (a message dropped meanwhile is no error).  A
        file that cannot be deleted (a read-only disk) stays, counted, and is said (at most once
        a minute): it goes again after a restart."""
        with self._lock:
            if seq not in self._sizes:
                return
        try:
            self._path(seq).unlink(missing_ok=True)
        except OSError as exc:
            self._throttled("remove", logging.ERROR, "fleet spool: cannot delete %s, which the "
                            "broker has (%s); it stays, counted, and goes again after a "
                            "restart", self._path(seq), exc.strerror)
            return
        self._forget(seq)

    # -- reading --------------------------------------------------------------------------------

    def pending(self, after: int = 0, limit: int = 100) -> list[int]:
        """Up to ``limit`` sequence numbers greater than ``after``, oldest first."""
        with self._lock:
            out = []
            for seq in self._sizes:
                if seq > after:
                    out.append(seq)
                    if len(out) == limit:
                        break
            return out

    def read(self, seq: int) -> tuple[str, bytes] | None:
        """(topic, payload) of a message; None when it was dropped meanwhile, or when its file
        cannot be read back (then it is moved to ``bad/`` and counted)."""
        try:
            data = self._path(seq).read_bytes()
        except FileNotFoundError:
            self._forget(seq)
            return None
        except OSError as exc:
            self._quarantine(seq, f"unreadable ({exc.strerror})")
            return None
        topic, newline, payload = data.partition(b"\n")
        try:
            text = topic.decode("utf-8")
        except UnicodeDecodeError:
            text = ""
        if not newline or not text or "+" in text or "#" in text:
            self._quarantine(seq, "not a spooled message (topic line missing or invalid)")
            return None
        return text, payload

    def counts(self) -> dict[str, int]:
        """queued (messages), bytes (on the disk), max_bytes, dropped (ever, this spool),
        bad."""
        with self._lock:
            return {"queued": len(self._sizes), "bytes": self._bytes,
                    "max_bytes": self.max_bytes, "dropped": self.dropped, "bad": self.bad}

    def __len__(self) -> int:
        with self._lock:
            return len(self._sizes)

    # -- helpers --------------------------------------------------------------------------------

    def _path(self, seq: int) -> Path:
        return self.folder / f"{seq:012d}.msg"

    def _forget(self, seq: int) -> None:
        with self._lock:
            size = self._sizes.pop(seq, None)
            if size is not None:
                self._bytes -= size

    def _quarantine(self, seq: int, why: str) -> None:
        self._forget(seq)
        bad = self.folder / "bad"
        try:
            bad.mkdir(exist_ok=True)
            os.replace(self._path(seq), bad / self._path(seq).name)
        except OSError:
            pass
        with self._lock:
            self.bad += 1
        log.error("fleet spool: %s is %s; moved to %s (not sent)", self._path(seq).name, why,
                  bad)

    def _read_dropped(self) -> int:
        try:
            return max(0, int((self.folder / _DROPPED).read_text().strip()))
        except (OSError, ValueError):
            return 0

    def _count_dropped(self, n: int) -> None:
        """(under the lock)"""
        self.dropped += n
        try:
            write_atomically(self.folder / _DROPPED, f"{self.dropped}\n".encode())
        except OSError as exc:
            log.warning("fleet spool: cannot keep the dropped count in %s (%s)",
                        self.folder / _DROPPED, exc.strerror)
