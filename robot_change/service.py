"""The daemon: commands from the base in, depth frames from the camera, PAUSE and reports out.

The service is handed everything it talks to -- a depth source (or a function that makes one),
an open serial port, a reference store and a configuration -- and never builds hardware itself
(``robot_change.cli`` does, for ``robot-change run``); tests hand it a recording and one end of
a pty pair exactly as the robot hands it a camera and ``/dev/robot-base``.

States (``HEARTBEAT.state``, ``robot_change.protocol.ModuleState``)::

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
frames (per-pixel median) and compares them with the station's reference; WATCH checks the
newest frame every ``check_interval_ms`` and at once when a cheap per-frame depth gate sees the
scene differ from what the last check saw, and raises PAUSE when a change is seen in
``watch_m`` of the last ``watch_n`` checks (once per change: CLEAR when ``watch_m`` of the last
``watch_n`` checks saw none, after which a new change pauses again).  A watch checks only while
the base's heartbeat says PARKED or PAUSED.  A check that sees nothing to compare (no depth:
covered lens, something against the camera) counts as a change in WATCH (PAUSE cause
CAMERA_LOST) and is a FAULT CAMERA_LOST for CHECK.  A recording that ends counts as a lost
camera (it is reopened, so it plays again); ``oni:...?loop=1&rate=auto`` plays one like a
camera.  SET_PARAM ``max_depth_mm`` applies to references captured after it (a check cleans
its frames with its reference's parameters); the other parameters apply at once.

Threads and queues (nothing grows without bound)::

    camera    source.read() at camera rate -> FrameQueue (bounded, oldest dropped and counted);
              on loss: FAULT via the controller, close, reopen with backoff 0.5 s .. 10 s
    link      LinkRunner.run(): bytes <-> messages; quick commands answered here
    control   commands (bounded queue), frames, capture / check / watch, heartbeat contents
    detector  <= 2 threads running WATCH checks (numba kernels release the GIL), so a change
              that shows while a scheduled check runs is checked at once, not after it

Every frame the camera delivers is accounted for: ``received == processed + dropped +
queued`` (:meth:`Service.frame_counts`).  Bad input never stops the service: garbage on the line
is NAKed by the link, a corrupt reference is quarantined by the store and reported (FAULT
REFERENCE_MISSING), and an exception inside a command is logged and answered with FAULT
INTERNAL_ERROR while the service carries on.

:func:`run_service` is the daemon's main loop around a :class:`Service`: systemd READY once the
numba kernels are compiled or loaded (:func:`warm_up`), WATCHDOG while the threads are alive,
SIGHUP reloads the configuration (a new camera source is reopened; a bad file keeps the old
configuration), SIGTERM stops cleanly.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import queue
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

import robot_change
from hw.depth import DepthFrame, DepthSource, Intrinsics
from hw.errors import DeviceLost, FrameTimeout, HwError
from robot_change import systemd
from robot_change.config import Config
from robot_change.errors import (
    ConfigError,
    EmptySceneError,
    InputError,
    ReferenceMissing,
    SceneMismatchError,
    StoreError,
)
from robot_change.link import (
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
from robot_change.protocol import (
    PARAM_BY_ID,
    REGIONS_PER_PART,
    Arm,
    BaseHeartbeat,
    Captured,
    CaptureReference,
    Check,
    Clear,
    Disarm,
    Fault,
    FaultCode,
    GetParam,
    Heartbeat,
    ModuleState,
    Motion,
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

__all__ = ["FrameQueue", "Service", "ServiceOptions", "run_service", "warm_up", "depth_gate"]

log = logging.getLogger(__name__)

#: Camera reopen backoff: first wait and cap, seconds.
CAMERA_BACKOFF = (0.5, 10.0)
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
    regions; ``<station>.last-check.npz``) for people and ``robot-change demo``; None: nowhere.
    ``link_max_wait``: the link thread's longest sleep (s), bounding the added send latency.
    """

    queue_frames: int = 4
    detector_threads: int = 2
    gate_step: int = 4
    gate_pixels: int = 50
    gate_fraction: float = 0.2
    report_dir: Path | None = None
    link_max_wait: float = 0.005
    command_queue: int = 16


# ---------------------------------------------------------------------------------------------
# the frame queue


