"""The daemon's views of its CHECKs for Foxglove ([viz] in the configuration): an MCAP file per
check in ``<state_dir>/reports/checks/`` (the newest ``keep_checks`` kept) and, with
``live = true``, a Foxglove WebSocket server on ``live_host:live_port``.

The answers to the base come first: the service hands a check over (:meth:`CheckViews.submit`,
which never blocks) once its PAUSE / CHECK_RESULT / CHANGE_REPORT are queued for the link, and
a worker thread of its own makes the messages (robot_change.export.foxglove), publishes them
live and writes the file.  A check that finds the worker still busy with two others is not
drawn (counted, logged).  Nothing here can stop the service: without foxglove-sdk, a full
disk or any failure, the view is skipped with a warning in the log.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import queue
import re
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from robot_change.change.mount import CameraMount
from robot_change.change.results import ChangeSet
from robot_change.errors import InputError
from robot_change.service.config import VizConfig

__all__ = ["CheckView", "CheckViews", "check_file_name", "prune_checks"]

log = logging.getLogger(__name__)

#: ``20261203T101500.123456Z-office.mcap``: UTC time of the check, then the station; names sort
#: as the checks came.
_CHECK_FILE = re.compile(r"\d{8}T\d{6}\.\d{6}Z-[A-Za-z0-9_-]+\.mcap\Z")
#: Checks that may wait for the worker (beyond these, a check is not drawn).
QUEUED_VIEWS = 2
#: The logger foxglove-sdk's MCAP writer reports failed writes to.
_SDK_WRITE_LOG = "foxglove.log_sink_set"


def _after_the_first_failure(record: logging.LogRecord) -> bool:
    """False for foxglove-sdk's lines about writes it refused after the first failed one (a
    full disk gave 13 of them per file: the first, and the view's own warning, tell it)."""
    return "AttemptedWriteAfterFailure" not in record.getMessage()


@dataclasses.dataclass(frozen=True, eq=False)
class CheckView:
    """What the view of one CHECK is made from: the station, its reference (a SceneModel), the
    fused current depth (H, W) uint16 mm, the ChangeSet, the camera's mounting and the check's
    time (ns since the epoch)."""

    station: str
    reference: Any
    depth: np.ndarray
    changes: ChangeSet
    mount: CameraMount
    stamp_ns: int

    def report(self) -> dict:
        """The JSON report: what ``<station>.last-check.json`` holds."""
        return {**self.changes.summary(self.mount), "station": self.station}


def check_file_name(station: str, stamp_ns: int) -> str:
    """The MCAP file name of a check of ``station`` at ``stamp_ns`` (module docstring)."""
    seconds, ns = divmod(int(stamp_ns), 1_000_000_000)
    utc = time.strftime("%Y%m%dT%H%M%S", time.gmtime(seconds))
    return f"{utc}.{ns // 1000:06d}Z-{station}.mcap"


