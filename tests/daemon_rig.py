"""A real ``robot-change run`` subprocess for fault tests and bench/bench_stall.py: an image
folder as the camera, one end of a pty pair for the base (robot_change.tools.basesim on the other),
a test socket as systemd's notify socket, optionally a hang injected (tests/hang_daemon.py).

Every wait is bounded.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

from hw.serial_port import FdPort
from robot_change.tools.basesim import BaseSim, check_script

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
sys.path.insert(0, str(TESTS))

from test_daemon_e2e import Notes  # noqa: E402

#: A base's script that captures station "office" and watches it (checks every 100 ms).
WATCH_SETUP = """
    capture office
    expect CAPTURED station=office 10
    set check_interval_ms 100
    expect PARAM_VALUE value=100
    watch office
    expect HEARTBEAT state=WATCHING 3
"""


def camera_folder(epoch: str = "reference") -> Path:
    """The PNG frames of office_box_added's ``epoch`` ("reference", or "current": the box is
    there) (decoded from its .oni once)."""
    from sim_fixtures import load_scene

    return Path(load_scene("office_box_added").uri(epoch, "images").removeprefix("images:"))


class Daemon:
    """``robot-change run`` as a subprocess.  ``hang``: where to inject a hang (armed by
    :meth:`arm`); ``watchdog_usec``: systemd's WATCHDOG_USEC (the stall bound is half of it,
    at least 2 s); ``env``: more environment (e.g. an empty NUMBA_CACHE_DIR); ``config``:
    more configuration (TOML sections) in every file written; ``state_dir``: the store's
    folder (default ``tmp/state``), e.g. one kept across two daemons; ``source``: the camera's
    depth URI (default: office_box_added's frames, :func:`camera_folder`)."""

    def __init__(self, tmp: Path, hang: str | None = None, watchdog_usec: int = 4_000_000,
                 env: dict[str, str] | None = None, config: str = "",
                 state_dir: Path | None = None, source: str | None = None) -> None:
        self.tmp = tmp
        self.source = source
        tmp.mkdir(parents=True, exist_ok=True)
        self.extra_config = config
        self.state_dir = state_dir or tmp / "state"
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.arm_file = tmp / "hang.arm"
        self.config = tmp / "robot-change.toml"
        self.write_config()
        self.notes = Notes(tmp / "notify.sock")
        full = dict(os.environ, NOTIFY_SOCKET=str(tmp / "notify.sock"),
                    WATCHDOG_USEC=str(watchdog_usec), PYTHONPATH=str(REPO), **(env or {}))
        full.pop("WATCHDOG_PID", None)
        cmd = ([sys.executable, str(TESTS / "hang_daemon.py"), hang, str(self.arm_file)] if hang
               else [sys.executable, "-m", "robot_change.cli"])
        self.log_path = tmp / "daemon.log"
        self._log = open(self.log_path, "w+")
        self.started = time.monotonic()
        self.proc = subprocess.Popen(cmd + ["run", "--config", str(self.config)], cwd=REPO,
                                     env=full, stdout=self._log, stderr=subprocess.STDOUT)
        self.transcript = io.StringIO()
        self._base_threads: list[threading.Thread] = []
        self.sims: list[BaseSim] = []

    def write_config(self, extra: str = "", epoch: str = "reference") -> None:
        """The configuration: the ``source`` given, else ``epoch``'s frames as the camera (see
        :func:`camera_folder`)."""
        source = self.source or f"images:{camera_folder(epoch)}?rate=30&loop=1"
        self.config.write_text(f"[camera]\nsource = {json.dumps(source)}\n"
                               f"[serial]\nport = {json.dumps(os.ttyname(self.slave))}\n"
                               f"[store]\nstate_dir = {json.dumps(str(self.state_dir))}\n"
                               + self.extra_config + extra)

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        self.notes.close()
        self._log.close()
        for thread in self._base_threads:
            thread.join(20)
        if any(t.is_alive() for t in self._base_threads):
            return  # leak the fds rather than let a late thread use a number reused elsewhere
        os.close(self.master)
        os.close(self.slave)

    def log(self) -> str:
        return self.log_path.read_text()

    def wait_for(self, what: str, timeout: float = 60.0) -> float:
        """Wait until the notify socket got the line ``what`` (or the log holds ``what``);
        returns the time it came."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for stamp, line in list(self.notes.stamped):
                if line == what:
                    return stamp
            if what in self.log():
                return time.monotonic()
            assert self.proc.poll() is None, f"the daemon exited:\n{self.log()}"
            time.sleep(0.02)
        raise AssertionError(f"{what!r} not seen within {timeout} s:\n{self.log()}")

    def base(self, text: str, connect_timeout: float = 10.0) -> int:
        """Run a basesim script against the daemon; returns its exit code (0: all held).  The
        simulated base is kept in ``sims`` (``sim.log``: what came, with monotonic times)."""
        script = self.tmp / f"script{time.monotonic_ns()}.txt"
        script.write_text("\n".join(line.strip() for line in text.strip().splitlines()) + "\n")
        sim = BaseSim(FdPort(self.master), out=self.transcript)
        self.sims.append(sim)
        return sim.run_script(check_script(script), connect_timeout)

    def first(self, name: str, **fields: object) -> float | None:
        """When the simulated base first got a ``name`` message with these field values."""
        for sim in self.sims:
            for entry in sim.log:
                if entry.name == name and all(getattr(entry.obj, k, None) == v
                                              for k, v in fields.items()):
                    return entry.t
        return None

    def base_in_thread(self, text: str) -> tuple[threading.Thread, list[int]]:
        result: list[int] = []
        thread = threading.Thread(target=lambda: result.append(self.base(text)), daemon=True)
        self._base_threads.append(thread)
        thread.start()
        return thread, result

    def arm(self) -> float:
        """Arm the injected hang; returns the time."""
        self.arm_file.touch()
        return time.monotonic()

    def wait_entered(self, timeout: float = 20.0) -> float:
        """Wait until a call is stuck in the injected hang; returns the time it was seen."""
        end = time.monotonic() + timeout
        entered = Path(f"{self.arm_file}.entered")
        while time.monotonic() < end:
            if entered.exists():
                return time.monotonic()
            time.sleep(0.01)
        raise AssertionError(f"the hang was not entered within {timeout} s:\n{self.log()}")

    def terminate(self, timeout: float = 10.0) -> tuple[int, float]:
        """SIGTERM; returns (exit status, seconds until the process ended)."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout)
        return code, time.monotonic() - t0

    def pings(self, after: float = 0.0) -> list[float]:
        """When WATCHDOG=1 came, after ``after``."""
        return [t for t, line in self.notes.stamped if line == "WATCHDOG=1" and t > after]

    def ready_after_stopping(self) -> bool:
        lines = [line for _t, line in self.notes.stamped]
        if "STOPPING=1" not in lines:
            return False
        return "READY=1" in lines[lines.index("STOPPING=1"):]
