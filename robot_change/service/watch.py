"""WATCH: the per-frame depth gate, the detector threads and the persistence window.

WATCH checks the newest frame every ``check_interval_ms`` and at once when a cheap per-frame
depth gate (:func:`depth_gate`) sees the scene differ from what the last check saw, and raises
PAUSE when a change is seen in ``watch_m`` of the last ``watch_n`` checks (once per change:
CLEAR when ``watch_m`` of the last ``watch_n`` checks saw none, after which a new change pauses
again).  A watch checks only while the base's heartbeat says PARKED or PAUSED.  A check that
sees nothing to compare (no depth: covered lens, something against the camera) counts as a
change (PAUSE cause CAMERA_LOST), and so does a check that finds the robot no longer at its
station (pushed, or crept: FAULT and PAUSE NOT_AT_STATION), since it cannot watch from there.
Every check registers the view again, starting from the last check's estimate, so a robot
that creeps a few centimetres is followed.

::

    detector  <= 2 threads running WATCH checks (numba kernels release the GIL), so a change
              that shows while a scheduled check runs is checked at once, not after it
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import time
from typing import Any

import numpy as np

from hw.depth import DepthFrame
from robot_change.change import detect
from robot_change.errors import EmptySceneError, SceneMismatchError
from robot_change.link.protocol import FaultCode, ModuleState, Motion, PauseCause
from robot_change.service.params import change_params

__all__ = ["WatchMixin", "depth_gate"]

log = logging.getLogger(__name__)


def depth_gate(reference: np.ndarray, depth: np.ndarray, margin_m: float, margin_per_m2: float,
               step: int = 4) -> int:
    """How many sampled pixels (every ``step``-th of every ``step``-th row) read nearer or
    farther than the reference by more than the sensor's noise, ``margin_m + margin_per_m2 *
    z^2`` (the free-space check's margin: ChangeParams.free_space_margin_m / _per_m2).

    A cheap per-frame trigger for WATCH checks, never a decision: a jump in this count means the
    scene is no longer what the last check saw, so a check runs at once.  ~0.3 ms at VGA.
    """
    r = reference[::step, ::step].astype(np.float32)
    c = depth[::step, ::step].astype(np.float32)
    both = (r > 0) & (c > 0)
    margin = 1000.0 * margin_m + 1e-3 * margin_per_m2 * r * r  # mm, r in mm
    return int(np.count_nonzero(both & (np.abs(c - r) > margin)))


@dataclasses.dataclass
class _WatchJob:
    seq: int  # the frame's sequence number in the FrameQueue
    frame_index: int
    future: concurrent.futures.Future
    submitted: float


class _Watch:
    """What a WATCH keeps: the station's reference, the persistence window, jobs in flight."""

    def __init__(self, station: str, reference: Any, n: int,
                 gate_margin: tuple[float, float]) -> None:
        self.station = station
        self.reference = reference
        self.window: collections.deque[bool] = collections.deque(maxlen=n)
        self.jobs: list[_WatchJob] = []
        self.last_submitted = -1
        self.last_recorded = -1
        self.next_check = 0.0
        self.gate_baseline: int | None = None
        self.episode = False  # a change is being reported (PAUSE sent or report made)
        self.blind_reported = False
        self.error_reported = False
        self.checks = 0
        self.latest: DepthFrame | None = None
        self.latest_seq = -1
        self.latest_gate = 0
        self.pose: np.ndarray | None = None  # the last registration (T_ref_from_cur)
        self.off_station_reported = False
        self.gate_margin = gate_margin  # the check's free-space margin (m, per m^2)


class WatchMixin:
    """The WATCH of :class:`robot_change.service.core.Service`: started and ended by the controller,
    fed every frame (:meth:`_watch_frame`) and stepped every tick (:meth:`_watch_step`).

    Uses the service's state (``_watch``, ``_lock``, ``store``, ``config``, ``params``,
    ``options``, ``activity``, ``motion``, ``camera_ok``, ``armed``, ``latched``, ``_pool``,
    ``_wake``, ``_cancel``, ``_commands``, ``counters``, ``watch_log``, ``progress``) and its methods
    (``_fault``, ``_pause``, ``_report``, ``_answer_no_change``, ``_send``, ``_kept_regions``,
    ``_refresh_heartbeat``).
    """

    def _start_watch(self, station: str) -> None:
        reference = self.store.load(station)
        with self._lock:
            # the gate's noise margin is the check's own, taken once (not per frame)
            params = change_params(self.config, self.params)
            self._watch = _Watch(station, reference, self.params["watch_n"],
                                 (params.free_space_margin_m, params.free_space_margin_per_m2))
            self.activity = ModuleState.WATCHING
        log.info("WATCH %s: a change in %d of %d checks, every %d ms", station,
                 self.params["watch_m"], self.params["watch_n"], self.params["check_interval_ms"])
        self._refresh_heartbeat(force=True)

    def _end_watch(self) -> None:
        with self._lock:
            watch, self._watch = self._watch, None
            if watch is not None:
                self.activity = ModuleState.IDLE
        self.progress.forget("watch")
        if watch is not None:
            for job in watch.jobs:
                job.future.cancel()
            log.info("watch of %s ended after %d checks", watch.station, watch.checks)

    def _gate(self, watch: _Watch, depth: np.ndarray) -> int:
        return depth_gate(watch.reference.depth, depth, *watch.gate_margin,
                          self.options.gate_step)

    def _parked(self) -> bool:
        return self.motion in (Motion.PARKED, Motion.PAUSED)

    def _watch_frame(self, frame: DepthFrame, seq: int) -> None:
        watch = self._watch
        assert watch is not None
        ref = watch.reference.depth
        watch.latest, watch.latest_seq = frame, seq
        if frame.depth.shape != ref.shape:
            return  # the check itself reports the mismatch
        watch.latest_gate = self._gate(watch, frame.depth)
        base = watch.gate_baseline
        if (base is not None and self._parked() and self.camera_ok
                and abs(watch.latest_gate - base) > self.options.gate_pixels + self.options.gate_fraction * base
                and len(watch.jobs) < self.options.detector_threads):
            self.counters["gate_triggers"] += 1
            self._submit(watch, frame, seq)

    def _submit(self, watch: _Watch, frame: DepthFrame, seq: int) -> None:
        assert self._pool is not None
        params = change_params(self.config, self.params)
        future = self._pool.submit(detect.detect_changes, watch.reference, frame.depth, params,
                                   intrinsics=frame.intrinsics, initial_pose=watch.pose)
        # a unit of work until the check really ends (a cancelled or stale one too): a check
        # that never ends is a stalled detector (robot_change.service.liveness)
        work = self.progress.begin("detector", f"WATCH {watch.station}: the check of frame "
                                   f"{frame.index}")

        def done(_future: concurrent.futures.Future) -> None:
            self.progress.end(work)
            self._wake.set()

        future.add_done_callback(done)
        watch.jobs.append(_WatchJob(seq, frame.index, future, time.monotonic()))
        watch.last_submitted = seq
        watch.gate_baseline = self._gate(watch, frame.depth) \
            if frame.depth.shape == watch.reference.depth.shape else None
        watch.next_check = time.monotonic() + self.params["check_interval_ms"] / 1000.0

    def _watch_step(self) -> None:
        watch = self._watch
        assert watch is not None
        if self._cancel.is_set():
            self._cancel.clear()
            if self._commands.empty():
                self._end_watch()
                self._refresh_heartbeat(force=True)
            return
        done = sorted((j for j in watch.jobs if j.future.done()), key=lambda j: j.seq)
        for job in done:
            watch.jobs.remove(job)
            if job.future.cancelled() or job.seq <= watch.last_recorded:
                continue  # an older frame's check finished after a newer one's: stale
            watch.last_recorded = job.seq
            self._watch_result(watch, job)
            if self._watch is not watch:
                return
        if not self._parked() or not self.camera_ok:
            # nothing to check: not a stall (a lost camera is a FAULT of its own)
            self.progress.forget("watch")
            if watch.window and not self._parked():
                watch.window.clear()
                log.info("watch of %s suspended: the base is %s", watch.station, self.motion.name)
            return
        # frames must be checked, not only received: a check must finish every interval
        self.progress.set_bound("watch", self.params["check_interval_ms"] / 1000.0
                                + self.progress.bound_s)
        if not self.progress.watches("watch"):
            self.progress.beat("watch")  # from now on
        if (self.camera_ok and not watch.jobs and watch.latest is not None
                and watch.latest_seq != watch.last_submitted
                and time.monotonic() >= watch.next_check):
            self._submit(watch, watch.latest, watch.latest_seq)

    def _watch_result(self, watch: _Watch, job: _WatchJob) -> None:
        exc = job.future.exception()
        self.progress.beat("watch")
        watch.checks += 1
        self.counters["watch_checks"] += 1
        blind = False
        regions: list[Any] = []
        changes = None
        if exc is None:
            changes = job.future.result()
            regions = self._kept_regions(changes)
            watch.error_reported = watch.blind_reported = False
            if changes.outcome == "not_at_station":
                blind = True  # cannot watch from here: as unsafe as a change
                if not watch.off_station_reported:
                    watch.off_station_reported = True
                    self._fault(FaultCode.NOT_AT_STATION, f"WATCH {watch.station}: the robot "
                                f"is no longer at the station ({changes.not_at_station_reason})")
            else:
                watch.pose = changes.registration.T_ref_from_cur
                if watch.off_station_reported:
                    watch.off_station_reported = False
                    self._fault(FaultCode.CLEARED, f"WATCH {watch.station}: back at the "
                                f"station")
        elif isinstance(exc, EmptySceneError):
            blind = True  # nothing to compare: as unsafe as a change
            if not watch.blind_reported:
                watch.blind_reported = True
                self._fault(FaultCode.CAMERA_LOST, f"WATCH {watch.station}: the camera sees "
                            f"nothing to compare ({exc})")
        elif isinstance(exc, SceneMismatchError):
            self._fault(FaultCode.REFERENCE_MISSING, f"WATCH {watch.station}: the reference "
                        f"does not fit this camera ({exc}); capture it again")
            self._end_watch()
            return
        else:
            if not watch.error_reported:
                watch.error_reported = True
                log.error("WATCH %s: check failed", watch.station, exc_info=exc)
                self._fault(FaultCode.INTERNAL_ERROR, f"WATCH {watch.station}: check failed "
                            f"({type(exc).__name__}: {exc})")
            return
        changed = bool(regions) or blind
        watch.window.append(changed)
        m, n = self.params["watch_m"], self.params["watch_n"]
        seen = sum(watch.window)
        log.debug("watch %s frame %d: %s (%d of the last %d)", watch.station, job.frame_index,
                  "change" if changed else "no change", seen, len(watch.window))
        entry = {"t": time.monotonic(), "seq": job.seq, "frame_index": job.frame_index,
                 "changed": changed, "changed_in_window": seen, "action": "",
                 "check_ms": (time.monotonic() - job.submitted) * 1e3}
        self.watch_log.append(entry)
        if not watch.episode and seen >= m:
            entry["action"] = "report"
            watch.episode = True
            log.warning("WATCH %s: change in %d of the last %d checks (frame %d)", watch.station,
                        seen, len(watch.window), job.frame_index)
            if self.armed and self.params["pause_on_change"] and not self.latched:
                entry["action"] = "pause"
                off = changes is not None and changes.outcome == "not_at_station"
                self._pause(PauseCause.NOT_AT_STATION if off else PauseCause.CAMERA_LOST
                            if blind and not regions else PauseCause.CHANGE_WATCH)
            if changes is not None and regions:
                self._report(watch.station, changes)
        elif watch.episode and len(watch.window) - seen >= min(m, n) and not changed:
            watch.episode = False
            entry["action"] = "clear"
            log.info("WATCH %s: the change is gone", watch.station)
            self._answer_no_change(watch.station, changes)