class FrameQueue:
    """A bounded queue of depth frames: ``put`` never blocks (a full queue drops its oldest
    frame and counts it), ``get`` waits at most its timeout.

    ``received == processed + dropped + len(queue)`` at every moment (:meth:`counts`).
    """

    def __init__(self, size: int = 4, on_put: Callable[[], None] | None = None) -> None:
        if size < 1:
            raise ValueError(f"FrameQueue size {size}: at least 1")
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
        """The oldest (frame, arrival time, sequence number), waiting at most ``timeout`` s; None if none."""
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


# ---------------------------------------------------------------------------------------------
# helpers


def depth_gate(reference: np.ndarray, depth: np.ndarray, step: int = 4) -> int:
    """How many sampled pixels (every ``step``-th of every ``step``-th row) read nearer or
    farther than the reference by more than the sensor's noise (30 mm + 4 mm per m^2).

    A cheap per-frame trigger for WATCH checks, never a decision: a jump in this count means the
    scene is no longer what the last check saw, so a check runs at once.  ~0.3 ms at VGA.
    """
    r = reference[::step, ::step].astype(np.float32)
    c = depth[::step, ::step].astype(np.float32)
    both = (r > 0) & (c > 0)
    margin = 30.0 + 4e-6 * r * r
    return int(np.count_nonzero(both & (np.abs(c - r) > margin)))


def _clip(value: float, lo: int, hi: int) -> int:
    return int(min(hi, max(lo, round(value))))


def _wire_regions(regions: list[Any]) -> list[Region]:
    """change.Region (metres) -> protocol.Region (mm, clipped to the field widths)."""
    out = []
    for r in regions:
        kind = RegionKind.APPEARED if r.kind == "appeared" else RegionKind.DISAPPEARED
        centroid = tuple(_clip(v * 1000.0, -32768, 32767) for v in r.centroid)
        extent = tuple(_clip(v * 1000.0, 0, 65535) for v in r.extent)
        out.append(Region(kind, centroid, extent, _clip(r.n_points, 0, 0xFFFF_FFFF)))
    return out


def _short(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text.encode()) <= _FAULT_TEXT else text.encode()[:_FAULT_TEXT - 3].decode(
        "utf-8", "ignore") + "..."


def change_params(config: Config, params: dict[str, int]):
    """The :class:`robot_change.change.ChangeParams` of a check: the configuration's free-form
    ``[change]`` keys that name ChangeParams fields, and the wire's ``min_region_points``."""
    from robot_change.change import ChangeParams

    fields = {f.name for f in dataclasses.fields(ChangeParams)}
    extra = {k: v for k, v in dict(config.change.extra).items() if k in fields}
    extra["min_region_points"] = int(params["min_region_points"])
    try:
        return ChangeParams(**extra)
    except InputError as exc:
        raise ConfigError(f"[change]: {exc}") from None


def scene_params(config: Config, params: dict[str, int]):
    """SceneParams of a new reference: the configuration's, with the wire's ``max_depth_mm``.
    (A check cleans its frames with its reference's parameters, so a changed ``max_depth_mm``
    applies to references captured after the change.)"""
    base = config.scene_params()
    cloud = dataclasses.replace(base.cloud, max_depth_m=params["max_depth_mm"] / 1000.0)
    if cloud.min_depth_m >= cloud.max_depth_m:
        cloud = base.cloud
    return dataclasses.replace(base, cloud=cloud)


def _synthetic_room(width: int = 160, height: int = 120, box: bool = False) -> np.ndarray:
    """A small synthetic depth image: floor, back wall, a side wall, optionally a box."""
    cam = Intrinsics.openni_default(width, height)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (u - cam.cx) / cam.fx
    y = (v - cam.cy) / cam.fy
    z = np.full((height, width), 3.0)  # back wall 3 m ahead
    floor = np.where(y > 1e-6, 1.0 / np.maximum(y, 1e-6), np.inf)  # floor 1 m below the camera
    z = np.minimum(z, floor)
    side = np.where(x > 1e-6, 1.2 / np.maximum(x, 1e-6), np.inf)  # wall 1.2 m to the right
    z = np.minimum(z, side)
    if box:
        px, py = x * 2.0, y * 2.0  # a 40 cm box standing 2 m ahead
        inside = (np.abs(px + 0.2) < 0.2) & (py > 0.6) & (py < 1.0)
        z = np.where(inside, np.minimum(z, 2.0), z)
    ripple = 0.002 * np.sin(u * 0.7) * np.cos(v * 0.5)
    return np.clip((z + ripple) * 1000.0, 0, 65535).astype(np.uint16)