def prune_checks(folder: Path, keep: int, now_ns: int | None = None) -> list[Path]:
    """Delete all but the newest ``keep`` check files in ``folder`` (only files named by
    :func:`check_file_name`); returns what was deleted.  A file named more than a minute after
    ``now_ns`` (the wall clock's now by default) was written before the clock was set back:
    the oldest, not the newest (it would outlive every check written since)."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    ahead = check_file_name("", now_ns + 60_000_000_000)[:-len("-.mcap")]
    files = sorted((p for p in folder.iterdir() if _CHECK_FILE.match(p.name)),
                   key=lambda p: (p.name[:len(ahead)] <= ahead, p.name))
    gone = files[:max(0, len(files) - keep)]
    for path in gone:
        path.unlink(missing_ok=True)
    return gone


class CheckViews:
    """The [viz] part of the service (module docstring).  :meth:`start`, :meth:`submit` per
    CHECK, :meth:`close`.  ``folder``: where the MCAP files go (None: no files);
    ``counters``: the service's (``views_written``, ``views_skipped``, ``views_failed``)."""

    def __init__(self, viz: VizConfig, folder: Path | None,
                 counters: collections.Counter | None = None) -> None:
        self.viz = viz
        self.folder = folder if viz.keep_checks > 0 else None
        self.counters = counters if counters is not None else collections.Counter()
        self.live: Any = None
        #: the last view written: path, bytes, ms (messages, live, file), or {} before any
        self.last: dict[str, Any] = {}
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUED_VIEWS)
        self._thread: threading.Thread | None = None
        self._writer: Any = None

    @property
    def enabled(self) -> bool:
        """Something to do: files to write or a live view to feed."""
        return self._thread is not None

    def start(self) -> None:
        """Check that foxglove-sdk is there (the service's start has removed the temp files an
        interrupted write left in the folder), start the live server (when asked) and the
        worker.  Never raises: what cannot be done is logged and left out."""
        if self.folder is None and not self.viz.live:
            return
        try:
            from robot_change.export.foxglove import sdk

            sdk()
        except InputError as exc:
            log.warning("check views for Foxglove skipped: %s", exc)
            return
        if self.folder is not None:
            sdk_log = logging.getLogger(_SDK_WRITE_LOG)
            if _after_the_first_failure not in sdk_log.filters:
                sdk_log.addFilter(_after_the_first_failure)
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                log.warning("check files skipped: cannot use the folder %s (%s)", self.folder,
                            exc)
                self.folder = None
        if self.viz.live:
            self._start_live()
        if self.folder is None and self.live is None:
            return
        self._thread = threading.Thread(target=self._main, name="rc-views", daemon=True)
        self._thread.start()

    def _start_live(self) -> None:
        from robot_change.export.live import LiveView

        try:
            self.live = LiveView(self.viz.live_host, self.viz.live_port)
        except Exception as exc:  # noqa: BLE001 -- a view never stops the service
            log.error("live view not started on %s:%d: %s", self.viz.live_host,
                      self.viz.live_port, exc)
            return
        log.info("live view for Foxglove on ws://%s:%d", self.live.host, self.live.port)

    def submit(self, view: CheckView) -> None:
        """Queue a check for the worker; never blocks (a full queue skips it)."""
        if self._thread is None:
            return
        try:
            self._queue.put_nowait(view)
        except queue.Full:
            self.counters["views_skipped"] += 1
            log.warning("view of the check of %s skipped: %d still being drawn",
                        view.station, QUEUED_VIEWS)

    def close(self, timeout: float = 0.5) -> None:
        """Stop the worker (a file being written is left unfinished as a temp file, removed
        at the next start) and the live server, waiting at most ``timeout`` seconds."""
        if self._thread is not None:
            while True:  # drop what waits: the service is stopping
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    break
            try:
                self._queue.put_nowait(None)
            except queue.Full:
                pass
            self._thread.join(timeout)
        if self.live is not None:
            try:
                self.live.close()
            except Exception:  # noqa: BLE001
                log.warning("live view did not stop cleanly", exc_info=True)

    def _main(self) -> None:
        while True:
            view = self._queue.get()
            if view is None:
                return
            try:
                self._draw(view)
            except (OSError, RuntimeError) as exc:  # a full disk, a folder gone: no traceback
                self.counters["views_failed"] += 1
                log.warning("view of the check of %s not written: %s%s", view.station, exc,
                            self._free_space())
            except Exception:  # noqa: BLE001 -- a view never stops the service
                self.counters["views_failed"] += 1
                log.warning("view of the check of %s not written", view.station, exc_info=True)

    def _free_space(self) -> str:
        """", N MB free in FOLDER" (what a failed write most often lacks), or ""."""
        try:
            return f", {shutil.disk_usage(self.folder).free / 1e6:.1f} MB free in {self.folder}"
        except (OSError, TypeError):
            return ""

    def _draw(self, view: CheckView) -> None:
        from robot_change.export.foxglove import check_messages
        from robot_change.export.mcap import CheckFileWriter

        t0 = time.perf_counter()
        messages = check_messages(view.reference, view.depth, view.changes, view.mount,
                                  report=view.report(), stamp_ns=view.stamp_ns)
        t1 = time.perf_counter()
        if self.live is not None:
            try:
                self.live.publish(messages, view.stamp_ns)
            except Exception:  # noqa: BLE001 -- the file is still worth writing
                self.counters["views_failed"] += 1
                log.warning("check of %s not sent to the live view", view.station,
                            exc_info=True)
        t2 = time.perf_counter()
        done: dict[str, Any] = {"messages_ms": (t1 - t0) * 1e3, "live_ms": (t2 - t1) * 1e3}
        if self.folder is not None:
            if self._writer is None:
                self._writer = CheckFileWriter()
            path = self.folder / check_file_name(view.station, view.stamp_ns)
            size = self._writer.write(path, messages, view.stamp_ns,
                                      {"station": view.station, "outcome": view.changes.outcome})
            prune_checks(self.folder, self.viz.keep_checks)
            done.update(path=path, bytes=size, file_ms=(time.perf_counter() - t2) * 1e3)
            self.counters["views_written"] += 1
            log.info("check of %s written for Foxglove: %s (%.2f MB) in %.0f ms", view.station,
                     path, size / 1e6, (time.perf_counter() - t0) * 1e3)
        done["ms"] = (time.perf_counter() - t0) * 1e3
        self.last = done
