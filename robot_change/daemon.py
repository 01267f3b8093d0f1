"""The daemon's main loop around a :class:`robot_change.service.Service`.

:func:`run_service`: systemd READY once the numba kernels are compiled or loaded
(:func:`robot_change.warmup.warm_up`), WATCHDOG while the threads are alive, SIGHUP reloads
the configuration (a new camera source is reopened; a bad file keeps the old configuration),
SIGTERM stops cleanly.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from typing import Any, Callable

from robot_change import systemd
from robot_change.config import Config
from robot_change.errors import ConfigError
from robot_change.service import Service
from robot_change.warmup import warm_up

__all__ = ["run_service"]

log = logging.getLogger(__name__)


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
