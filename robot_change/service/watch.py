"""WATCH: the per-frame depth gate, the detector threads and the persistence window.

WATCH checks the newest frame every ``check_interval_ms`` and at once when a cheap per-frame
depth gate (:func:`depth_gate`) sees the scene differ from what the last check saw, and raises
PAUSE when a change is seen in ``watch_m`` of the last ``watch_n`` checks (once per change:
CLEAR when ``watch_m`` of the last ``watch_n`` checks saw none, after which a new change pauses
again; a new change beside the one reported -- regions away from its regions, in
``watch_m`` of the last ``watch_n`` checks -- is reported and pauses too; a change reported
while it could not pause -- disarmed, the latch set -- pauses once it may).  A watch checks
only while the base's heartbeat says PARKED or PAUSED.  A check that sees nothing to compare
(no depth: covered lens, something against the camera) counts as a change (PAUSE cause
CAMERA_LOST), and so does a check that finds the robot no longer at its station (pushed, or
crept: FAULT and PAUSE NOT_AT_STATION), since it cannot watch from there.  Every check
registers the view again, starting from the last check's estimate, so a robot
that creeps a few centimetres is followed.

A :class:`StationWatch` is an object the service (robot_change.service.core) makes for each
WATCH and calls through a few methods -- :meth:`~StationWatch.frame` for every frame,
:meth:`~StationWatch.step` every tick, :meth:`~StationWatch.configure` when parameters change,
:meth:`~StationWatch.close` at the end -- and it talks back only through the small
:class:`WatchHost` interface (what the base is doing, and FAULT / PAUSE / report / CLEAR).

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
from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np

from hw.depth import DepthFrame
from robot_change.change import detect
from robot_change.change.params import ChangeParams
from robot_change.change.results import ChangeSet
from robot_change.change.scene import SceneModel
from robot_change.errors import EmptySceneError, SceneMismatchError
from robot_change.link.protocol import FaultCode, PauseCause
from robot_change.noise.profile import NoiseProfile
from robot_change.service.liveness import Progress

__all__ = ["EPISODE_MARGIN_M", "GateOptions", "StationWatch", "WatchHost", "depth_gate"]

log = logging.getLogger(__name__)

#: A region of a later check is part of the change already reported when its box comes within
#: this many metres of one of that change's regions (the same object seen again, its box a
#: little different each time); one farther off is a new change, and pauses again.  Measured
#: (bench/watch_episode_margin.py: 25 changed scenes, harsh Kinect noise, 12 single-frame
#: checks each, 2026-12-07): the same change needed at most 0.2 cm on the dev scenes and
#: 7.1 cm on the held-out ones (a fragment of meeting_two_changes_pose_5cm seen in 4 of 12
#: checks); smaller would pause again for it.
EPISODE_MARGIN_M = 0.1


def depth_gate(reference: np.ndarray, depth: np.ndarray, noise: NoiseProfile, sigmas: float,
               pose_m: float, step: int = 4) -> int:
    """How many sampled pixels (every ``step``-th of every ``step``-th row) read nearer or
    farther than the reference by more than the camera's noise allows (the free-space check's
    margin: ``noise.margin`` with ChangeParams.free_space_sigmas / free_space_pose_m).

    A cheap per-frame trigger for WATCH checks, never a decision: a jump in this count means the
    scene is no longer what the last check saw, so a check runs at once.  ~0.5 ms at VGA.
    """
    r = reference[::step, ::step].astype(np.float32)
    c = depth[::step, ::step].astype(np.float32)
    both = (r > 0) & (c > 0)
    margin = 1000.0 * noise.margin(r[both] * 1e-3, sigmas, pose_m)  # mm
    return int(np.count_nonzero(np.abs(c[both] - r[both]) > margin))



class WatchHost(Protocol):
    """What a :class:`StationWatch` needs of the service that owns it."""

    @property
    def parked(self) -> bool:
        """The base's heartbeat says PARKED or PAUSED (a watch checks only then)."""

    @property
    def camera_ok(self) -> bool:
        """The camera is delivering frames."""

    def may_pause(self) -> bool:
        """A change may raise PAUSE now (armed, ``pause_on_change``, the latch not set)."""

    def send_fault(self, code: FaultCode, text: str) -> None:
        """FAULT ``code`` to the base."""

    def send_pause(self, cause: PauseCause) -> None:
        """PAUSE ``cause`` to the base (sets the latch)."""

    def send_report(self, station: str, changes: ChangeSet) -> int:
        """CHECK_RESULT and CHANGE_REPORT of a change; returns the report id."""

    def send_no_change(self, station: str, changes: ChangeSet) -> None:
        """CHECK_RESULT and CLEAR."""