def warm_up(config: Config | None = None) -> float:
    """Compile (or load from the numba cache) every kernel a capture and a check use, on a tiny
    synthetic scene; returns the seconds it took."""
    from robot_change.change import detect_changes
    from robot_change.scene import build_scene

    config = config or Config()
    t0 = time.perf_counter()
    width, height = 160, 120
    cam = Intrinsics.openni_default(width, height)
    params = config.scene_params()
    # regions of any size, so that every stage runs on the tiny scene (both directions)
    change = change_params(config, config.parameters()).replace(min_region_points=1)
    rooms = (_synthetic_room(width, height), _synthetic_room(width, height, box=True))
    for before, after in (rooms, rooms[::-1]):
        try:
            reference = build_scene(np.stack([before] * 2), params, intrinsics=cam,
                                    source="warm-up")
            detect_changes(reference, after, change)
        except (EmptySceneError, InputError):
            pass  # a tiny scene may be too small for some parameter set; kernels ran anyway
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------
# the service


@dataclasses.dataclass
class _WatchJob:
    seq: int  # the frame's sequence number in the FrameQueue
    frame_index: int
    future: concurrent.futures.Future
    submitted: float


class _Watch:
    """What a WATCH keeps: the station's reference, the persistence window, jobs in flight."""

    def __init__(self, station: str, reference: Any, n: int) -> None:
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


