"""Depth frames from the camera to the controller: the camera thread and the bounded queue.

::

    camera    source.read() at camera rate -> FrameQueue (bounded, oldest dropped and counted);
              on loss: FAULT via the controller, close, reopen with backoff 0.5 s .. 10 s

Hysteresis, so a flaky source cannot make FAULT and CLEARED alternate: a reopened source counts
as delivering again (CLEARED) only after :data:`CAMERA_HEALTHY_FRAMES` good frames in a row, and
the back-off doubles with every loss until the source has stayed healthy for
:data:`CAMERA_STABLE_S`; so FAULT / CLEARED come at most once per back-off period.  A loss is
always reported at once.

Every frame the camera delivers is accounted for: ``received == processed + dropped +
queued`` (:meth:`FrameQueue.counts`).  A recording that ends counts as a lost camera (it is
reopened, so it plays again); ``oni:...?loop=1&rate=auto`` plays one like a camera.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from hw.backoff import Backoff
from hw.depth import DepthFrame, DepthSource
from hw.errors import DeviceLost, FrameTimeout, HwError
from robot_change import validate

__all__ = ["CAMERA_BACKOFF", "CAMERA_HEALTHY_FRAMES", "CAMERA_STABLE_S", "CameraThread",
           "FrameQueue"]

log = logging.getLogger(__name__)

#: Camera reopen backoff: first wait and cap, seconds.
CAMERA_BACKOFF = (0.5, 10.0)
#: Good frames in a row before a reopened source counts as delivering again.
CAMERA_HEALTHY_FRAMES = 5
#: Seconds a source must stay healthy before the back-off starts again from its first wait.
CAMERA_STABLE_S = 30.0


class FrameQueue:
    """A bounded queue of depth frames: ``put`` never blocks (a full queue drops its oldest
    frame and counts it), ``get`` waits at most its timeout.

    ``received == processed + dropped + len(queue)`` at every moment (:meth:`counts`).
    """

    def __init__(self, size: int = 4, on_put: Callable[[], None] | None = None) -> None:
        validate.whole("FrameQueue", "size", size, 1, 10_000)
        self._frames: collections.deque[tuple[DepthFrame, float, int]] = collections.deque()
        self._size = size
        self._cond = threading.Condition()
        self._on_put = on_put
        self.received = 0
        self.processed = 0
        self.dropped = 0

    def put(self, frame: DepthFrame) -> None:
        """Queue a frame with its arrival time and sequence number (``received`` so far: it
        keeps increasing when a reopened camera counts its frames from 0 again); drop the
        oldest when full."""
        with self._cond:
            if len(self._frames) >= self._size:
                self._frames.popleft()
                self.dropped += 1
            self._frames.append((frame, time.monotonic(), self.received))
            self.received += 1
            self._cond.notify_all()
        if self._on_put is not None:
            self._on_put()

    def get(self, timeout: float = 0.0) -> tuple[DepthFrame, float, int] | None:
        """The oldest (frame, arrival time, sequence number), waiting at most ``timeout`` s;
        None if none."""
        end = time.monotonic() + max(0.0, timeout)
        with self._cond:
            while not self._frames:
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            self.processed += 1
            return self._frames.popleft()

    def drain(self) -> list[tuple[DepthFrame, float, int]]:
        """Every queued frame, oldest first (all counted as processed)."""
        with self._cond:
            frames = list(self._frames)
            self._frames.clear()
            self.processed += len(frames)
            return frames

    def counts(self) -> dict[str, int]:
        """received, processed, dropped, queued: received == processed + dropped + queued."""
        with self._cond:
            return {"received": self.received, "processed": self.processed,
                    "dropped": self.dropped, "queued": len(self._frames)}


class CameraThread:
    """The camera thread of :class:`robot_change.service.core.Service`: open the source, read
    frames into ``frames``, reopen with back-off after a loss (module docstring).

    ``camera``: a DepthSource, or a function that makes one; ``read_timeout()``: seconds a read
    may take (the service's configuration, which a reload may change); ``progress``: stamped
    every turn (liveness); ``stop``: ends :meth:`run`; ``wake``: set when something the
    controller must tell the base happened.  The controller reads ``ok``, ``error``,
    ``losses``, ``uri`` and :meth:`fps`.
    """

    def __init__(self, camera: DepthSource | Callable[[], DepthSource], frames: FrameQueue,
                 progress: Any, stop: threading.Event, wake: threading.Event,
                 read_timeout: Callable[[], float]) -> None:
        self._camera = camera
        self._swap: DepthSource | Callable[[], DepthSource] | None = None
        self.frames, self.progress, self._stop, self._wake = frames, progress, stop, wake
        self._read_timeout = read_timeout
        self.ok = False
        self.error = ""
        self.losses = 0
        self.uri = ""
        #: the camera's model as its driver names it (None: the source names none)
        self.model: str | None = None
        self._arrivals: collections.deque[float] = collections.deque(maxlen=31)

    def swap(self, camera: DepthSource | Callable[[], DepthSource]) -> None:
        """Use ``camera`` from now on: the current source is closed and this one opened."""
        self._swap = camera

    def replace_factory(self, camera: DepthSource | Callable[[], DepthSource]) -> None:
        """The source to make at the next (re)open, without closing the current one."""
        self._camera = camera

    def fps(self) -> float:
        """Frames per second over the last second or so (0 when frames stopped)."""
        times = list(self._arrivals)
        if len(times) < 2 or time.monotonic() - times[-1] > 1.0:
            return 0.0
        span = times[-1] - times[0]
        return (len(times) - 1) / span if span > 0 else 0.0

    def _make_source(self) -> DepthSource:
        if self._swap is not None:
            self._camera, self._swap = self._swap, None
        cam = self._camera
        source = cam if isinstance(cam, DepthSource) else cam()
        source.open()
        self.uri = getattr(source, "uri", "") or type(source).__name__
        self.model = (getattr(source, "info", None) or {}).get("name") or None
        log.info("camera %s open%s", self.uri, f" ({self.model})" if self.model else "")
        return source

    def run(self) -> None:
        """The thread's loop, until ``stop``."""
        backoff = Backoff(*CAMERA_BACKOFF)
        source: DepthSource | None = None
        good = 0  # good frames in a row since the source was (re)opened
        healthy_since = 0.0
        try:
            while not self._stop.is_set():
                self.progress.beat("camera")
                if self._swap is not None and source is not None:
                    self._close_source(source)
                    source = None
                    backoff.reset()
                if source is None:
                    good = 0
                    try:
                        source = self._make_source()
                    except Exception as exc:  # noqa: BLE001 -- any failure to open is a lost camera
                        self._down(f"cannot open the camera: {exc}")
                        self._sleep(backoff.next())
                        continue
                try:
                    frame = source.read(timeout=self._read_timeout())
                except (FrameTimeout, DeviceLost, HwError, OSError) as exc:
                    why = str(exc)
                    frame = None
                else:
                    why = f"{getattr(source, 'uri', 'the recording')}: the recording ended"
                if frame is None:
                    self._down(why)
                    self._close_source(source)
                    source = None
                    self._sleep(backoff.next())
                    continue
                now = time.monotonic()
                self._arrivals.append(now)
                good += 1
                if not self.ok and (good >= CAMERA_HEALTHY_FRAMES or not self.error):
                    # healthy again (or, at start, the first frame: nothing had failed)
                    self.ok, self.error = True, ""
                    healthy_since = now
                    log.info("camera delivering frames (frame %d)", frame.index)
                    self._wake.set()
                if self.ok and now - healthy_since >= CAMERA_STABLE_S:
                    backoff.reset()  # stable: the next loss waits little again
                self.frames.put(frame)
        finally:
            if source is not None:
                self._close_source(source)

    def _down(self, why: str) -> None:
        if self.ok or not self.error:
            self.losses += 1
            log.error("camera lost: %s", why)
        elif why != self.error:  # another reason (a reload named another source): said too
            log.error("camera still lost, now: %s", why)
        self.ok, self.error = False, why
        self._wake.set()

    def _close_source(self, source: DepthSource) -> None:
        try:
            source.close()
        except Exception:  # noqa: BLE001 -- closing a lost device may fail any way it likes
            log.debug("closing the camera failed", exc_info=True)

    def _sleep(self, seconds: float) -> None:
        """Sleep in short steps, stamping progress (a back-off is not a stall)."""
        end = time.monotonic() + seconds
        while not self._stop.is_set() and self._swap is None:
            left = end - time.monotonic()
            if left <= 0:
                return
            self.progress.beat("camera")
            self._stop.wait(min(0.1, left))
