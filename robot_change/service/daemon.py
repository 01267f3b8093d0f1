"""The daemon's main loop around a :class:`robot_change.service.core.Service`.

:func:`run_service`: the link first (HELLO, heartbeats of state BOOTING), then systemd READY
once the numba kernels are compiled or loaded (:func:`robot_change.service.warmup.warm_up`, in
a thread of its own so that SIGTERM is honoured at once even during a cold compile), WATCHDOG
only while every part makes progress (:meth:`Service.healthy`), SIGHUP reloads the
configuration (a new camera source is reopened; a refused file keeps the old configuration,
and STATUS says so), SIGTERM stops within ~1 s in every state (a hung kernel is abandoned, not
waited for).

A stall (robot_change.service.liveness) ends the loop: the service has told the base (FAULT STALLED,
PAUSE when watching); the loop waits up to :data:`STALL_GRACE_S` for the base's ACK of the
FAULT, stops feeding the watchdog and returns :data:`EXIT_STALLED`, and the process exits
for systemd to restart it (``Restart=on-failure``).  No READY is sent after STOPPING.
"""

from __future__ import annotations

import logging
import select
import signal
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from robot_change.errors import ConfigError
from robot_change.service import systemd
from robot_change.service.config import Config
from robot_change.service.core import Service
from robot_change.service.warmup import warm_up

__all__ = ["EXIT_STALLED", "STALL_GRACE_S", "run_service", "set_log_level", "stall_bound"]

log = logging.getLogger(__name__)

#: Exit status after a stall (sysexits.h EX_SOFTWARE): systemd restarts the service.
EXIT_STALLED = 70
#: How long a stalled daemon waits for the base to acknowledge the FAULT before it exits.
STALL_GRACE_S = 1.5
#: The shortest stall bound, seconds: a capture or a check on a slow computer takes ~1 s.
MIN_STALL_S = 2.0
#: The stall bound without a systemd watchdog, seconds (half of the unit's WatchdogSec=10).
DEFAULT_STALL_S = 5.0


def set_log_level(level: str) -> None:
    """Log ``level`` ("debug" ... "error") and worse from robot_change and hw (the command
    line's -v / -q / --log-level, the configuration's [service] log_level, a reload)."""
    for name in ("robot_change", "hw"):
        logging.getLogger(name).setLevel(level.upper())


def stall_bound(watchdog_interval: float | None) -> float:
    """Seconds a part may go without progress: half of WatchdogSec (systemd's
    ``watchdog_interval()``), at least :data:`MIN_STALL_S`; :data:`DEFAULT_STALL_S` without a
    watchdog."""
    if not watchdog_interval:
        return DEFAULT_STALL_S
    return max(float(watchdog_interval), MIN_STALL_S)


def run_service(service: Service, *, load: Callable[[], Config] | None = None,
                make_camera: Callable[[Config], Any] | None = None,
                stop: threading.Event | None = None, warm: bool = True) -> int:
    """Run ``service`` until SIGTERM/SIGINT (or ``stop``): warm-up, READY, WATCHDOG, SIGHUP.

    ``load()`` reads and checks the configuration again on SIGHUP (a :class:`ConfigError`
    keeps the old one); ``make_camera(config)`` gives the new camera when ``[camera]``
    changed.  Returns the exit status: 0, or :data:`EXIT_STALLED`.  Threads that did not stop
    (a hung kernel) are left to the caller: :meth:`Service.close`'s list, ``service.stuck``.
    Call from the main thread (signal handlers).
    """
    stop = stop or threading.Event()
    signals = _Signals()
    in_main = threading.current_thread() is threading.main_thread()
    previous: dict[int, Any] = {}
    if in_main:
        for sig, handler in ((signal.SIGTERM, signals.on_term), (signal.SIGINT, signals.on_term),
                             (signal.SIGHUP, signals.on_hup)):
            previous[sig] = signal.signal(sig, handler)
    service.stuck = []
    try:
        t0 = time.perf_counter()
        service.open_link()  # HELLO and BOOTING heartbeats while the kernels compile
        try:
            if warm and not _warm_up(service, stop, signals):
                return _stalled(service, service.stalled) if service.stalled else _stop(service)
        except BaseException:
            service.close()
            raise
        service.start()
        signals.wait(0.0, stop)  # a SIGTERM that came meanwhile: no READY
        if stop.is_set():
            return _stop(service)
        systemd.ready(status=f"ready in {time.perf_counter() - t0:.1f} s; idle")
        log.info("READY (%.2f s after start)", time.perf_counter() - t0)
        interval = systemd.watchdog_interval()
        beat = min(interval, 1.0) if interval else 1.0
        last_status = ""
        while not stop.is_set():
            signals.wait(beat, stop)
            if stop.is_set():
                break
            if signals.hup:
                signals.hup = False
                _reload(service, load, make_camera, stop)
            ok, why = service.healthy()
            if not ok:
                return _stalled(service, why)
            if service.config.service.watchdog and interval:
                systemd.watchdog()
            text = _status_line(service)
            if text != last_status:
                systemd.status(text)
                last_status = text
        return _stop(service)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        signals.close()


