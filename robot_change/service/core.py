"""The daemon: commands from the base in, depth frames from the camera, PAUSE and reports out.

The service is handed everything it talks to -- a depth source (or a function that makes one),
an open serial port, a reference store and a configuration -- and never builds hardware itself
(``robot_change.cli`` does, for ``robot-change run``); tests hand it a recording and one end of
a pty pair exactly as the robot hands it a camera and ``/dev/robot-base``.

States (``HEARTBEAT.state``, ``robot_change.link.protocol.ModuleState``)::

    BOOTING --start()--> IDLE
    IDLE --CAPTURE_REFERENCE s--> CAPTURING --CAPTURED s | FAULT--> IDLE
    IDLE --CHECK s--> CHECKING --CLEAR s | PAUSE + CHANGE_REPORT | FAULT--> IDLE
    IDLE --WATCH s--> WATCHING --STOP (or a new CAPTURE/CHECK/WATCH)--> IDLE
    any --camera lost--> FAULT --camera back--> the state it left (a watch carries on)

``PAUSED`` is what an idle module reports while its pause latch is set (after a CHECK that
raised PAUSE, until RESUME).  The latch itself is the heartbeat's ``paused`` flag in every
state: it is set when PAUSE is sent and cleared only by RESUME (docs/protocol.md 7.6).  While
WATCHING the state stays WATCHING with the latch shown alongside, since the watch goes on (it
reports CLEAR when the change is gone).  ``armed`` (ARM / DISARM, armed at start) and the
``pause_on_change`` parameter decide whether a change raises PAUSE or is only reported.

Commands: CAPTURE_REFERENCE, CHECK and WATCH queue for the controller thread and replace any
watch in progress; the quick ones (STATUS_QUERY, ARM, DISARM, RESUME, STOP, SET_PARAM,
GET_PARAM) are answered at once from the link thread.  CHECK fuses ``fuse_frames`` fresh
frames (per-pixel median) and compares them with the station's reference; a check that sees
nothing to compare (no depth: covered lens, something against the camera) is a FAULT
CAMERA_LOST.  WATCH (``robot_change.service.watch``) checks the newest frame again and again and
raises PAUSE when a change persists.  SET_PARAM ``max_depth_mm`` applies to references
captured after it (a check cleans its frames with its reference's parameters); the other
parameters apply at once.

Threads and queues (nothing grows without bound)::

    camera    (robot_change.service.camera) source.read() -> FrameQueue (bounded, oldest dropped)
    link      LinkRunner.run(): bytes <-> messages; quick commands answered here
    control   commands (bounded queue), frames, capture / check / watch, heartbeat contents
    detector  (robot_change.service.watch) <= 2 threads running WATCH checks
    monitor   progress of every part (robot_change.service.liveness): a stall is told to the base
    fleet     (robot_change.fleet.publisher; with [fleet]) a bounded report queue, its writer
              (-> on-disk spool) and network (-> MQTT broker) threads; a check told to the
              base is handed to it afterwards with a call that never blocks

Liveness: the link, camera and control threads stamp every turn, a CHECK or capture and every
WATCH check is a unit of work that must end, and while a watch runs (the base parked, the
camera delivering) checks must keep finishing.  A part that makes no progress within
``ServiceOptions.stall_after_s`` (half of WatchdogSec under systemd) is a stall: FAULT STALLED
to the base, PAUSE (cause INTERNAL_ERROR) when armed and watching, the heartbeat's state FAULT,
and :meth:`Service.healthy` false from then on, so the daemon stops feeding the watchdog and
exits for systemd to restart it (``robot_change.service.daemon``).

Every frame the camera delivers is accounted for: ``received == processed + dropped +
queued`` (:meth:`Service.frame_counts`).  Bad input never stops the service: garbage on the line
is NAKed by the link, a corrupt reference is quarantined by the store and reported (FAULT
REFERENCE_MISSING), and an exception inside a command is logged and answered with FAULT
INTERNAL_ERROR while the service carries on.

``robot_change.service.daemon.run_service`` is the daemon's main loop around a :class:`Service`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import json
import logging
import math
import queue
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

import robot_change
from hw.atomic import remove_temp_files, write_atomically
from hw.depth import DepthFrame, DepthSource
from robot_change import npzfile
from robot_change.change import detect, scene
from robot_change.change.limits import detection_limit
from robot_change.change.mount import CameraMount
from robot_change.change.results import ChangeSet
from robot_change.change.results import Region as ChangeRegion
from robot_change.change.scene import SceneModel
from robot_change.cloud.fusion import fuse_depth
from robot_change.errors import (
    EmptySceneError,
    ReferenceMissing,
    SceneMismatchError,
    StoreError,
)
from robot_change.fleet.messages import utc_text
from robot_change.fleet.publisher import Publisher
from robot_change.fleet.spool import Spool
from robot_change.link.port import BytePort
from robot_change.link.protocol import (
    PARAM_BY_ID,
    REGIONS_PER_PART,
    V1_FAULT_CODE,
    V1_PAUSE_CAUSE,
    WEAK_BITS,
    Arm,
    BaseHeartbeat,
    Captured,
    CaptureReference,
    Check,
    CheckOutcome,
    CheckResult,
    Clear,
    Disarm,
    Fault,
    FaultCode,
    GetParam,
    Heartbeat,
    Message,
    ModuleState,
    Motion,
    NakReason,
    ParamValue,
    Pause,
    PauseCause,
    Region,
    RegionKind,
    Resume,
    Role,
    SetParam,
    Status,
    StatusQuery,
    Stop,
    Watch,
    split_change_report,
)
from robot_change.link.session import (
    Delivered,
    Link,
    LinkConfig,
    LinkRunner,
    LinkState,
    PortProblem,
    Received,
    SendFailed,
    StateChanged,
)
from robot_change.service.camera import CameraThread, FrameQueue
from robot_change.service.config import Config
from robot_change.service.documents import check_report, status_document
from robot_change.service.liveness import Progress
from robot_change.service.params import change_params, scene_params
from robot_change.service.store import ReferenceStore
from robot_change.service.views import CheckView, CheckViews
from robot_change.service.watch import GateOptions, StationWatch
from robot_change.throttle import Throttled

__all__ = ["Service", "ServiceOptions"]

log = logging.getLogger(__name__)

#: Format of ``<station>.last-check.npz`` (robot_change.npzfile): the last CHECK's fused depth,
#: the reference's, the change masks (H, W) bool, intrinsics (6,) w h fx fy cx cy, region boxes
#: (R, 10) min xyz, max xyz, centroid xyz (m, camera frame), points; region kinds (R,) 1 / 2.
CHECK_FORMAT = "robot_change.check"

#: Most CHANGE_REPORT regions sent for one report (the largest first): 255 parts of 11.
MAX_REPORT_REGIONS = 255 * REGIONS_PER_PART
_FAULT_TEXT = 200


@dataclasses.dataclass(frozen=True)
class ServiceOptions:
    """Knobs of the service itself (the configuration file holds the method's).

    ``queue_frames``: frames the camera may queue ahead of the controller (older ones are
    dropped and counted).  ``detector_threads``: WATCH checks that may run at once (2: a gate
    triggered check need not wait for a scheduled one).  ``gate_step``: the depth gate looks at
    every ``gate_step``-th pixel of every ``gate_step``-th row; ``gate_pixels`` and
    ``gate_fraction``: it triggers a check when the count of pixels that differ from the
    reference moved by more than ``gate_pixels + gate_fraction x`` the count at the last check.
    ``report_dir``: where the last CHECK of each station is written (fused depth, change masks,
    regions; ``<station>.last-check.npz``) for people and ``robot-change demo``, and every
    CHECK as an MCAP file for Foxglove in its ``checks/`` folder (the configuration's [viz],
    robot_change.service.views); None: nowhere.
    ``link_max_wait``: the link thread's longest sleep (s), bounding the added send latency.
    ``stall_after_s``: a part that makes no progress for this long (a check, a capture or a
    WATCH check that does not end, a thread that does not turn) is a stall (module docstring);
    the daemon sets it to half of systemd's WatchdogSec.  ``command_allowance_s``: what a
    CAPTURE_REFERENCE or CHECK (frames, fusion, the fit) may take beyond ``stall_after_s``
    before it is a stall (docs/protocol.md 7.10): ~0.5 s on a quiet 2-core machine, several
    on a busy or slow one.
    """

    queue_frames: int = 4
    detector_threads: int = 2
    gate_step: int = 4
    gate_pixels: int = 50
    gate_fraction: float = 0.2
    report_dir: Path | None = None
    link_max_wait: float = 0.005
    command_queue: int = 16
    stall_after_s: float = 5.0
    command_allowance_s: float = 8.0


# ---------------------------------------------------------------------------------------------
# helpers


def _clip(value: float, lo: int, hi: int) -> int:
    return int(min(hi, max(lo, round(value))))


def _wire_regions(regions: list[ChangeRegion], mount: CameraMount | None = None
                  ) -> list[Region]:
    """change.Region (metres) -> protocol.Region (mm, clipped to the field widths): in the
    camera optical frame (protocol version 1), or with ``mount`` in base_link (version 2)."""
    out = []
    for r in regions:
        kind = RegionKind.APPEARED if r.kind == "appeared" else RegionKind.DISAPPEARED
        if mount is None:
            centre, size = r.centroid, r.extent
        else:
            lo, hi = r.base_box(mount)
            centre, size = mount.to_base(r.centroid[None])[0], hi - lo
        centroid = tuple(_clip(v * 1000.0, -32768, 32767) for v in centre)
        extent = tuple(_clip(v * 1000.0, 0, 65535) for v in size)
        out.append(Region(kind, centroid, extent, _clip(r.n_points, 0, 0xFFFF_FFFF)))
    return out


def check_result(station: str, changes: ChangeSet, mount: CameraMount, report_id: int = 0
                 ) -> CheckResult:
    """The CHECK_RESULT (protocol version 2) of a ChangeSet: outcome and the robot's offset
    from its station pose in base_link (mm, centi-degrees), fitness, unobserved share, weak
    directions."""
    offset = mount.offset(changes.registration)
    outcome = {"changed": CheckOutcome.CHANGED, "no_change": CheckOutcome.NO_CHANGE,
               "not_at_station": CheckOutcome.NOT_AT_STATION}[changes.outcome]
    if outcome == CheckOutcome.CHANGED and not report_id:
        outcome = CheckOutcome.NO_CHANGE  # every region was below the wire's size limits
    weak = 0
    for name in offset.weak:
        weak |= WEAK_BITS[name]
    return CheckResult(
        station, outcome, report_id,
        tuple(_clip(v * 1000.0, -32768, 32767) for v in offset.translation_m),
        tuple(_clip(v * 100.0, -32768, 32767) for v in offset.rpy_deg),
        _clip(changes.registration.fitness * 1000.0, 0, 1000),
        _clip(changes.unobserved_fraction * 1000.0, 0, 1000), weak)


_ABSOLUTE_PATH = re.compile(r"(?<![\w.~-])/[^\s'\"(),;:]+")


def wire_text(text: str) -> str:
    """A FAULT text for the wire: every absolute path of this machine replaced by its last
    component, the name of the file, folder or port (``/dev/ttyUSB0`` -> ``ttyUSB0``); the log
    keeps the whole text (docs/protocol.md, FAULT)."""
    def name(match: re.Match) -> str:
        return match.group(0).rstrip("/").rsplit("/", 1)[-1] or "/"
    return _ABSOLUTE_PATH.sub(name, text)


def _short(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text.encode()) <= _FAULT_TEXT else text.encode()[:_FAULT_TEXT - 3].decode(
        "utf-8", "ignore") + "..."


# ---------------------------------------------------------------------------------------------
# the service


class Service:
    """The daemon's state machine (module docstring).  Make it, :meth:`start` it, and
    :meth:`close` it; everything else arrives over the link.

    ``camera``: a :class:`hw.depth.DepthSource` (reopened with close()/open() after a loss) or
    a callable returning a new unopened one (called again after a loss).  ``port``: an open
    port (pyserial, :class:`hw.serial_port.ReopeningPort`, or anything with read, write,
    in_waiting, fileno).  ``store``: a :class:`robot_change.service.store.ReferenceStore`.
    """

    def __init__(self, config: Config, camera: DepthSource | Callable[[], DepthSource],
                 port: BytePort, store: ReferenceStore, options: ServiceOptions | None = None, *,
                 link_config: LinkConfig | None = None) -> None:
        self.config = config
        self.options = options or ServiceOptions()
        self.store = store
        self.port = port
        self.params: dict[str, int] = dict(config.parameters())
        self.link = Link(Role.MODULE, config=link_config or LinkConfig.for_baud(config.serial.baud),
                         software=f"robot-change {robot_change.__version__}", admit=self._admit)
        self._throttled = Throttled(log)
        self._admitted = 0  # commands admitted by the link, not yet in self._commands
        self.runner = LinkRunner(self.link, port, max_wait=self.options.link_max_wait)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.frames = FrameQueue(self.options.queue_frames, on_put=self._wake.set)
        self._commands: queue.Queue = queue.Queue(maxsize=self.options.command_queue)
        self._threads: list[threading.Thread] = []
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self.started_at = time.monotonic()
        # state (guarded by _lock)
        self.state = ModuleState.BOOTING
        self.activity = ModuleState.IDLE  # what the controller does (IDLE/CAPTURING/...)
        self.latched = False
        self.armed = True
        self.station = ""
        self.motion = Motion.UNKNOWN
        self._pause_undelivered = False
        self._last_pause_cause = PauseCause.CHANGE_CHECK
        self._cancel = threading.Event()
        self._watch: StationWatch | None = None
        self._report_id = 0
        self._camera_reported = None  # what the controller last told the base: True ok / False lost
        self.last_frame_index = 0
        # liveness: the camera's reads may take their timeout, and then some
        self.progress = Progress(self.options.stall_after_s, {
            "camera": max(self.options.stall_after_s, config.camera.read_timeout_s + 2.0)})
        self.camera = CameraThread(camera, self.frames, self.progress, self._stop, self._wake,
                                   lambda: self.config.camera.read_timeout_s)
        self.stalled = ""  # what stalled (set once, by the monitor thread)
        self.stall_told = threading.Event()  # the base acknowledged the FAULT STALLED
        self.stuck: list[str] = []  # threads that did not stop (robot_change.service.daemon)
        self.counters = collections.Counter()
        self.views = CheckViews(config.viz, None if self.options.report_dir is None
                                else Path(self.options.report_dir) / "checks", self.counters)
        self.last_check: dict[str, Any] = {}
        #: the last FAULTs told to the base, newest last: time (UTC text), code, text
        self.faults: collections.deque[dict[str, str]] = collections.deque(maxlen=10)
        #: the fleet (robot_change.fleet), when the configuration names a broker
        self.fleet: Publisher | None = self._make_fleet(config) if config.fleet.enabled else None
        #: the last WATCH results, newest last: t, seq, frame_index, changed, changed_in_window,
        #: action ("pause", "report", "clear" or "")
        self.watch_log: collections.deque[dict[str, Any]] = collections.deque(maxlen=256)
        self._heartbeat_at = 0.0

    # -- life cycle ---------------------------------------------------------------------------

    def _make_fleet(self, config: Config) -> Publisher:
        """The fleet's publisher: reports spooled in ``<state_dir>/fleet-spool``, the status
        from :func:`robot_change.service.documents.status_document`."""
        fleet = config.fleet
        spool = Spool(Path(config.store.state_dir) / "fleet-spool",
                      int(fleet.spool_mb * 1024 * 1024))
        return Publisher(fleet.settings(), fleet.robot_id, spool, prefix=fleet.topic_prefix,
                         status=lambda: status_document(self),
                         versions={"robot_change": robot_change.__version__})

    def start(self) -> None:
        """Start the link, camera and controller threads (call :func:`warm_up` first)."""
        self.store.recover()  # references/ and quarantine/; the fleet's spool: Spool()
        if self.options.report_dir is not None:
            reports = Path(self.options.report_dir)
            for folder in (reports, reports / "checks"):
                if remove_temp_files(folder):
                    log.info("removed temp files left by an interrupted write in %s", folder)
        self._pool = concurrent.futures.ThreadPoolExecutor(self.options.detector_threads,
                                                           thread_name_prefix="detector")
        self.views.start()
        with self._lock:
            self.state = ModuleState.IDLE
        self._refresh_heartbeat(force=True)
        for name, target in (("link", self._link_main), ("camera", self.camera.run),
                             ("control", self._control_main), ("monitor", self._monitor_main)):
            thread = threading.Thread(target=self._guard(name, target), name=f"rc-{name}",
                                      daemon=True)
            if name != "monitor":
                self.progress.beat(name)
            self._threads.append(thread)
            thread.start()
        if self.fleet is not None:
            self.fleet.start()
            log.info("fleet: reports to %s as robot %s (spool %s: %d waiting)",
                     self.fleet.settings.url, self.fleet.robot, self.fleet.spool.folder,
                     len(self.fleet.spool))
        log.info("service started: store %s, link %s", self.store.root,
                 getattr(self.port, "url", None) or getattr(self.port, "name", None) or self.port)

    def close(self, timeout: float = 1.0) -> list[str]:
        """Stop every thread, close the camera; the port stays the caller's.  Waits at most
        ``timeout`` seconds in all (a hung kernel is not waited for: SIGTERM must be quick);
        returns the names of the threads still running (the caller then exits the process
        with ``os._exit``, as an interpreter exit would wait for them)."""
        self._stop.set()
        self._wake.set()
        self._cancel.set()
        end = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.05, end - time.monotonic()))
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        detectors = [t for t in threading.enumerate() if t.name.startswith("detector")]
        for thread in detectors:  # idle workers end at once; a hung one is not waited for
            thread.join(max(0.05, end - time.monotonic()))
        self.views.close(max(0.05, end - time.monotonic()))  # a view is not worth waiting for
        if self.fleet is not None:  # what is queued goes to the spool; never waited for long
            self.fleet.close(max(0.05, min(0.3, end - time.monotonic())))
        stuck = [t.name for t in self._threads + detectors if t.is_alive()]
        if stuck:
            log.warning("threads still running at exit: %s", ", ".join(stuck))
        return stuck

    def __enter__(self) -> "Service":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _guard(self, name: str, target: Callable[[], None]) -> Callable[[], None]:
        """Run a thread's loop; an exception that escapes it is logged and the loop restarted
        (after a pause), so no bug stops the service."""
        def run() -> None:
            while not self._stop.is_set():
                try:
                    target()
                    return
                except Exception:  # noqa: BLE001 -- a bug: log it, keep the service up
                    log.exception("the %s thread failed; restarting it", name)
                    self.counters[f"{name}_restarts"] += 1
                    self._stop.wait(0.5)
        return run

    def healthy(self) -> tuple[bool, str]:
        """Is every part making progress?  (the systemd watchdog is fed only while it is)
        False once a stall was found (module docstring), or when a thread ended."""
        if self.stalled:
            return False, self.stalled
        for thread in self._threads:
            if not thread.is_alive():
                return False, f"thread {thread.name} ended"
        return True, "ok"

    # -- liveness (monitor thread) --------------------------------------------------------------

    def _monitor_main(self) -> None:
        while not self._stop.wait(0.1):
            if self.stalled:
                continue
            why = self.progress.stalled()
            if not why:
                dead = [t.name for t in self._threads if not t.is_alive()]
                why = f"thread {dead[0]} ended" if dead else ""
            if why:
                self._on_stall(why)

    def _on_stall(self, why: str) -> None:
        """Tell the base first: FAULT STALLED, PAUSE when armed and watching (a stalled watcher
        must stop the robot), the heartbeat's state FAULT.  The lock is not waited for long: a
        hung part may hold it."""
        self.stalled = why
        log.error("STALLED: %s; telling the base, then the module restarts", why)
        self.counters["stalls"] += 1
        locked = self._lock.acquire(timeout=0.5)
        try:
            pause = self.armed and self._watch is not None and not self.latched
            if pause:
                self.latched = True
                self._last_pause_cause = PauseCause.INTERNAL_ERROR
            self.send_fault(FaultCode.STALLED, f"{why}; the module restarts")
            if pause:
                self._send(Pause(PauseCause.INTERNAL_ERROR))
                self.counters["pauses"] += 1
                log.warning("PAUSE INTERNAL_ERROR (stalled while watching)")
            if locked:  # the heartbeat's state FAULT (it reads the state under the lock)
                self._refresh_heartbeat(force=True)
        finally:
            if locked:
                self._lock.release()

    def reload(self, config: Config, camera: DepthSource | Callable[[], DepthSource] | None = None) -> None:
        """Take a new configuration (SIGHUP): the parameter table is reseeded from it, and a new
        ``camera`` (when given) replaces the old one: it is closed and the new one opened."""
        with self._lock:
            old = self.config
            self.config = config
            self.params = dict(config.parameters())
            if self._watch is not None:
                self._watch.configure(self.params, change_params(config, self.params))
        if config.serial != old.serial:
            log.warning("[serial] changed in the configuration: restart the service to use it")
        if config.store != old.store:
            log.warning("[store] changed in the configuration: restart the service to use it")
        if config.viz != old.viz:
            log.warning("[viz] changed in the configuration: restart the service to use it")
        if config.fleet != old.fleet:
            log.warning("[fleet] changed in the configuration: restart the service to use it")
        if camera is not None:
            self.camera.swap(camera)
            log.info("configuration reloaded; reopening the camera")
        else:
            log.info("configuration reloaded")

    # -- public views -----------------------------------------------------------------------

    def frame_counts(self) -> dict[str, int]:
        """received, processed, dropped, queued: received == processed + dropped + queued."""
        return self.frames.counts()

    def fps(self) -> float:
        """Camera frames per second over the last second or so (0 when frames stopped)."""
        return self.camera.fps()

    @property
    def camera_ok(self) -> bool:
        """The camera is delivering frames (robot_change.service.camera)."""
        return self.camera.ok

    @property
    def camera_error(self) -> str:
        """Why the camera is not delivering ("" while it is)."""
        return self.camera.error

    @property
    def camera_losses(self) -> int:
        """Times the camera was lost since start."""
        return self.camera.losses

    @property
    def camera_uri(self) -> str:
        """The URI of the source the camera thread has open."""
        return self.camera.uri

    @property
    def parked(self) -> bool:
        """The base's last heartbeat said PARKED or PAUSED (a watch checks only then)."""
        return self.motion in (Motion.PARKED, Motion.PAUSED)

    def may_pause(self) -> bool:
        """A change may raise PAUSE now: armed, ``pause_on_change`` set, the latch not set."""
        with self._lock:
            return self.armed and bool(self.params["pause_on_change"]) and not self.latched

    def state_fields(self) -> dict[str, Any]:
        """state, paused, armed, station, last_check, faults: one consistent snapshot."""
        with self._lock:
            return {"state": self.reported_state().name.lower(), "paused": self.latched,
                    "armed": self.armed, "station": self.station,
                    "last_check": dict(self.last_check) or None, "faults": list(self.faults)}

    def reported_state(self) -> ModuleState:
        """The state HEARTBEAT and STATUS show."""
        with self._lock:
            if self.stalled or (not self.camera_ok and self._camera_reported is False):
                return ModuleState.FAULT
            if self.activity == ModuleState.IDLE and self.latched:
                return ModuleState.PAUSED
            return self.activity

    def status(self) -> Status:
        """What STATUS_QUERY answers."""
        with self._lock:
            counts = self.frames.counts()
            return Status(self.reported_state(), self.latched, self.armed, not self.camera_ok,
                          min(0xFFFF, round(self.fps() * 10)), self.last_frame_index & 0xFFFF_FFFF,
                          counts["dropped"] & 0xFFFF_FFFF,
                          int(time.monotonic() - self.started_at) & 0xFFFF_FFFF, self.station)

    # -- link thread ----------------------------------------------------------------------------

    def _link_main(self) -> None:
        while not self._stop.is_set():
            self.progress.beat("link")
            for event in self.runner.step():
                try:
                    self._on_event(event)
                except Exception:  # noqa: BLE001 -- a bad command must not stop the link
                    log.exception("handling %r failed", event)
                    self.send_fault(FaultCode.INTERNAL_ERROR, "internal error handling a command; "
                                "see the module's log")

    def _on_event(self, event: Any) -> None:
        if isinstance(event, Received):
            self._on_message(event.message)
        elif isinstance(event, Delivered):
            if isinstance(event.message, Pause):
                self._pause_undelivered = False
            elif isinstance(event.message, Fault) and self.stalled:
                self.stall_told.set()
        elif isinstance(event, SendFailed):
            self._throttled(f"failed-{event.message.TYPE.name}", logging.WARNING,
                            "%s seq %d not delivered: %s", event.message.TYPE.name, event.seq,
                            event.reason)
            self.counters["send_failed"] += 1
            if isinstance(event.message, Pause):
                self._pause_undelivered = True
        elif isinstance(event, StateChanged):
            log.log(logging.WARNING if event.new != LinkState.UP else logging.INFO,
                    "link %s: %s", event.new.value, event.why)
            if event.new == LinkState.UP and event.old != LinkState.CONNECTING and self.latched:
                log.info("link back up with the pause latch set: sending PAUSE again")
                self._send(Pause(self._last_pause_cause))
        elif isinstance(event, PortProblem):
            log.log(logging.INFO if event.up else logging.ERROR, "serial port %s: %s",
                    "back" if event.up else "lost", event.detail)

    def _on_message(self, m: Any) -> None:
        if isinstance(m, BaseHeartbeat):
            self.motion = m.motion
            return
        if isinstance(m, (CaptureReference, Check, Watch)):
            self._admitted = max(0, self._admitted - 1)
            try:
                self._commands.put_nowait(m)
            except queue.Full:  # version 1/2 (version 3 NAKs BUSY before the ACK: _admit)
                self.counters["commands_refused"] += 1
                self.send_fault(FaultCode.COMMAND_REFUSED, f"{m.TYPE.name} {m.station} refused: "
                                f"busy, {self.options.command_queue} commands already waiting "
                                f"({self.counters['commands_refused']} refused so far)",
                                coalesce="busy")
                return
            if self._watch is not None:  # a new command ends the watch at once
                self._cancel.set()
            self._wake.set()
            return
        if isinstance(m, StatusQuery):
            self._send(self.status(), coalesce="status")
        elif isinstance(m, Arm):
            with self._lock:
                self.armed = True
            log.info("armed: a change raises PAUSE")
        elif isinstance(m, Disarm):
            with self._lock:
                self.armed = False
            log.info("disarmed: changes are reported, no PAUSE")
        elif isinstance(m, Resume):
            with self._lock:
                was, self.latched = self.latched, False
                self._pause_undelivered = False
            if was:
                log.info("RESUME: pause latch cleared")
        elif isinstance(m, Stop):
            self._cancel.set()
            self._wake.set()
            log.info("STOP")
        elif isinstance(m, GetParam):
            name = PARAM_BY_ID[m.param].name
            self._send(ParamValue(m.param, self.params[name]), coalesce=("param", m.param))
        elif isinstance(m, SetParam):
            self._set_param(m.param, m.value)
        self._refresh_heartbeat(force=True)

    def _set_param(self, pid: int, value: int) -> None:
        name = PARAM_BY_ID[pid].name  # the protocol already NAKed unknown ids and bounds
        with self._lock:
            trial = dict(self.params, **{name: value})
            if trial["watch_m"] > trial["watch_n"]:
                self.send_fault(FaultCode.COMMAND_REFUSED,
                            f"SET_PARAM {name}={value} refused: watch_m ({trial['watch_m']}) "
                            f"must be <= watch_n ({trial['watch_n']})")
                self._send(ParamValue(pid, self.params[name]), coalesce=("param", pid))
                return
            self.params = trial
            if self._watch is not None:
                self._watch.configure(self.params, change_params(self.config, self.params))
        log.info("parameter %s = %d", name, value)
        self._send(ParamValue(pid, value), coalesce=("param", pid))

    # -- sending (send_fault, send_pause, send_report and send_no_change are also what a
    # -- watch calls: robot_change.service.watch.WatchHost) -------------------------------------

    def _admit(self, m: Message) -> NakReason | None:
        """Version 3: refuse a command the module cannot take now with NAK BUSY, before it is
        acknowledged (docs/protocol.md 7.12).  Answers to queries are coalesced instead."""
        if not isinstance(m, (CaptureReference, Check, Watch)):
            return None
        # commands admitted in this turn of the link thread are queued after it (_on_message)
        if self.link.version < 3 or self._commands.qsize() + self._admitted < self.options.command_queue:
            self._admitted += 1
            return None
        self.counters["commands_refused"] += 1
        self._throttled("busy", logging.WARNING, "%s %s refused (NAK BUSY): %d commands "
                        "already waiting", m.TYPE.name, m.station, self.options.command_queue)
        return NakReason.BUSY

    def _send(self, message: Any, coalesce: Any = None) -> None:
        try:
            self.runner.send(message, coalesce=coalesce)
        except Exception:  # noqa: BLE001 -- e.g. a message field out of range: log, go on
            log.exception("cannot send %s", type(message).__name__)

    def send_fault(self, code: FaultCode, text: str, coalesce: Any = None) -> None:
        """FAULT to the base; the log has ``text`` whole, the wire without this machine's
        paths (wire_text)."""
        if coalesce is None:
            (log.info if code == FaultCode.CLEARED else log.error)("FAULT %s: %s", code.name, text)
        else:
            self._throttled(f"fault-{coalesce}", logging.ERROR, "FAULT %s: %s", code.name, text)
        self.counters[f"fault_{code.name.lower()}"] += 1
        self.faults.append({"time": utc_text(time.time()), "code": code.name,
                            "text": _short(wire_text(text))})
        if self.link.version < 2:
            code = V1_FAULT_CODE.get(code, code)
        self._send(Fault(code, _short(wire_text(text))), coalesce=coalesce)

    def send_pause(self, cause: PauseCause) -> None:
        with self._lock:
            self.latched = True
            self._last_pause_cause = cause
        self._send(Pause(V1_PAUSE_CAUSE.get(cause, cause) if self.link.version < 2 else cause))
        self.counters["pauses"] += 1
        log.warning("PAUSE %s", cause.name)
        self._refresh_heartbeat(force=True)

    def send_report(self, station: str, changes: ChangeSet) -> int:
        """CHECK_RESULT (version 2) then the CHANGE_REPORT parts; regions in base_link in
        version 2, in the camera optical frame in version 1."""
        regions = self._kept_regions(changes)
        with self._lock:
            self._report_id = self._report_id % 0xFFFF + 1
            report_id = self._report_id
        v2 = self.link.version >= 2
        mount = self.config.camera.mount()
        if v2:
            self._send(check_result(station, changes, mount, report_id))
        for part in split_change_report(report_id, station,
                                        _wire_regions(regions, mount if v2 else None)):
            self._send(part)
        self._to_fleet(station, changes, report_id)
        return report_id

    def send_no_change(self, station: str, changes: ChangeSet) -> None:
        """CHECK_RESULT (version 2) then CLEAR."""
        if self.link.version >= 2:
            self._send(check_result(station, changes, self.config.camera.mount()))
        self._send(Clear(station))
        self._to_fleet(station, changes)

    def _answer_not_at_station(self, station: str, changes: ChangeSet, what: str) -> None:
        """CHECK_RESULT NOT_AT_STATION (version 2), or FAULT COMMAND_REFUSED (version 1)."""
        offset = self.config.camera.mount().offset(changes.registration)
        text = (f"{what} {station}: not at the station ({changes.not_at_station_reason}); "
                f"offset {[round(v, 2) for v in offset.translation_m]} m "
                f"{[round(v, 1) for v in offset.rpy_deg]} deg")
        log.warning("%s", text)
        self.counters["not_at_station"] += 1
        if self.link.version >= 2:
            self._send(check_result(station, changes, self.config.camera.mount()))
        else:
            self._send(Fault(FaultCode.COMMAND_REFUSED, _short(text)))
        self._to_fleet(station, changes)

    def _to_fleet(self, station: str, changes: ChangeSet, report_id: int | None = None) -> None:
        """A check told to the base goes to the fleet too, after the base's messages: queued
        at once (the report is made on the fleet's writer thread), never waited for."""
        if self.fleet is None:
            return
        mount = self.config.camera.mount()
        self.fleet.report(station, lambda: check_report(station, changes, mount),
                          origin="watch" if self._watch is not None else "check",
                          link_report_id=report_id, changed=report_id is not None)

    def _kept_regions(self, changes: ChangeSet) -> list[ChangeRegion]:
        """The regions of a ChangeSet to report, largest first, at most MAX_REPORT_REGIONS (the
        size limits of the wire's parameters were applied by the check itself:
        robot_change.service.params.change_params)."""
        kept = sorted(changes.regions, key=lambda r: -r.n_points)
        return kept[:MAX_REPORT_REGIONS]

    def _refresh_heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._heartbeat_at < 0.1:
            return
        self._heartbeat_at = now
        with self._lock:
            beat = Heartbeat(self.reported_state(), self.latched, self.armed,
                             not self.camera_ok or bool(self.stalled),
                             min(0xFFFF, round(self.fps() * 10)), self.last_frame_index & 0xFFFF_FFFF)
        self.runner.set_heartbeat(beat)

    # -- controller thread ----------------------------------------------------------------------

    def _control_main(self) -> None:
        while not self._stop.is_set():
            self.progress.beat("control")
            self._wake.wait(0.05)
            self._wake.clear()
            self._tick()
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                command = None
            if command is not None:
                self._run_command(command)

    def _tick(self) -> None:
        """Frames, camera transitions, the watch, the heartbeat: everything but commands."""
        self._camera_transitions()
        for frame, _arrived, seq in self.frames.drain():
            self.last_frame_index = frame.index
            if self._watch is not None:
                self._watch.frame(frame, seq)
        if self._watch is not None:
            if self._cancel.is_set():  # STOP, or a new command (which ends the watch itself)
                self._cancel.clear()
                if self._commands.empty():
                    self._end_watch()
                    self._refresh_heartbeat(force=True)
            elif not self._watch.step():
                self._end_watch()
        self._refresh_heartbeat()

    def _start_watch(self, station: str) -> None:
        reference = self.store.load(station)
        o = self.options
        with self._lock:
            self._watch = StationWatch(station, reference, self, self.params,
                                       change_params(self.config, self.params),
                                       GateOptions(o.gate_step, o.gate_pixels, o.gate_fraction,
                                                   o.detector_threads),
                                       self._pool, self.progress, self.counters,
                                       self.watch_log, self._wake.set)
            self.activity = ModuleState.WATCHING
        log.info("WATCH %s: a change in %d of %d checks, every %d ms", station,
                 self.params["watch_m"], self.params["watch_n"], self.params["check_interval_ms"])
        self._refresh_heartbeat(force=True)

    def _end_watch(self) -> None:
        with self._lock:
            watch, self._watch = self._watch, None
            if watch is not None:
                self.activity = ModuleState.IDLE
        if watch is not None:
            watch.close()
        self.progress.forget("watch")

    def _camera_transitions(self) -> None:
        """Tell the base when the camera is lost (FAULT CAMERA_LOST; PAUSE while watching and
        armed) and when it is back (FAULT CLEARED)."""
        ok = self.camera_ok
        if ok == self._camera_reported:
            return
        if ok:
            if self._camera_reported is False:
                self.send_fault(FaultCode.CLEARED, "camera delivering frames again")
        else:
            if not self.camera_error:
                return  # still opening at start: nothing has failed yet
            self.send_fault(FaultCode.CAMERA_LOST, f"{self.camera_error}; retrying")
            watch = self._watch
            if watch is not None:
                watch.camera_lost()
                if self.armed and not self.latched:
                    self.send_pause(PauseCause.CAMERA_LOST)
        self._camera_reported = ok
        self._refresh_heartbeat(force=True)

    def _run_command(self, m: Any) -> None:
        self._cancel.clear()
        self._end_watch()
        with self._lock:
            self.station = m.station
        # a capture or check reads frames and fits: it has more time than a thread turn
        work = self.progress.begin("control", f"{m.TYPE.name} {m.station}",
                                   self.progress.bound_s + self.options.command_allowance_s)
        try:
            if isinstance(m, CaptureReference):
                self._capture(m.station)
            elif isinstance(m, Check):
                self._check(m.station)
            elif isinstance(m, Watch):
                self._start_watch(m.station)
        except ReferenceMissing as exc:
            if exc.quarantined is not None:
                log.error("station %s: corrupt reference quarantined at %s", m.station,
                          exc.quarantined)
            self.send_fault(FaultCode.REFERENCE_MISSING, str(exc))
        except SceneMismatchError as exc:
            self.send_fault(FaultCode.REFERENCE_MISSING, f"station {m.station}: the reference does "
                        f"not fit this camera ({exc}); capture it again")
        except StoreError as exc:
            self.send_fault(FaultCode.STORAGE_ERROR, str(exc))
        except _CameraLost as exc:
            self.send_fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: {exc}")
        except _Cancelled as exc:
            self.send_fault(FaultCode.COMMAND_REFUSED, str(exc))
        except EmptySceneError as exc:
            self.send_fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: the camera sees "
                        f"nothing to compare ({exc})")
        except Exception as exc:  # noqa: BLE001 -- never let a command take the service down
            log.exception("%s %s failed", m.TYPE.name, m.station)
            self.send_fault(FaultCode.INTERNAL_ERROR, f"{m.TYPE.name} {m.station}: internal error "
                        f"{type(exc).__name__}: {exc}")
        finally:
            self.progress.end(work)
            with self._lock:
                if self._watch is None:
                    self.activity = ModuleState.IDLE
            self._refresh_heartbeat(force=True)

    def _set_activity(self, activity: ModuleState) -> None:
        with self._lock:
            self.activity = activity
        self._refresh_heartbeat(force=True)

    def _fresh_frames(self, n: int, what: str) -> list[DepthFrame]:
        """``n`` frames taken after now (older queued ones are passed over), in order."""
        self.frames.drain()
        frames: list[DepthFrame] = []
        per_frame = self.config.camera.read_timeout_s
        deadline = time.monotonic() + per_frame * (n + 1) + 1.0
        while len(frames) < n:
            if self._cancel.is_set():
                raise _Cancelled(f"{what} stopped by STOP or a newer command")
            if self._stop.is_set():
                raise _Cancelled(f"{what}: the service is stopping")
            if not self.camera_ok and self.camera_error:
                raise _CameraLost(self.camera_error)
            if time.monotonic() > deadline:
                raise _CameraLost(f"{len(frames)} of {n} frames within "
                                  f"{per_frame * (n + 1) + 1.0:.1f} s")
            got = self.frames.get(0.05)
            self.progress.beat("control")
            self._camera_transitions()
            self._refresh_heartbeat()
            if got is not None:
                frames.append(got[0])
                self.last_frame_index = got[0].index
        return frames

    def _capture(self, station: str) -> None:
        self.store.path(station)  # a bad name fails before any frame is read
        self._set_activity(ModuleState.CAPTURING)
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CAPTURE_REFERENCE {station}")
        t0 = time.perf_counter()
        model = scene.build_scene(frames, scene_params(self.config, self.params),
                                  source=self.camera_uri, mount=self.config.camera.mount(),
                                  noise=self.config.camera.noise_profile(self.camera.model))
        path = self.store.save(station, model)
        limit = detection_limit(model.depth, model.noise, change_params(self.config, self.params),
                                model.params.cloud.leaf_m, model.intrinsics.fx).median_m
        smallest_mm = min(round(limit * 1000), 0xFFFF) if math.isfinite(limit) else 0
        log.info("station %s: reference of %d frames (%d points, K=%d, noise %s, smallest change "
                 "seen %d mm) built in %.0f ms, saved to %s", station, n, len(model),
                 model.mixture.n_components, model.noise.name, smallest_mm,
                 (time.perf_counter() - t0) * 1e3, path)
        # version 4: what the station can see, with the answer
        self._send(Captured(station, smallest_mm, model.noise.name) if self.link.version >= 4
                   else Captured(station))

    def _check(self, station: str) -> None:
        self._set_activity(ModuleState.CHECKING)
        reference = self.store.load(station)
        mount = self.config.camera.mount()
        if reference.mount is not None and reference.mount != mount:
            log.warning("station %s: its reference was captured with the camera mounted at "
                        "%s, the configuration says %s; base-frame results use the "
                        "configuration (capture the station again if the camera was moved)",
                        station, reference.mount.to_dict(), mount.to_dict())
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CHECK {station}")
        t0 = time.perf_counter()
        stamp_ns = time.time_ns()
        stack = np.stack([f.depth for f in frames])
        depth = stack[0] if n == 1 else fuse_depth(stack, reference.params.min_valid(n))
        changes = detect.detect_changes(reference, depth, change_params(self.config, self.params),
                                        intrinsics=frames[0].intrinsics)
        regions = self._kept_regions(changes)
        ms = (time.perf_counter() - t0) * 1e3
        self.counters["checks"] += 1
        reg = changes.registration
        log.info("CHECK %s: %s in %.0f ms (%d frames fused; registration %.0f mm %.1f deg, "
                 "fitness %.2f)", station, changes.outcome if changes.outcome !=
                 "changed" or not regions else f"{len(regions)} changed region(s)", ms, n,
                 1e3 * float(np.linalg.norm(reg.translation_m)), reg.rotation_deg, reg.fitness)
        self.last_check = {"station": station, "regions": len(regions), "ms": round(ms, 1),
                           "frame_index": frames[-1].index, "outcome": changes.outcome,
                           "time": utc_text(time.time())}
        changed = changes.outcome != "not_at_station" and bool(regions)
        if changed and self.may_pause():
            # the stop first: writing the check's files (compressed, fsynced) takes tens of ms
            self.send_pause(PauseCause.CHANGE_CHECK)
        # written before the answer, so that a base (or a person) told of this check finds them
        self._write_check(station, reference, depth, changes, regions)
        if changes.outcome == "not_at_station":
            self._answer_not_at_station(station, changes, "CHECK")
        elif changed:
            self.send_report(station, changes)
        else:
            self.send_no_change(station, changes)
        # the answers are queued for the link: the view for Foxglove is drawn on its own thread
        self.views.submit(CheckView(station, reference, depth, changes, mount, stamp_ns))

    def _write_check(self, station: str, reference: SceneModel, depth: np.ndarray,
                     changes: ChangeSet, regions: list[ChangeRegion]) -> None:
        folder = self.options.report_dir
        if folder is None:
            return
        try:
            cam = reference.intrinsics
            boxes = np.array([[*r.bbox_min, *r.bbox_max, *r.centroid, r.n_points]
                              for r in regions], dtype=np.float64).reshape(-1, 10)
            kinds = np.array([1 if r.kind == "appeared" else 2 for r in regions], np.uint8)
            Path(folder).mkdir(parents=True, exist_ok=True)
            npzfile.write(Path(folder) / f"{station}.last-check.npz", CHECK_FORMAT, 1, {
                "depth": depth, "reference_depth": reference.depth,
                "appeared_mask": changes.appeared_mask,
                "disappeared_mask": changes.disappeared_mask,
                "intrinsics": np.array([cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy]),
                "region_boxes": boxes, "region_kinds": kinds}, {"station": station})
            report = check_report(station, changes, self.config.camera.mount())
            write_atomically(Path(folder) / f"{station}.last-check.json",
                             (json.dumps(report, indent=1) + "\n").encode())
        except Exception:  # noqa: BLE001 -- a picture for people is never worth a fault
            log.warning("could not write the last check of %s to %s", station, folder,
                        exc_info=True)


class _CameraLost(Exception):
    """No frames for a capture or check."""


class _Cancelled(Exception):
    """STOP (or a newer command) ended a capture or check."""