@dataclasses.dataclass(frozen=True)
class GateOptions:
    """The per-frame depth gate: every ``step``-th pixel of every ``step``-th row; a check runs
    when the count of pixels that differ from the reference moved by more than ``pixels +
    fraction x`` the count at the last check.  ``max_jobs``: checks that may run at once."""

    step: int = 4
    pixels: int = 50
    fraction: float = 0.2
    max_jobs: int = 2


@dataclasses.dataclass
class _Job:
    seq: int  # the frame's sequence number in the FrameQueue
    frame_index: int
    future: concurrent.futures.Future
    submitted: float


class StationWatch:
    """One WATCH of one station (module docstring).

    ``reference``: the station's scene.  ``params``: the wire's parameter table (``watch_m``,
    ``watch_n``, ``check_interval_ms``) and ``change``: the check's ChangeParams, both replaced
    by :meth:`configure` when SET_PARAM or a reload changes them.  ``pool`` runs the checks;
    ``progress`` tracks each check as a unit of work (part "detector") and that checks keep
    coming (part "watch": it beats when a check starts and when its result is taken, so a
    check that hangs is past the detector's bound before the watch is silent past its own,
    and is named as the detector's stall); ``counters`` gets ``watch_checks`` and
    ``gate_triggers``; ``history`` gets one entry per check (t, seq, frame_index, changed,
    changed_in_window, action "pause" / "report" / "clear" / "", check_ms); ``on_done`` is
    called when a check ends (it wakes the controller).
    """

    def __init__(self, station: str, reference: SceneModel, host: WatchHost,
                 params: Mapping[str, int], change: ChangeParams, gate: GateOptions,
                 pool: concurrent.futures.Executor, progress: Progress,
                 counters: collections.Counter, history: collections.deque,
                 on_done: Callable[[], None]) -> None:
        self.station = station
        self.reference = reference
        self._host = host
        self._gate_options = gate
        self._pool = pool
        self._progress = progress
        self._counters = counters
        self._history = history
        self._on_done = on_done
        self.window: collections.deque[bool] = collections.deque(maxlen=params["watch_n"])
        self.configure(params, change)
        self.checks = 0
        self._jobs: list[_Job] = []
        self._last_submitted = -1
        self._last_recorded = -1
        self._next_check = 0.0
        self._gate_baseline: int | None = None
        self._episode = False  # a change is being reported (PAUSE sent or report made)
        self._episode_paused = False  # ... and it raised PAUSE (else it does once it may)
        self._episode_boxes: list[tuple[np.ndarray, np.ndarray]] = []  # its regions, widened
        self._new_window: collections.deque[bool] = collections.deque(maxlen=params["watch_n"])
        self._blind_reported = False
        self._error_reported = False
        self._latest: DepthFrame | None = None
        self._latest_seq = -1
        self._pose: np.ndarray | None = None  # the last registration (T_ref_from_cur)
        self._off_station_reported = False
        self._ended = False

    def configure(self, params: Mapping[str, int], change: ChangeParams) -> None:
        """Take a new parameter table and ChangeParams (the window keeps its newest entries)."""
        self._params = dict(params)
        self._change = change
        if self.window.maxlen != params["watch_n"]:
            self.window = collections.deque(self.window, maxlen=params["watch_n"])
            self._new_window = collections.deque(self._new_window, maxlen=params["watch_n"])

    @staticmethod
    def _widened(changes: ChangeSet) -> list[tuple[np.ndarray, np.ndarray]]:
        """The regions' boxes (camera frame, m), widened by EPISODE_MARGIN_M each way."""
        return [(r.bbox_min - EPISODE_MARGIN_M, r.bbox_max + EPISODE_MARGIN_M)
                for r in changes.regions]

    def _outside_episode(self, changes: ChangeSet) -> list:
        """The regions of ``changes`` whose box meets none of the reported change's boxes."""
        return [r for r in changes.regions
                if not any(np.all(r.bbox_max >= lo) and np.all(r.bbox_min <= hi)
                           for lo, hi in self._episode_boxes)]

    def camera_lost(self) -> None:
        """The camera was lost: what the window saw and the gate's baseline no longer hold."""
        self.window.clear()
        self._new_window.clear()
        self._gate_baseline = None

    def close(self) -> None:
        """End the watch: cancel the checks not started (a running one ends on its own)."""
        self._progress.forget("watch")
        for job in self._jobs:
            job.future.cancel()
        log.info("watch of %s ended after %d checks", self.station, self.checks)

    # -- frames ---------------------------------------------------------------------------------

    def _gate(self, depth: np.ndarray) -> int | None:
        if depth.shape != self.reference.depth.shape:
            return None  # the check itself reports the mismatch
        return depth_gate(self.reference.depth, depth, self.reference.noise,
                          self._change.free_space_sigmas, self._change.free_space_pose_m,
                          self._gate_options.step)

    def frame(self, frame: DepthFrame, seq: int) -> None:
        """Every frame the camera delivers: kept as the newest, and checked at once when the
        depth gate sees the scene move away from what the last check saw."""
        self._latest, self._latest_seq = frame, seq
        count = self._gate(frame.depth)
        base, gate = self._gate_baseline, self._gate_options
        if (count is not None and base is not None and self._host.parked
                and self._host.camera_ok and abs(count - base) > gate.pixels + gate.fraction * base
                and len(self._jobs) < gate.max_jobs):
            self._counters["gate_triggers"] += 1
            self._submit(frame, seq)

    def _submit(self, frame: DepthFrame, seq: int) -> None:
        future = self._pool.submit(detect.detect_changes, self.reference, frame.depth,
                                   self._change, intrinsics=frame.intrinsics,
                                   initial_pose=self._pose)
        # a unit of work until the check really ends (a cancelled or stale one too): a check
        # that never ends is a stalled detector (robot_change.service.liveness)
        work = self._progress.begin("detector", f"WATCH {self.station}: the check of frame "
                                    f"{frame.index}")
        self._progress.beat("watch")

        def done(_future: concurrent.futures.Future) -> None:
            self._progress.end(work)
            self._on_done()

        future.add_done_callback(done)
        self._jobs.append(_Job(seq, frame.index, future, time.monotonic()))
        self._last_submitted = seq
        self._gate_baseline = self._gate(frame.depth)
        self._next_check = time.monotonic() + self._params["check_interval_ms"] / 1000.0

    # -- ticks ----------------------------------------------------------------------------------

    def step(self) -> bool:
        """Every tick of the controller: take the checks that ended (oldest frame first) and
        start the next one when it is due.  False when the watch ended itself (the reference
        does not fit the camera): the owner then closes it."""
        done = sorted((j for j in self._jobs if j.future.done()), key=lambda j: j.seq)
        for job in done:
            self._jobs.remove(job)
            if job.future.cancelled() or job.seq <= self._last_recorded:
                continue  # an older frame's check finished after a newer one's: stale
            self._last_recorded = job.seq
            self._result(job)
            if self._ended:
                return False
        host = self._host
        if not host.parked or not host.camera_ok:
            # nothing to check: not a stall (a lost camera is a FAULT of its own)
            self._progress.forget("watch")
            if self.window and not host.parked:
                self.window.clear()
                log.info("watch of %s suspended: the base is not parked", self.station)
            return True
        # frames must be checked, not only received: a check must finish every interval
        self._progress.set_bound("watch", self._params["check_interval_ms"] / 1000.0
                                 + self._progress.bound_s)
        if not self._progress.watches("watch"):
            self._progress.beat("watch")  # from now on
        if (not self._jobs and self._latest is not None
                and self._latest_seq != self._last_submitted
                and time.monotonic() >= self._next_check):
            self._submit(self._latest, self._latest_seq)
        return True

    def _result(self, job: _Job) -> None:
        exc = job.future.exception()
        host = self._host
        self._progress.beat("watch")
        self.checks += 1
        self._counters["watch_checks"] += 1
        blind = False
        changes: ChangeSet | None = None
        if exc is None:
            changes = job.future.result()
            if self._blind_reported or self._error_reported:  # what was told is over
                host.send_fault(FaultCode.CLEARED, f"WATCH {self.station}: "
                                + ("the camera sees the room again" if self._blind_reported
                                   else "checks work again"))
            self._error_reported = self._blind_reported = False
            if changes.outcome == "not_at_station":
                blind = True  # cannot watch from here: as unsafe as a change
                if not self._off_station_reported:
                    self._off_station_reported = True
                    host.send_fault(FaultCode.NOT_AT_STATION, f"WATCH {self.station}: the robot "
                                    f"is no longer at the station "
                                    f"({changes.not_at_station_reason})")
            else:
                self._pose = changes.registration.T_ref_from_cur
                if self._off_station_reported:
                    self._off_station_reported = False
                    host.send_fault(FaultCode.CLEARED, f"WATCH {self.station}: back at the "
                                    f"station")
        elif isinstance(exc, EmptySceneError):
            blind = True  # nothing to compare: as unsafe as a change
            if not self._blind_reported:
                self._blind_reported = True
                host.send_fault(FaultCode.CAMERA_LOST, f"WATCH {self.station}: the camera sees "
                                f"nothing to compare ({exc})")
        elif isinstance(exc, SceneMismatchError):
            host.send_fault(FaultCode.REFERENCE_MISSING, f"WATCH {self.station}: the reference "
                            f"does not fit this camera ({exc}); capture it again")
            self._ended = True
            return
        else:
            if not self._error_reported:
                self._error_reported = True
                log.error("WATCH %s: check failed", self.station, exc_info=exc)
                host.send_fault(FaultCode.INTERNAL_ERROR, f"WATCH {self.station}: check failed "
                                f"({type(exc).__name__}: {exc})")
            return
        has_regions = changes is not None and bool(changes.regions)
        changed = has_regions or blind
        self.window.append(changed)
        new = has_regions and self._episode and bool(self._outside_episode(changes))
        self._new_window.append(new)
        m, n = self._params["watch_m"], self._params["watch_n"]
        seen = sum(self.window)
        log.debug("watch %s frame %d: %s (%d of the last %d)", self.station, job.frame_index,
                  "change" if changed else "no change", seen, len(self.window))
        entry = {"t": time.monotonic(), "seq": job.seq, "frame_index": job.frame_index,
                 "changed": changed, "changed_in_window": seen, "action": "",
                 "check_ms": (time.monotonic() - job.submitted) * 1e3}
        self._history.append(entry)
        cause = (PauseCause.NOT_AT_STATION if changes is not None
                 and changes.outcome == "not_at_station" else PauseCause.CAMERA_LOST
                 if blind and not has_regions else PauseCause.CHANGE_WATCH)
        if (not self._episode and seen >= m) or sum(self._new_window) >= m:
            # a change, or a new one beside the change reported (regions outside its boxes)
            entry["action"] = "report"
            self._episode, self._episode_paused = True, False
            self._new_window.clear()
            log.warning("WATCH %s: change in %d of the last %d checks (frame %d)", self.station,
                        seen, len(self.window), job.frame_index)
            if host.may_pause():
                entry["action"] = "pause"
                self._episode_paused = True
                host.send_pause(cause)
            if changes is not None and has_regions:
                self._episode_boxes += self._widened(changes)
                host.send_report(self.station, changes)
        elif self._episode and changed and not self._episode_paused and host.may_pause():
            # reported while it could not pause (disarmed, pause_on_change 0, the latch of an
            # earlier PAUSE set): still there once it may (ARM, RESUME), so it pauses now
            entry["action"] = "pause"
            self._episode_paused = True
            host.send_pause(cause)
        elif (self._episode and len(self.window) - seen >= min(m, n) and not changed
              and changes is not None):  # (not changed: the check gave a ChangeSet)
            self._episode = False
            self._episode_boxes = []
            entry["action"] = "clear"
            log.info("WATCH %s: the change is gone", self.station)
            host.send_no_change(self.station, changes)
