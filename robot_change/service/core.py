"""The daemon: commands from the base in, depth frames from the camera, PAUSE and reports out.

The service is handed everything it talks to -- a depth source (or a function that makes one),
an open serial port, a reference store and a configuration -- and never builds hardware itself
(``robot_change.cli`` does, for ``robot-change run``); tests hand it a recording and one end of
a pty pair exactly as the robot hands it a camera and ``/dev/robot-base``.

States (``HEARTBEAT.state``, ``robot_change.link.protocol.ModuleState``)::

    BOOTING --start()--> IDLE      (open_link() first: the link talks while kernels compile)
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

The parts of :class:`Service` live beside it, each a base class of it: the link thread and the
dispatch of commands (``robot_change.service.dispatch``), what it sends
(``robot_change.service.sending``), the controller thread running captures, checks and watches
(``robot_change.service.control``); the wire's forms of a check and a fault
(``robot_change.service.wire``) and the last check's files (``robot_change.service.last_check``)
are functions of their own.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import robot_change
from hw.atomic import remove_temp_files
from hw.depth import DepthSource
from robot_change.fleet.publisher import Publisher
from robot_change.fleet.spool import Spool
from robot_change.link.port import BytePort
from robot_change.link.protocol import (
    FaultCode,
    ModuleState,
    Motion,
    Pause,
    PauseCause,
    Role,
    Status,
)
from robot_change.link.session import Link, LinkConfig, LinkRunner
from robot_change.service.camera import CameraThread, FrameQueue
from robot_change.service.config import Config
from robot_change.service.control import Control
from robot_change.service.dispatch import Dispatch
from robot_change.service.documents import status_document
from robot_change.service.last_check import CHECK_FORMAT
from robot_change.service.liveness import Progress
from robot_change.service.params import change_params
from robot_change.service.sending import Sending
from robot_change.service.store import ReferenceStore
from robot_change.service.views import CheckViews
from robot_change.service.watch import StationWatch
from robot_change.service.wire import MAX_REPORT_REGIONS, check_result, wire_text
from robot_change.throttle import Throttled

#: Service and ServiceOptions, and names re-exported from where they moved (CHECK_FORMAT:
#: robot_change.service.last_check; MAX_REPORT_REGIONS, check_result, wire_text:
#: robot_change.service.wire).
__all__ = ["CHECK_FORMAT", "MAX_REPORT_REGIONS", "Service", "ServiceOptions", "check_result",
           "wire_text"]

log = logging.getLogger(__name__)


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
# the service


class Service(Dispatch, Sending, Control):
    """The daemon's state machine (module docstring).  Make it, :meth:`start` it, and
    :meth:`close` it; everything else arrives over the link.

    ``camera``: a :class:`hw.depth.DepthSource` (reopened with close()/open() after a loss) or
    a callable returning a new unopened one (called again after a loss).  ``port``: an open
    port (pyserial, :class:`hw.serial_port.ReopeningPort`, or anything with read, write,
    in_waiting, fileno).  ``store``: a :class:`robot_change.service.store.ReferenceStore`.

    Its link thread and the dispatch of commands, its sending and its controller thread are
    its base classes :class:`~robot_change.service.dispatch.Dispatch`,
    :class:`~robot_change.service.sending.Sending` and
    :class:`~robot_change.service.control.Control`.
    """

    def __init__(self, config: Config, camera: DepthSource | Callable[[], DepthSource],
                 port: BytePort, store: ReferenceStore, options: ServiceOptions | None = None, *,
                 link_config: LinkConfig | None = None) -> None:
        self.config = config
        self.options = options or ServiceOptions()
        self.store = store
        self.port = port
        self.params: dict[str, int] = dict(config.parameters())
        #: the values the base set with SET_PARAM since this start: a reload keeps them
        self.base_params: dict[str, int] = {}
        self.link = Link(Role.MODULE, config=link_config or LinkConfig.for_baud(config.serial.baud),
                         admit=self._admit)
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
        self.booting = True  # until start(): the heartbeat's state BOOTING
        self.activity = ModuleState.IDLE  # what the controller does (IDLE/CAPTURING/...)
        self.latched = False
        self.armed = True
        self.station = ""
        self.motion = Motion.UNKNOWN
        self._last_pause_cause = PauseCause.CHANGE_CHECK
        self._cancel = threading.Event()
        self._watch: StationWatch | None = None
        self._stale_told: dict[str, str] = {}  # station -> what was said of its reference
        self._report_id = 0
        self._camera_reported = None  # what the controller last told the base: True ok / False lost
        self._lost_pause_due = False  # the camera is lost: a watch pauses once it may
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

    def open_link(self) -> None:
        """Start the link thread alone, the heartbeat's state BOOTING: HELLO, heartbeats and
        the quick commands flow while the kernels compile; CAPTURE_REFERENCE, CHECK and WATCH
        wait in their queue for :meth:`start`.  Once only (:meth:`start` calls it if not)."""
        if any(t.name == "rc-link" for t in self._threads):
            return
        self._refresh_heartbeat(force=True)
        self._start_thread("link", self._link_main)

    def _start_thread(self, name: str, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=self._guard(name, target), name=f"rc-{name}",
                                  daemon=True)
        if name != "monitor":
            self.progress.beat(name)
        self._threads.append(thread)
        thread.start()

    def start(self) -> None:
        """Start the camera and controller threads, and the link's if :meth:`open_link` did
        not (call :func:`warm_up` first): the state IDLE."""
        self.store.recover()  # references/ and quarantine/; the fleet's spool: Spool()
        if self.options.report_dir is not None:
            reports = Path(self.options.report_dir)
            for folder in (reports, reports / "checks"):
                try:
                    if remove_temp_files(folder):
                        log.info("removed temp files left by an interrupted write in %s", folder)
                except OSError as exc:  # its files are lost, never the service
                    log.warning("%s: %s; the checks' files cannot be written there until the "
                                "service's user owns it", folder, exc.strerror or exc)
        self._pool = concurrent.futures.ThreadPoolExecutor(self.options.detector_threads,
                                                           thread_name_prefix="detector")
        self.views.start()
        self.open_link()
        with self._lock:
            self.booting = False
        self._refresh_heartbeat(force=True)
        for name, target in (("camera", self.camera.run), ("control", self._control_main),
                             ("monitor", self._monitor_main)):
            self._start_thread(name, target)
        if self.fleet is not None:
            if self.fleet.settings.cleartext_warning():
                log.warning("fleet: %s", self.fleet.settings.cleartext_warning())
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

    def __enter__(self) -> Service:
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
                self.report_stall(why)

    def report_stall(self, why: str) -> None:
        """A part stalled (the monitor thread; the daemon, for a warm-up past its deadline).
        Tell the base first: FAULT STALLED, PAUSE when armed and watching (a stalled watcher
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

    def reload(self, config: Config,
               camera: DepthSource | Callable[[], DepthSource] | None = None) -> None:
        """Take a new configuration (SIGHUP): the parameter table is reseeded from it, but for
        the values the base set (SET_PARAM: they stay until the next start, docs/protocol.md
        7.9), and a new ``camera`` (when given) replaces the old one: it is closed and the new
        one opened."""
        with self._lock:
            old = self.config
            self.config = config
            params = dict(config.parameters(), **self.base_params)
            if params["watch_m"] > params["watch_n"]:  # the file's one against the base's other
                log.warning("reload: watch_m %d > watch_n %d (the file's and the base's "
                            "SET_PARAM together): both kept at %d of %d", params["watch_m"],
                            params["watch_n"], self.params["watch_m"], self.params["watch_n"])
                params.update(watch_m=self.params["watch_m"], watch_n=self.params["watch_n"])
            self.params = params
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
            if self.stalled:
                return ModuleState.FAULT
            if self.booting:
                return ModuleState.BOOTING
            if not self.camera_ok and self._camera_reported is False:
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