class _Signals:
    """What SIGTERM / SIGINT and SIGHUP tell the main loop: plain flags, and a byte on a socket
    that ends its wait at once.  A handler runs on the main thread between two of its
    bytecodes, maybe inside a lock that thread holds (an Event's: a burst of SIGHUPs hung the
    daemon for good, SIGTERM too), so it takes none: no Event, no logging."""

    def __init__(self) -> None:
        # sockets, not a pipe's descriptors: an abandoned warm-up thread that notifies after
        # close() gets an error, never a descriptor number reused by another file
        self._read, self._write = socket.socketpair()
        self._read.setblocking(False)
        self._write.setblocking(False)
        self.term = ""  # the stopping signal's name, once one came
        self.hup = False

    def on_term(self, signum: int, _frame: Any) -> None:
        self.term = signal.Signals(signum).name
        self.notify()

    def on_hup(self, _signum: int, _frame: Any) -> None:
        self.hup = True
        self.notify()

    def notify(self) -> None:
        """End a :meth:`wait` now (from a handler or any thread)."""
        try:
            self._write.send(b"\0")
        except OSError:  # its buffer full: a wake is pending anyway; or closed
            pass

    def wait(self, timeout: float, stop: threading.Event) -> None:
        """Wait up to ``timeout`` seconds or until notified; a stopping signal sets ``stop``."""
        select.select([self._read], [], [], max(0.0, timeout))
        try:
            while self._read.recv(4096):
                pass
        except BlockingIOError:
            pass
        if self.term and not stop.is_set():
            log.info("signal %s: stopping", self.term)
            stop.set()

    def close(self) -> None:
        self._read.close()
        self._write.close()


def _warm_up(service: Service, stop: threading.Event, signals: _Signals) -> bool:
    """Compile or load the kernels in a thread while the main thread waits for it, for a
    signal or for ``[service] warmup_timeout_s``; False when told to stop first, or when the
    deadline passed (then a stall, told to the base: :meth:`Service.report_stall`; a hung
    compile is as silent as any hang).  The thread is abandoned then: it only compiles."""
    done = threading.Event()
    failed: list[BaseException] = []

    def run() -> None:
        try:
            log.info("kernels ready in %.2f s", warm_up(service.config))
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the main thread
            failed.append(exc)
        finally:
            done.set()
            signals.notify()

    limit = service.config.service.warmup_timeout_s
    systemd.extend_timeout(limit + 60.0)  # time to tell the base before systemd gives up
    systemd.status("compiling the numba kernels (or loading them from the cache)")
    thread = threading.Thread(target=run, name="rc-warmup", daemon=True)
    thread.start()
    end = time.monotonic() + limit
    while not done.is_set() and not stop.is_set():
        if time.monotonic() >= end:
            service.report_stall(f"kernels not ready {limit:.0f} s after start (a hung or "
                                 f"slow warm-up: [service] warmup_timeout_s)")
            break
        signals.wait(min(1.0, max(0.0, end - time.monotonic())), stop)
    if failed:
        raise failed[0]
    if not done.is_set():
        service.stuck = [thread.name]
        return False
    return True


def _stop(service: Service) -> int:
    systemd.stopping()
    log.info("stopping")
    service.stuck = service.stuck + service.close()
    return 0


def _stalled(service: Service, why: str) -> int:
    """The service told the base; give the FAULT a moment to be acknowledged, then exit
    without feeding the watchdog again."""
    log.error("not feeding the watchdog: %s", why)
    systemd.status(f"stalled ({why}); exiting for systemd to restart the service"[:200])
    if not service.stall_told.wait(STALL_GRACE_S):
        log.warning("the base did not acknowledge FAULT STALLED within %.1f s", STALL_GRACE_S)
    systemd.stopping()
    service.stuck = service.stuck + service.close(timeout=0.5)
    return EXIT_STALLED


def _reload(service: Service, load: Callable[[], Config] | None,
            make_camera: Callable[[Config], Any] | None, stop: threading.Event) -> None:
    systemd.reloading()
    outcome = "configuration reloaded"
    try:
        if load is None:
            log.warning("SIGHUP: no configuration file to reload")
            outcome = "no configuration file to reload"
            return
        try:
            config = load()
            _check_no_key_lost(service.config, config)
        except ConfigError as exc:
            log.error("SIGHUP: the new configuration is refused, the old one stays: %s", exc)
            outcome = f"configuration refused, the old one stays: {exc}"
            return
        set_log_level(config.service.log_level)
        camera = None
        if config.camera.source != service.config.camera.source and make_camera is not None:
            camera = make_camera(config)
        service.reload(config, camera)
    finally:
        if not stop.is_set():  # never READY after STOPPING
            systemd.ready(status=outcome[:200])


def _check_no_key_lost(running: Config, new: Config) -> None:
    """A reload of a file that lost a key the running configuration's file set is refused
    (:class:`ConfigError`): most likely a file cut short (half copied, a full disk) whose rest
    would silently become defaults.  A restart takes such a file."""
    lost = sorted(running.keys - new.keys)
    if lost:
        shown = ", ".join(lost[:6]) + (f" and {len(lost) - 6} more" if len(lost) > 6 else "")
        raise ConfigError(f"{new.path}: does not set {shown}, which the running configuration "
                          "sets (a file cut short?); a reload never drops a setting: restart "
                          "the service to run without them")


def _status_line(service: Service) -> str:
    """systemd's STATUS=: changes only with the state (sent only when it changes)."""
    state = service.reported_state().name.lower()
    where = f" {service.station}" if service.station else ""
    camera = ("camera ok" if service.camera_ok else f"camera lost: {service.camera_error}"
              if service.camera_error else "camera opening")
    fleet = "" if service.fleet is None else "; " + fleet_status(service.fleet.counts())
    return f"{state}{where}; {camera}; link {service.link.state.value}{fleet}"[:200]


def fleet_status(counts: dict) -> str:
    """The fleet's part of STATUS= from :meth:`Publisher.counts`: its connection (down: why,
    cut short), what waits in the spool, what was dropped."""
    spool = counts["spool"]
    dropped = spool["dropped"] + counts["queue_dropped"]
    why = counts["last_error"] if counts["connection"] == "down" else ""
    return (f"fleet {counts['connection']}" + (f" ({why[:60]})" if why else "")
            + f", {spool['queued']} spooled" + (f", {dropped} dropped" if dropped else ""))