class Service:
    """The daemon's state machine (module docstring).  Make it, :meth:`start` it, and
    :meth:`close` it; everything else arrives over the link.

    ``camera``: a :class:`hw.depth.DepthSource` (reopened with close()/open() after a loss) or
    a callable returning a new unopened one (called again after a loss).  ``port``: an open
    port (pyserial, :class:`hw.serial_port.ReopeningPort`, or anything with read, write,
    in_waiting, fileno).  ``store``: a :class:`robot_change.store.ReferenceStore`.
    """

    def __init__(self, config: Config, camera: DepthSource | Callable[[], DepthSource], port: Any,
                 store: Any, options: ServiceOptions | None = None, *,
                 link_config: LinkConfig | None = None) -> None:
        self.config = config
        self.options = options or ServiceOptions()
        self.store = store
        self.port = port
        self.params: dict[str, int] = dict(config.parameters())
        self.link = Link(Role.MODULE, config=link_config or LinkConfig.for_baud(config.serial.baud),
                         software=f"robot-change {robot_change.__version__}")
        self.runner = LinkRunner(self.link, port, max_wait=self.options.link_max_wait)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.frames = FrameQueue(self.options.queue_frames, on_put=self._wake.set)
        self._commands: queue.Queue = queue.Queue(maxsize=self.options.command_queue)
        self._camera = camera
        self._camera_swap: Any = None
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
        self._watch: _Watch | None = None
        self._report_id = 0
        # camera (written by the camera thread)
        self.camera_ok = False
        self.camera_error = ""
        self.camera_losses = 0
        self.camera_uri = ""
        self._camera_reported = None  # what the controller last told the base: True ok / False lost
        self._arrivals: collections.deque[float] = collections.deque(maxlen=31)
        self.last_frame_index = 0
        self._alive: dict[str, float] = {}
        self.counters = collections.Counter()
        self.last_check: dict[str, Any] = {}
        #: the last WATCH results, newest last: t, seq, frame_index, changed, changed_in_window,
        #: action ("pause", "report", "clear" or "")
        self.watch_log: collections.deque[dict[str, Any]] = collections.deque(maxlen=256)
        self._heartbeat_at = 0.0

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start the link, camera and controller threads (call :func:`warm_up` first)."""
        removed = self.store.remove_stale_temp_files()
        if removed:
            log.info("removed %d temp file(s) left by an interrupted write", len(removed))
        self._pool = concurrent.futures.ThreadPoolExecutor(self.options.detector_threads,
                                                           thread_name_prefix="detector")
        with self._lock:
            self.state = ModuleState.IDLE
        self._refresh_heartbeat(force=True)
        for name, target in (("link", self._link_main), ("camera", self._camera_main),
                             ("control", self._control_main)):
            thread = threading.Thread(target=self._guard(name, target), name=f"rc-{name}",
                                      daemon=True)
            self._alive[name] = time.monotonic()
            self._threads.append(thread)
            thread.start()
        log.info("service started: store %s, link %s", self.store.root,
                 getattr(self.port, "url", None) or getattr(self.port, "name", None) or self.port)

    def close(self, timeout: float = 5.0) -> None:
        """Stop every thread, close the camera; the port stays the caller's."""
        self._stop.set()
        self._wake.set()
        end = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.1, end - time.monotonic()))
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        stuck = [t.name for t in self._threads if t.is_alive()]
        if stuck:
            log.warning("threads still running at exit: %s", ", ".join(stuck))

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

    def healthy(self, limits: dict[str, float] | None = None) -> tuple[bool, str]:
        """Are the threads alive and turning?  (for the systemd watchdog)"""
        limits = limits or {"link": 5.0, "camera": 30.0, "control": 30.0}
        now = time.monotonic()
        for thread in self._threads:
            if not thread.is_alive():
                return False, f"thread {thread.name} ended"
        for name, limit in limits.items():
            seen = self._alive.get(name)
            if seen is not None and now - seen > limit:
                return False, f"the {name} thread has not turned for {now - seen:.1f} s"
        return True, "ok"

    def reload(self, config: Config, camera: DepthSource | Callable[[], DepthSource] | None = None) -> None:
        """Take a new configuration (SIGHUP): the parameter table is reseeded from it, and a new
        ``camera`` (when given) replaces the old one: it is closed and the new one opened."""
        with self._lock:
            old = self.config
            self.config = config
            self.params = dict(config.parameters())
            if self._watch is not None:
                self._watch.window = collections.deque(self._watch.window,
                                                       maxlen=self.params["watch_n"])
        if config.serial != old.serial:
            log.warning("[serial] changed in the configuration: restart the service to use it")
        if config.store != old.store:
            log.warning("[store] changed in the configuration: restart the service to use it")
        if camera is not None:
            self._camera_swap = camera
            log.info("configuration reloaded; reopening the camera")
        else:
            log.info("configuration reloaded")

    # -- public views -----------------------------------------------------------------------

    def frame_counts(self) -> dict[str, int]:
        """received, processed, dropped, queued: received == processed + dropped + queued."""
        return self.frames.counts()

    def fps(self) -> float:
        """Camera frames per second over the last second or so (0 when frames stopped)."""
        times = list(self._arrivals)
        if len(times) < 2 or time.monotonic() - times[-1] > 1.0:
            return 0.0
        span = times[-1] - times[0]
        return (len(times) - 1) / span if span > 0 else 0.0

    def reported_state(self) -> ModuleState:
        """The state HEARTBEAT and STATUS show."""
        with self._lock:
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

    # -- link thread ----------------------------------------------------------------------------

    def _link_main(self) -> None:
        while not self._stop.is_set():
            self._alive["link"] = time.monotonic()
            for event in self.runner.step():
                try:
                    self._on_event(event)
                except Exception:  # noqa: BLE001 -- a bad command must not stop the link
                    log.exception("handling %r failed", event)
                    self._fault(FaultCode.INTERNAL_ERROR, "internal error handling a command; "
                                "see the module's log")

    def _on_event(self, event: Any) -> None:
        if isinstance(event, Received):
            self._on_message(event.message)
        elif isinstance(event, Delivered):
            if isinstance(event.message, Pause):
                self._pause_undelivered = False
        elif isinstance(event, SendFailed):
            log.warning("%s seq %d not delivered: %s", event.message.TYPE.name, event.seq,
                        event.reason)
            self.counters["send_failed"] += 1
            if isinstance(event.message, Pause):
                self._pause_undelivered = True
        elif isinstance(event, StateChanged):
            log.log(logging.WARNING if event.new != LinkState.UP else logging.INFO,
                    "link %s: %s", event.new.value, event.why)
            if event.new == LinkState.UP and self.latched and self._pause_undelivered:
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
            try:
                self._commands.put_nowait(m)
            except queue.Full:
                self._fault(FaultCode.COMMAND_REFUSED, f"{m.TYPE.name} {m.station} refused: "
                            f"{self.options.command_queue} commands already waiting")
                return
            if self._watch is not None:  # a new command ends the watch at once
                self._cancel.set()
            self._wake.set()
            return
        if isinstance(m, StatusQuery):
            self._send(self.status())
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
            self._send(ParamValue(m.param, self.params[name]))
        elif isinstance(m, SetParam):
            self._set_param(m.param, m.value)
        self._refresh_heartbeat(force=True)

    def _set_param(self, pid: int, value: int) -> None:
        name = PARAM_BY_ID[pid].name  # the protocol already NAKed unknown ids and bounds
        with self._lock:
            trial = dict(self.params, **{name: value})
            if trial["watch_m"] > trial["watch_n"]:
                self._fault(FaultCode.COMMAND_REFUSED,
                            f"SET_PARAM {name}={value} refused: watch_m ({trial['watch_m']}) "
                            f"must be <= watch_n ({trial['watch_n']})")
                self._send(ParamValue(pid, self.params[name]))
                return
            self.params = trial
            if name == "watch_n" and self._watch is not None:
                self._watch.window = collections.deque(self._watch.window, maxlen=value)
        log.info("parameter %s = %d", name, value)
        self._send(ParamValue(pid, value))

    # -- sending --------------------------------------------------------------------------------

    def _send(self, message: Any) -> None:
        try:
            self.runner.send(message)
        except Exception:  # noqa: BLE001 -- e.g. a message field out of range: log, go on
            log.exception("cannot send %s", type(message).__name__)

    def _fault(self, code: FaultCode, text: str) -> None:
        (log.info if code == FaultCode.CLEARED else log.error)("FAULT %s: %s", code.name, text)
        self.counters[f"fault_{code.name.lower()}"] += 1
        self._send(Fault(code, _short(text)))

    def _pause(self, cause: PauseCause) -> None:
        with self._lock:
            self.latched = True
            self._last_pause_cause = cause
        self._send(Pause(cause))
        self.counters["pauses"] += 1
        log.warning("PAUSE %s", cause.name)
        self._refresh_heartbeat(force=True)

    def _report(self, station: str, changes: Any) -> int:
        regions = self._kept_regions(changes)
        with self._lock:
            self._report_id = self._report_id % 0xFFFF + 1
            report_id = self._report_id
        for part in split_change_report(report_id, station, _wire_regions(regions)):
            self._send(part)
        return report_id

    def _kept_regions(self, changes: Any) -> list[Any]:
        """Regions of a ChangeSet that pass the wire's size limits, largest first."""
        min_points = self.params["min_region_points"]
        min_extent = self.params["min_region_extent_mm"] / 1000.0
        kept = [r for r in changes.regions
                if r.n_points >= min_points and float(np.max(r.extent)) >= min_extent]
        kept.sort(key=lambda r: -r.n_points)
        return kept[:MAX_REPORT_REGIONS]

    def _refresh_heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._heartbeat_at < 0.1:
            return
        self._heartbeat_at = now
        with self._lock:
            beat = Heartbeat(self.reported_state(), self.latched, self.armed, not self.camera_ok,
                             min(0xFFFF, round(self.fps() * 10)), self.last_frame_index & 0xFFFF_FFFF)
        self.runner.set_heartbeat(beat)

    # -- camera thread --------------------------------------------------------------------------

    def _make_source(self) -> DepthSource:
        if self._camera_swap is not None:
            self._camera, self._camera_swap = self._camera_swap, None
        cam = self._camera
        source = cam if isinstance(cam, DepthSource) else cam()
        source.open()
        self.camera_uri = getattr(source, "uri", "") or type(source).__name__
        log.info("camera %s open", self.camera_uri)
        return source

    def _camera_main(self) -> None:
        backoff = CAMERA_BACKOFF[0]
        source: DepthSource | None = None
        try:
            while not self._stop.is_set():
                self._alive["camera"] = time.monotonic()
                if self._camera_swap is not None and source is not None:
                    self._close_source(source)
                    source = None
                    backoff = CAMERA_BACKOFF[0]
                if source is None:
                    try:
                        source = self._make_source()
                    except Exception as exc:  # noqa: BLE001 -- any failure to open is a lost camera
                        self._camera_down(f"cannot open the camera: {exc}")
                        self._sleep(backoff)
                        backoff = min(backoff * 2, CAMERA_BACKOFF[1])
                        continue
                try:
                    frame = source.read(timeout=self.config.camera.read_timeout_s)
                except (FrameTimeout, DeviceLost, HwError, OSError) as exc:
                    why = str(exc)
                    frame = None
                else:
                    why = f"{getattr(source, 'uri', 'the recording')}: the recording ended"
                if frame is None:
                    self._camera_down(why)
                    self._close_source(source)
                    source = None
                    self._sleep(backoff)
                    backoff = min(backoff * 2, CAMERA_BACKOFF[1])
                    continue
                backoff = CAMERA_BACKOFF[0]
                self._arrivals.append(time.monotonic())
                if not self.camera_ok:
                    self.camera_ok, self.camera_error = True, ""
                    log.info("camera delivering frames (frame %d)", frame.index)
                    self._wake.set()
                self.frames.put(frame)
        finally:
            if source is not None:
                self._close_source(source)

    def _camera_down(self, why: str) -> None:
        if self.camera_ok or not self.camera_error:
            self.camera_losses += 1
            log.error("camera lost: %s", why)
        self.camera_ok, self.camera_error = False, why
        self._wake.set()

    def _close_source(self, source: DepthSource) -> None:
        try:
            source.close()
        except Exception:  # noqa: BLE001 -- closing a lost device may fail any way it likes
            log.debug("closing the camera failed", exc_info=True)

    def _sleep(self, seconds: float) -> None:
        """Sleep in short steps, marking the thread alive (the watchdog keeps being fed)."""
        end = time.monotonic() + seconds
        while not self._stop.is_set() and self._camera_swap is None:
            left = end - time.monotonic()
            if left <= 0:
                return
            self._alive["camera"] = time.monotonic()
            self._stop.wait(min(0.1, left))

    # -- controller thread ----------------------------------------------------------------------

    def _control_main(self) -> None:
        while not self._stop.is_set():
            self._alive["control"] = time.monotonic()
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
                self._watch_frame(frame, seq)
        if self._watch is not None:
            self._watch_step()
        self._refresh_heartbeat()

    def _camera_transitions(self) -> None:
        """Tell the base when the camera is lost (FAULT CAMERA_LOST; PAUSE while watching and
        armed) and when it is back (FAULT CLEARED)."""
        ok = self.camera_ok
        if ok == self._camera_reported:
            return
        if ok:
            if self._camera_reported is False:
                self._fault(FaultCode.CLEARED, "camera delivering frames again")
        else:
            if not self.camera_error:
                return  # still opening at start: nothing has failed yet
            self._fault(FaultCode.CAMERA_LOST, f"{self.camera_error}; retrying")
            watch = self._watch
            if watch is not None:
                watch.window.clear()
                watch.gate_baseline = None
                if self.armed and not self.latched:
                    self._pause(PauseCause.CAMERA_LOST)
        self._camera_reported = ok
        self._refresh_heartbeat(force=True)

    def _run_command(self, m: Any) -> None:
        self._cancel.clear()
        self._end_watch()
        with self._lock:
            self.station = m.station
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
            self._fault(FaultCode.REFERENCE_MISSING, str(exc))
        except SceneMismatchError as exc:
            self._fault(FaultCode.REFERENCE_MISSING, f"station {m.station}: the reference does "
                        f"not fit this camera ({exc}); capture it again")
        except StoreError as exc:
            self._fault(FaultCode.STORAGE_ERROR, str(exc))
        except _CameraLost as exc:
            self._fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: {exc}")
        except _Cancelled as exc:
            self._fault(FaultCode.COMMAND_REFUSED, str(exc))
        except EmptySceneError as exc:
            self._fault(FaultCode.CAMERA_LOST, f"{m.TYPE.name} {m.station}: the camera sees "
                        f"nothing to compare ({exc})")
        except Exception as exc:  # noqa: BLE001 -- never let a command take the service down
            log.exception("%s %s failed", m.TYPE.name, m.station)
            self._fault(FaultCode.INTERNAL_ERROR, f"{m.TYPE.name} {m.station}: internal error "
                        f"{type(exc).__name__}: {exc}")
        finally:
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
            self._alive["control"] = time.monotonic()
            self._camera_transitions()
            self._refresh_heartbeat()
            if got is not None:
                frames.append(got[0])
                self.last_frame_index = got[0].index
        return frames

    def _capture(self, station: str) -> None:
        from robot_change.scene import build_scene

        self.store.path(station)  # a bad name fails before any frame is read
        self._set_activity(ModuleState.CAPTURING)
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CAPTURE_REFERENCE {station}")
        t0 = time.perf_counter()
        model = build_scene(frames, scene_params(self.config, self.params),
                            source=self.camera_uri)
        path = self.store.save(station, model)
        log.info("station %s: reference of %d frames (%d points, K=%d) built in %.0f ms, saved "
                 "to %s", station, n, len(model), model.mixture.n_components,
                 (time.perf_counter() - t0) * 1e3, path)
        self._send(Captured(station))

    def _check(self, station: str) -> None:
        from robot_change.change import detect_changes
        from robot_change.filters import fuse_depth

        self._set_activity(ModuleState.CHECKING)
        reference = self.store.load(station)
        n = self.params["fuse_frames"]
        frames = self._fresh_frames(n, f"CHECK {station}")
        t0 = time.perf_counter()
        stack = np.stack([f.depth for f in frames])
        depth = stack[0] if n == 1 else fuse_depth(stack, reference.params.min_valid(n))
        changes = detect_changes(reference, depth, change_params(self.config, self.params),
                                 intrinsics=frames[0].intrinsics)
        regions = self._kept_regions(changes)
        ms = (time.perf_counter() - t0) * 1e3
        self.counters["checks"] += 1
        log.info("CHECK %s: %s in %.0f ms (%d frames fused)", station,
                 f"{len(regions)} changed region(s)" if regions else "no change", ms, n)
        self.last_check = {"station": station, "regions": len(regions), "ms": ms,
                           "frame_index": frames[-1].index}
        self._write_check(station, reference, depth, changes, regions)
        if regions:
            if self.armed and self.params["pause_on_change"] and not self.latched:
                self._pause(PauseCause.CHANGE_CHECK)
            self._report(station, changes)
        else:
            self._send(Clear(station))

    def _write_check(self, station: str, reference: Any, depth: np.ndarray, changes: Any,
                     regions: list[Any]) -> None:
        folder = self.options.report_dir
        if folder is None:
            return
        try:
            import io

            from hw.atomic import write_atomically

            cam = reference.intrinsics
            buf = io.BytesIO()
            boxes = np.array([[*r.bbox_min, *r.bbox_max, *r.centroid, r.n_points]
                              for r in regions], dtype=np.float64).reshape(-1, 10)
            kinds = np.array([1 if r.kind == "appeared" else 2 for r in regions], np.uint8)
            np.savez_compressed(buf, depth=depth, reference_depth=reference.depth,
                                appeared_mask=changes.appeared_mask,
                                disappeared_mask=changes.disappeared_mask,
                                intrinsics=np.array([cam.width, cam.height, cam.fx, cam.fy,
                                                     cam.cx, cam.cy]),
                                region_boxes=boxes, region_kinds=kinds)
            Path(folder).mkdir(parents=True, exist_ok=True)
            write_atomically(Path(folder) / f"{station}.last-check.npz", buf.getvalue())
        except Exception:  # noqa: BLE001 -- a picture for people is never worth a fault
            log.warning("could not write the last check of %s to %s", station, folder,
                        exc_info=True)

    # -- watch ----------------------------------------------------------------------------------

    def _start_watch(self, station: str) -> None:
        reference = self.store.load(station)
        with self._lock:
            self._watch = _Watch(station, reference, self.params["watch_n"])
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
            for job in watch.jobs:
                job.future.cancel()
            log.info("watch of %s ended after %d checks", watch.station, watch.checks)

    def _parked(self) -> bool:
        return self.motion in (Motion.PARKED, Motion.PAUSED)

    def _watch_frame(self, frame: DepthFrame, seq: int) -> None:
        watch = self._watch
        assert watch is not None
        ref = watch.reference.depth
        watch.latest, watch.latest_seq = frame, seq
        if frame.depth.shape != ref.shape:
            return  # the check itself reports the mismatch
        watch.latest_gate = depth_gate(ref, frame.depth, self.options.gate_step)
        base = watch.gate_baseline
        if (base is not None and self._parked() and self.camera_ok
                and abs(watch.latest_gate - base) > self.options.gate_pixels + self.options.gate_fraction * base
                and len(watch.jobs) < self.options.detector_threads):
            self.counters["gate_triggers"] += 1
            self._submit(watch, frame, seq)

    def _submit(self, watch: _Watch, frame: DepthFrame, seq: int) -> None:
        from robot_change.change import detect_changes

        assert self._pool is not None
        params = change_params(self.config, self.params)
        future = self._pool.submit(detect_changes, watch.reference, frame.depth, params,
                                   intrinsics=frame.intrinsics)
        future.add_done_callback(lambda _f: self._wake.set())
        watch.jobs.append(_WatchJob(seq, frame.index, future, time.monotonic()))
        watch.last_submitted = seq
        watch.gate_baseline = depth_gate(watch.reference.depth, frame.depth, self.options.gate_step) \
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
        if not self._parked():
            if watch.window:
                watch.window.clear()
                log.info("watch of %s suspended: the base is %s", watch.station, self.motion.name)
            return
        if (self.camera_ok and not watch.jobs and watch.latest is not None
                and watch.latest_seq != watch.last_submitted
                and time.monotonic() >= watch.next_check):
            self._submit(watch, watch.latest, watch.latest_seq)

    def _watch_result(self, watch: _Watch, job: _WatchJob) -> None:
        exc = job.future.exception()
        watch.checks += 1
        self.counters["watch_checks"] += 1
        blind = False
        regions: list[Any] = []
        changes = None
        if exc is None:
            changes = job.future.result()
            regions = self._kept_regions(changes)
            watch.error_reported = watch.blind_reported = False
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
                self._pause(PauseCause.CAMERA_LOST if blind and not regions
                            else PauseCause.CHANGE_WATCH)
            if changes is not None and regions:
                self._report(watch.station, changes)
        elif watch.episode and len(watch.window) - seen >= min(m, n) and not changed:
            watch.episode = False
            entry["action"] = "clear"
            log.info("WATCH %s: the change is gone", watch.station)
            self._send(Clear(watch.station))


class _CameraLost(Exception):
    """No frames for a capture or check."""


class _Cancelled(Exception):
    """STOP (or a newer command) ended a capture or check."""


# ---------------------------------------------------------------------------------------------
# the daemon's main loop


def run_service(service: Service, *, load: Callable[[], Config] | None = None,
                make_camera: Callable[[Config], Any] | None = None,
                stop: threading.Event | None = None, warm: bool = True) -> int:
    """Run ``service`` until SIGTERM/SIGINT (or ``stop``): warm-up, READY, WATCHDOG, SIGHUP.

    ``load()`` reads the configuration again on SIGHUP (a :class:`ConfigError` keeps the old
    one); ``make_camera(config)`` gives the new camera when ``[camera]`` changed.  Returns the
    exit status (0).  Call from the main thread (signal handlers).
    """
    stop = stop or threading.Event()
    hup = threading.Event()
    wake = threading.Event()  # a signal ends the wait at once
    in_main = threading.current_thread() is threading.main_thread()
    previous: dict[int, Any] = {}
    if in_main:
        def on_term(signum: int, _frame: Any) -> None:
            log.info("signal %s: stopping", signal.Signals(signum).name)
            stop.set()
            wake.set()

        def on_hup(_signum: int, _frame: Any) -> None:
            hup.set()
            wake.set()

        for sig, handler in ((signal.SIGTERM, on_term), (signal.SIGINT, on_term),
                             (signal.SIGHUP, on_hup)):
            previous[sig] = signal.signal(sig, handler)
    try:
        t0 = time.perf_counter()
        if warm:
            systemd.extend_timeout(300)
            systemd.status("compiling the numba kernels (or loading them from the cache)")
            seconds = warm_up(service.config)
            log.info("kernels ready in %.2f s", seconds)
        service.start()
        systemd.ready(status=f"ready in {time.perf_counter() - t0:.1f} s; idle")
        log.info("READY (%.2f s after start)", time.perf_counter() - t0)
        interval = systemd.watchdog_interval()
        beat = min(interval, 1.0) if interval else 1.0
        last_status = ""
        while not stop.is_set():
            wake.wait(beat)
            wake.clear()
            if stop.is_set():
                break
            if hup.is_set():
                hup.clear()
                _reload(service, load, make_camera)
            ok, why = service.healthy()
            if ok and service.config.service.watchdog and interval:
                systemd.watchdog()
            elif not ok:
                log.error("not feeding the watchdog: %s", why)
            text = _status_line(service)
            if text != last_status:
                systemd.status(text)
                last_status = text
        systemd.stopping()
        log.info("stopping")
        service.close()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _reload(service: Service, load: Callable[[], Config] | None,
            make_camera: Callable[[Config], Any] | None) -> None:
    systemd.reloading()
    try:
        if load is None:
            log.warning("SIGHUP: no configuration file to reload")
            return
        try:
            config = load()
        except ConfigError as exc:
            log.error("SIGHUP: the new configuration is refused, the old one stays: %s", exc)
            return
        logging.getLogger().setLevel(config.service.log_level.upper())
        camera = None
        if config.camera.source != service.config.camera.source and make_camera is not None:
            camera = make_camera(config)
        service.reload(config, camera)
    finally:
        systemd.ready(status="configuration reloaded")


def _status_line(service: Service) -> str:
    """systemd's STATUS=: changes only with the state (sent only when it changes)."""
    state = service.reported_state().name.lower()
    where = f" {service.station}" if service.station else ""
    camera = "camera ok" if service.camera_ok else f"camera lost: {service.camera_error}"
    return f"{state}{where}; {camera}; link {service.link.state.value}"[:200]
