"""The daemon's targets (issue 7): PAUSE latency, start to READY, CPU in watch mode, soak.

    .venv/bin/python bench/bench_service.py [--trials 20] [--ready-runs 3] [--cpu-seconds 20]
                                            [--soak-seconds 600] [--soak-camera realsense]
                                            [--soak-check-every 60]
                                            [--cold-runs 2]
                                            [--only latency,ready,ready-cold,cpu,soak,soak-daemon]
                                            [--json]

latency  In process: the real service, link and simulated base over a pty pair, fed by a
         source that plays the reference frames of office_box_added at 30 fps and switches to
         the frames with the box at a moment the bench picks (a random phase of the watch's
         check cycle).  Measured: from the source handing out the first changed frame to the
         base receiving PAUSE on the pty.  WATCH with watch_m = watch_n = 1 (the detector's own
         latency) and with the defaults 3 of 5 (what persistence adds); CHECK for comparison
         (command sent -> PAUSE received).  Target: p95 <= 150 ms for WATCH, M = N = 1.
ready    ``robot-change run`` as a subprocess with a test NOTIFY_SOCKET: exec -> READY=1, with
         a warm numba cache (one run first to warm it).  Target <= 3 s (issue 15: <= 2 s).
ready-cold  The same with an empty numba cache (a fresh NUMBA_CACHE_DIR each run): the first
         start after an install.  Target <= 30 s.
cpu      The daemon subprocess watching the looped reference.oni at 30 fps with the default
         parameters: (utime + stime) / wall time from /proc, the daemon alone and with its
         OpenNI2 reader child.  Target <= 1 core.
soak     In process, watching the looped reference.oni at 30 fps for --soak-seconds: RSS of
         the process (and of the reader child) sampled every second, growth from the end of
         the first 10 % to the end; the longest gap between heartbeats at the base (a stall);
         frames received == processed + dropped + queued, and received == the source's
         delivered count.  Targets: RSS growth <= 5 %, no stall, every frame accounted for.
soak-daemon  The same soak with ``robot-change run`` as a subprocess (what tests/test_soak.py
         runs for 60 s): RSS of the daemon and of its OpenNI2 reader child from /proc, heartbeat
         gaps at the simulated base, and the frame counts and the source's delivered count that
         the daemon writes when SIGTERM stops it (an observer around ``robot_change.cli.main``,
         the console script's entry point: nothing else differs); plus its exit status and the
         reader's CPU.  ``--soak-camera realsense``: the same frames as a RealSense recording
         (written by librealsense, played by it at 30 fps in a loop; issue 43's target: no
         frame dropped or repeated, the reader under 10 % of one core); ``--soak-camera bag``:
         that recording read by the bag backend (``rosbag:FILE``) in the daemon's camera
         thread, the reader's CPU the thread time spent in the source's reads.
         ``--soak-check-every S``: a CHECK every S seconds, then WATCH again (issue 44: a
         60-minute soak in WATCH with CHECKs, its RSS slope over the last 30 minutes within
         noise: ``rss_slope_last_half_mb_per_min`` against ``rss_residual_sd_last_half_mb``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import logging
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from hw.depth import DepthFrame, DepthSource, Intrinsics, open_depth  # noqa: E402
from hw.serial_port import FdPort, open_port  # noqa: E402
from robot_change.service.config import Config  # noqa: E402
from robot_change.service.core import Service, ServiceOptions  # noqa: E402
from robot_change.service.store import ReferenceStore  # noqa: E402
from robot_change.service.warmup import warm_up  # noqa: E402
from robot_change.tools.basesim import BaseSim  # noqa: E402

SCENE = ROOT / "sim_fixtures" / "scenes" / "office_box_added"


class SwitchingSource(DepthSource):
    """Frames of two epochs at ``rate`` fps, like a camera; :meth:`switch` makes the next frame
    come from the other epoch and records when the first such frame is handed out."""

    def __init__(self, epochs: dict[str, list[np.ndarray]], intrinsics: Intrinsics,
                 rate: float = 30.0) -> None:
        super().__init__()
        self.epochs, self._intrinsics, self.period = epochs, intrinsics, 1.0 / rate
        self.epoch = "reference"
        self.uri = "bench:switching"
        self.index = 0
        self._due = 0.0
        self._want: str | None = None
        self.switched_at: float | None = None
        self.switched_index: int | None = None

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    def open(self) -> None:
        self._due = time.monotonic()

    def close(self) -> None:
        pass

    def switch(self, epoch: str) -> None:
        self.switched_at = self.switched_index = None
        self._want = epoch

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        wait = self._due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        self._due = max(self._due, time.monotonic() - self.period) + self.period
        if self._want is not None:
            self.epoch, self._want = self._want, None
            first = True
        else:
            first = False
        frames = self.epochs[self.epoch]
        self.index += 1
        frame = DepthFrame(frames[self.index % len(frames)], self.index * 33_333, self.index,
                           self._intrinsics)
        self.stats.delivered += 1
        if first:
            self.switched_at, self.switched_index = time.monotonic(), self.index
        return frame


class InProcess:
    """A service and a simulated base on a pty pair, in this process."""

    def __init__(self, camera, tmp: Path, config: Config | None = None,
                 options: ServiceOptions | None = None) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        self.master, self.slave = master, slave
        self.port = open_port(os.ttyname(slave), timeout=0.01)
        self.service = Service(config or Config(), camera, self.port,
                               ReferenceStore(tmp / "references"), options)
        self.log = open(tmp / "base.log", "w")
        self.sim = BaseSim(FdPort(master), out=self.log)

    def __enter__(self) -> InProcess:
        self.service.start()
        assert self.sim.pump(10.0, until=lambda: self.sim.link.state.value == "up"), "no link"
        return self

    def __exit__(self, *exc: object) -> None:
        self.service.close()
        self.port.close()
        self.log.close()
        os.close(self.slave)
        os.close(self.master)

    def do(self, line: str) -> None:
        self.sim.command(line)

    def expect(self, what: str, seconds: float, **filters: str):
        entry = self.sim.expect(what, filters, seconds)
        if entry is None:
            raise RuntimeError(f"no {what} within {seconds} s")
        return entry


def _frames(epoch: str) -> list[np.ndarray]:
    with open_depth(f"oni:{SCENE / (epoch + '.oni')}") as source:
        return [f.depth.copy() for f in source]


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def summary(values: list[float]) -> dict[str, float]:
    return {"n": len(values), "median_ms": round(statistics.median(values), 1),
            "p95_ms": round(percentile(values, 95), 1), "max_ms": round(max(values), 1)}


# --------------------------------------------------------------------------------------------
# latency


def bench_latency(trials: int, seed: int = 0) -> dict:
    rng = random.Random(seed)
    warm_up()
    epochs = {"reference": _frames("reference"), "current": _frames("current")}
    with open_depth(f"oni:{SCENE / 'reference.oni'}") as s:
        camera = s.intrinsics
    source = SwitchingSource(epochs, camera)
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp, InProcess(source, Path(tmp)) as rig:
        rig.do("capture office")
        rig.expect("CAPTURED", 10)
        gated = rig.service.options
        for label, m, n in (("watch_1_of_1", 1, 1), ("watch_1_of_1_without_gate", 1, 1),
                            ("watch_3_of_5", 3, 5)):
            # without the gate only the scheduled checks (every check_interval_ms) see it
            rig.service.options = dataclasses.replace(
                gated, gate_pixels=10**9 if "without" in label else gated.gate_pixels)
            rig.do(f"set watch_m {min(m, 1)}")
            rig.do(f"set watch_n {n}")
            rig.do(f"set watch_m {m}")
            rig.expect("PARAM_VALUE", 2, value=str(m))
            times: list[float] = []
            for _ in range(trials if label == "watch_1_of_1" else max(3, trials // 4)):
                rig.do("watch office")
                rig.sim.pump(rng.uniform(0.6, 1.1))  # a random phase of the check cycle
                rig.sim.cursor = len(rig.sim.log)
                source.switch("current")
                pause = rig.expect("PAUSE", 10)
                times.append((pause.t - source.switched_at) * 1e3)
                rig.do("stop")
                source.switch("reference")
                rig.do("resume")
                rig.expect("HEARTBEAT", 2, state="IDLE", paused="0")
            out[label] = summary(times)
        rig.do("set watch_m 1")
        rig.do("set watch_n 5")
        times = []
        source.switch("current")
        rig.sim.pump(0.3)
        for _ in range(max(3, trials // 2)):
            rig.sim.cursor = len(rig.sim.log)
            sent = time.monotonic()
            rig.do("check office")
            pause = rig.expect("PAUSE", 10)
            times.append((pause.t - sent) * 1e3)
            rig.do("resume")
            rig.expect("HEARTBEAT", 2, paused="0")
        out["check_command_to_pause"] = summary(times)
        counts = rig.service.frame_counts()
        out["frames"] = counts
        out["gate_triggers"] = rig.service.counters["gate_triggers"]
    return out


# --------------------------------------------------------------------------------------------
# the daemon as a subprocess: READY time and CPU


#: ``robot-change run`` (``robot_change.cli.main``, what the console script calls) with an
#: observer: the sources the daemon opens and its service are kept, and once the daemon returns
#: (SIGTERM) their counts go as JSON to the file named by the first argument, with the CPU time
#: the calling threads spent in the sources' reads (an in-process reader's whole cost).
_OBSERVED_RUN = """
import json, sys, time
import robot_change.cli as cli, robot_change.service.daemon as daemon
out = sys.argv.pop(1)
sources, services, read_cpu, opened = [], [], [0.0], []
real_open, real_run = cli.open_depth, daemon.run_service
def open_depth(*args, **kwargs):
    source = real_open(*args, **kwargs)
    sources.append(source)
    opened.append(time.monotonic())
    real_read = source.read
    def read(*args, **kwargs):
        started = time.thread_time()
        try:
            return real_read(*args, **kwargs)
        finally:
            read_cpu[0] += time.thread_time() - started
    source.read = read
    return source
def run_service(service, **kwargs):
    services.append(service)
    return real_run(service, **kwargs)
cli.open_depth, daemon.run_service = open_depth, run_service
code = None
try:
    code = cli.main(sys.argv[1:])
finally:
    if services:
        service = services[0]
        with open(out, "w") as f:
            json.dump({"exit": code, "frames": service.frame_counts(),
                       "source_delivered": sum(s.stats.delivered for s in sources),
                       "source_dropped": sum(s.stats.dropped for s in sources),
                       "source_restarts": sum(s.stats.restarts for s in sources),
                       "sources_opened": len(sources), "camera_losses": service.camera_losses,
                       "read_cpu_s": read_cpu[0],
                       "read_wall_s": time.monotonic() - opened[0] if opened else 0.0,
                       "counters": dict(service.counters)}, f)
sys.exit(code)
"""


class Daemon:
    """``robot-change run`` on the looped reference.oni (or ``source``), a pty pair, a test
    notify socket.

    ``observe``: a file the daemon writes its frame counts to when it stops (``_OBSERVED_RUN``).
    """

    def __init__(self, tmp: Path, observe: Path | None = None,
                 env: dict[str, str] | None = None, source: str | None = None) -> None:
        self.tmp = tmp
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        self.master, self.slave = master, slave
        config = tmp / "robot-change.toml"
        default_source = f"oni:{SCENE / 'reference.oni'}?loop=1&rate=auto"
        config.write_text(
            f'[camera]\nsource = {json.dumps(source or default_source)}\n'
            f'[serial]\nport = "{os.ttyname(slave)}"\n[store]\nstate_dir = "{tmp / "state"}"\n'
            '[service]\nwatchdog = false\nlog_level = "warning"\n')
        self.notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock = tmp / f"notify-{time.monotonic_ns()}.sock"
        self.notify.bind(str(sock))
        self.ready = threading.Event()
        self._done = threading.Event()
        # read all along, as systemd does: an unread datagram queue would block sd_notify
        threading.Thread(target=self._read_notes, daemon=True).start()
        env = dict(os.environ, NOTIFY_SOCKET=str(sock), **(env or {}))
        self.started = time.monotonic()
        entry = ["-m", "robot_change.cli"] if observe is None else ["-c", _OBSERVED_RUN,
                                                                   str(observe)]
        self.proc = subprocess.Popen([sys.executable, *entry, "run", "--config", str(config)],
                                     cwd=ROOT, env=env,
                                     stdout=open(tmp / "daemon.log", "a"), stderr=subprocess.STDOUT)

    def _read_notes(self) -> None:
        self.notify.settimeout(0.1)
        while not self._done.is_set():
            try:
                data = self.notify.recv(4096).decode()
            except (TimeoutError, OSError):
                continue
            if "READY=1" in data.splitlines() and not self.ready.is_set():
                self.ready_at = time.monotonic()
                self.ready.set()

    def wait_ready(self, timeout: float = 180.0) -> float:
        while not self.ready.wait(0.2):
            if self.proc.poll() is not None:
                raise RuntimeError("the daemon exited; see daemon.log")
            if time.monotonic() - self.started > timeout:
                raise RuntimeError("no READY=1")
        return self.ready_at - self.started

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(15)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self._done.set()
            time.sleep(0.15)
            self.notify.close()
            os.close(self.master)
            os.close(self.slave)


def bench_ready(runs: int) -> dict:
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(runs + 1):  # the first one warms the numba cache
            daemon = Daemon(Path(tmp))
            try:
                seconds = daemon.wait_ready()
            finally:
                daemon.stop()
            if i:
                times.append(seconds)
    return {"runs": runs, "median_s": round(statistics.median(times), 2),
            "max_s": round(max(times), 2)}


def bench_ready_cold(runs: int) -> dict:
    """exec -> READY=1 with an empty numba cache (NUMBA_CACHE_DIR a new empty folder each
    run): the first start after an install, before ``robot-change warm-up`` ran.  A simulated
    base listens all along: exec -> its first heartbeat, and the longest gap between the
    heartbeats of state BOOTING (the base's silence rule pauses at 400 ms)."""
    times, first, gaps = [], [], []
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp) / "numba-cache"
            cache.mkdir()
            daemon = Daemon(Path(tmp), env={"NUMBA_CACHE_DIR": str(cache)})
            try:
                with open(Path(tmp) / "base.log", "w") as log:
                    sim = BaseSim(FdPort(daemon.master), out=log)
                    sim.pump(180.0, until=daemon.ready.is_set)
                times.append(daemon.wait_ready())
            finally:
                daemon.stop()
            beats = [e.t for e in sim.log
                     if e.name == "HEARTBEAT" and e.obj.state.name == "BOOTING"]
            first.append(beats[0] - daemon.started if beats else float("nan"))
            gaps.append(max(b - a for a, b in zip(beats, beats[1:], strict=False))
                        if len(beats) > 1 else float("nan"))
    return {"runs": runs, "median_s": round(statistics.median(times), 2),
            "max_s": round(max(times), 2), "all_s": [round(t, 2) for t in times],
            "first_heartbeat_s": [round(t, 2) for t in first],
            "longest_booting_gap_ms": [round(g * 1e3) for g in gaps]}


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_cpu(seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        daemon = Daemon(Path(tmp))
        try:
            daemon.wait_ready()
            sim = BaseSim(FdPort(daemon.master), out=open(Path(tmp) / "base.log", "w"))
            assert sim.pump(10, until=lambda: sim.link.state.value == "up")
            sim.command("capture office")
            assert sim.expect("CAPTURED", {}, 10)
            sim.command("watch office")
            assert sim.expect("HEARTBEAT", {"state": "WATCHING"}, 5)
            sim.pump(2.0)  # settle
            pids = [daemon.proc.pid] + _children(daemon.proc.pid)
            before = {pid: _cpu_seconds(pid) for pid in pids}
            t0 = time.monotonic()
            sim.pump(seconds)
            wall = time.monotonic() - t0
            used = {pid: _cpu_seconds(pid) - before[pid] for pid in pids}
            sim.command("status")
            status = sim.expect("STATUS", {}, 3).obj
        finally:
            daemon.stop()
    return {"seconds": round(wall, 1), "daemon_cores": round(used[pids[0]] / wall, 3),
            "with_reader_cores": round(sum(used.values()) / wall, 3),
            "fps": status.fps_x10 / 10, "frames_dropped": status.frames_dropped,
            "load_avg_1min": os.getloadavg()[0]}


# --------------------------------------------------------------------------------------------
# soak


def _soak_loop(sim: BaseSim, seconds: float, rss: Callable[[], tuple[float, float]],
               frames: Callable[[], object] = lambda: "",
               check_every: float = 0.0) -> tuple[list, list[float], dict]:
    """Pump the base for ``seconds``; every second: the longest gap between the module's
    heartbeats (up to now) and ``rss()`` (MB of the process and of its reader).
    ``check_every`` > 0: every that many seconds the base sends CHECK office (which ends the
    watch) and WATCH office again.  Returns [(t, rss, reader rss)], the gaps, and what the
    heartbeats and messages showed (``states``: heartbeat state -> count; ``messages``: the
    other messages -> count)."""
    rss_samples: list[tuple[float, float, float]] = []
    gaps: list[float] = []
    states: collections.Counter = collections.Counter()
    messages: collections.Counter = collections.Counter()
    t0 = last_print = time.monotonic()
    beats_seen = len(sim.log)
    last_beat = last_check = time.monotonic()
    while time.monotonic() - t0 < seconds:
        sim.pump(1.0)
        now = time.monotonic()
        if check_every > 0 and now - last_check >= check_every:
            last_check = now
            sim.command("check office")
            sim.command("watch office")
        beats = []
        for e in sim.log[beats_seen:]:
            if e.name == "HEARTBEAT":
                beats.append(e.t)
                states[e.obj.state.name] += 1
            elif e.name not in ("BASE_HEARTBEAT", "LINK"):
                messages[e.name] += 1
        stamps = [last_beat] + beats
        gaps.append(max(b - a for a, b in zip(stamps, stamps[1:] + [now], strict=True)))
        if beats:
            last_beat = beats[-1]
        del sim.log[:]  # the base's log would grow for ever
        sim.consumed.clear()
        sim.cursor = sim.mark = beats_seen = 0
        rss_samples.append((now - t0, *rss()))
        if now - last_print > 60:
            last_print = now
            print(f"  soak {now - t0:.0f} s: rss {rss_samples[-1][1]:.1f} MB, frames "
                  f"{frames()}", file=sys.stderr, flush=True)
    return rss_samples, gaps, {"states": dict(states), "messages": dict(messages)}


def _slope(samples: list[tuple[float, float]]) -> tuple[float, float]:
    """Least-squares slope (MB/min) of [(t s, MB)] and the residuals' standard deviation (MB):
    the noise a slope is judged against."""
    import numpy as np

    t, mb = np.array(samples, dtype=float).T
    a, b = np.polyfit(t / 60.0, mb, 1)
    return float(a), float(np.std(mb - (a * t / 60.0 + b)))


def _rss_growth(rss: list[tuple[float, float, float]], warmup: float) -> dict:
    """RSS from the first sample at or after ``warmup`` s to the last one; the slope of the
    daemon's and the reader's RSS over the second half of the run (MB/min) and its noise."""
    start = next(r for r in rss if r[0] >= warmup)
    growth = 100.0 * (rss[-1][1] - start[1]) / start[1]
    reader = 100.0 * (rss[-1][2] - start[2]) / start[2] if start[2] else 0.0
    half = [r for r in rss if r[0] >= rss[-1][0] / 2]
    slope, noise = _slope([(r[0], r[1]) for r in half])
    reader_slope, _ = _slope([(r[0], r[2]) for r in half])
    return {"rss_slope_last_half_mb_per_min": round(slope, 4),
            "rss_residual_sd_last_half_mb": round(noise, 2),
            "reader_rss_slope_last_half_mb_per_min": round(reader_slope, 4),
            "rss_last_half_start_mb": round(half[0][1], 1),"rss_start_mb": round(start[1], 1),
            "rss_end_mb": round(rss[-1][1], 1),
            "rss_growth_pct": round(growth, 2), "rss_peak_mb": round(max(r[1] for r in rss), 1),
            "reader_rss_start_mb": round(start[2], 1), "reader_rss_end_mb": round(rss[-1][2], 1),
            "reader_rss_growth_pct": round(reader, 2)}


def _accounted(counts: dict[str, int], delivered: int) -> bool:
    return (counts["received"] == counts["processed"] + counts["dropped"] + counts["queued"]
            and counts["received"] == delivered)


def bench_soak(seconds: float) -> dict:
    warm_up()
    uri = f"oni:{SCENE / 'reference.oni'}?loop=1&rate=auto"
    sources: list[DepthSource] = []

    def camera() -> DepthSource:
        source = open_depth(uri)
        sources.append(source)
        return source

    def rss() -> tuple[float, float]:
        reader = getattr(sources[-1], "pid", None)
        return _rss_mb(os.getpid()), _rss_mb(reader) if reader else 0.0

    with tempfile.TemporaryDirectory() as tmp, InProcess(camera, Path(tmp)) as rig:
        rig.do("capture office")
        rig.expect("CAPTURED", 10)
        rig.do("watch office")
        rig.expect("HEARTBEAT", 5, state="WATCHING")
        samples, gaps, _ = _soak_loop(rig.sim, seconds, rss, rig.service.frame_counts)
        counts = rig.service.frame_counts()
        delivered = sum(s.stats.delivered for s in sources)
        checks = rig.service.counters["watch_checks"]
    growth = _rss_growth(samples, seconds * 0.1)
    return {"seconds": round(seconds), **{k: v for k, v in growth.items()
                                          if k in ("rss_start_mb", "rss_end_mb", "rss_growth_pct",
                                                   "reader_rss_start_mb", "reader_rss_end_mb")},
            "longest_heartbeat_gap_s": round(max(gaps), 3), "frames": counts,
            "source_delivered": delivered, "accounted": _accounted(counts, delivered),
            "watch_checks": checks, "camera_losses": rig.service.camera_losses}


def _readers(pid: int) -> list[int]:
    """The daemon's reader children (``python -c`` running a backend's ``reader_entry``,
    hw.supervised)."""
    out = []
    for child in _children(pid):
        try:
            if b"reader_entry" in Path(f"/proc/{child}/cmdline").read_bytes():
                out.append(child)
        except OSError:
            pass
    return out


def soak_daemon(seconds: float, warmup: float | None = None, camera: str = "oni",
                compress: bool = True, check_every: float = 0.0) -> dict:
    """``robot-change run`` as a subprocess watching the looped reference.oni at 30 fps for
    ``seconds`` (counted from WATCHING), then SIGTERM; ``camera="realsense"``: the same frames
    as a RealSense recording written by librealsense, played by it (``realsense:FILE``);
    ``camera="bag"``: that recording read in the daemon by the bag backend (``rosbag:FILE``).  RSS
    growth is from ``warmup`` s (default: 10 % of the run, at least 10 s) to the end.  Returns
    the figures as a dict (``accounted``: received == processed + dropped + queued == the
    source's delivered; ``reader_cpu_pct``: the reader's CPU time over the soak, % of one
    core; for ``bag``, the CPU of its reads in the camera thread over the time since the source
    opened).  ``compress``: the RealSense recording's depth as compressedDepth PNG (librealsense's
    default), else raw.  ``check_every``: a CHECK (then WATCH again) every that many seconds."""
    warmup = max(10.0, 0.1 * seconds) if warmup is None else warmup
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        source = None
        if camera in ("realsense", "bag"):
            from hw.oni import read_oni_frames
            from hw.realsense_record import write_realsense_recording

            write_realsense_recording(tmp / "room.db3", read_oni_frames(SCENE / "reference.oni"),
                                      compress=compress)
            scheme = "realsense" if camera == "realsense" else "rosbag"
            source = f"{scheme}:{tmp / 'room.db3'}?loop=1&rate=30"
        daemon = Daemon(tmp, observe=tmp / "counts.json", source=source)
        code: int | None = None
        readers: set[int] = set()
        try:
            ready_s = daemon.wait_ready()
            log = open(tmp / "base.log", "w")
            sim = BaseSim(FdPort(daemon.master), out=log)
            if not sim.pump(10, until=lambda: sim.link.state.value == "up"):
                raise RuntimeError("the link to the daemon did not come up in 10 s")
            sim.command("capture office")
            if not sim.expect("CAPTURED", {}, 15):
                raise RuntimeError("no CAPTURED within 15 s")
            sim.command("watch office")
            if not sim.expect("HEARTBEAT", {"state": "WATCHING"}, 5):
                raise RuntimeError("no HEARTBEAT state=WATCHING within 5 s")

            def rss() -> tuple[float, float]:
                now = _readers(daemon.proc.pid)
                readers.update(now)
                return _rss_mb(daemon.proc.pid), sum(_rss_mb(r) for r in now)

            cpu_start = {pid: _cpu_seconds(pid) for pid in _readers(daemon.proc.pid)}
            soak_start = time.monotonic()
            samples, gaps, seen = _soak_loop(sim, seconds, rss, check_every=check_every)
            soak_wall = time.monotonic() - soak_start
            reader_cpu = sum(_cpu_seconds(pid) - cpu_start.get(pid, 0.0)
                             for pid in _readers(daemon.proc.pid))
            log.close()
        finally:
            stopped = time.monotonic()
            code = daemon.stop()
            stop_s = time.monotonic() - stopped
        try:
            counts = json.loads((tmp / "counts.json").read_text())
        except (OSError, ValueError) as exc:
            raise RuntimeError(f"the daemon wrote no frame counts ({exc}); exit status {code}; "
                               f"log: {(tmp / 'daemon.log').read_text()[-2000:]}") from None
        daemon_log = (tmp / "daemon.log").read_text()
    frames, delivered = counts["frames"], counts["source_delivered"]
    read_cpu_pct = 100 * counts["read_cpu_s"] / max(counts["read_wall_s"], 1e-9)
    if camera == "bag":  # the reader is the camera thread's reads, not a process
        reader_cpu = read_cpu_pct / 100 * soak_wall
    return {"seconds": round(seconds), "warmup_s": warmup, "ready_s": round(ready_s, 2),
            **_rss_growth(samples, warmup), "reader_pids": len(readers),
            "longest_heartbeat_gap_s": round(max(gaps), 3),
            "heartbeat_states": seen["states"], "messages": seen["messages"],
            "camera": camera, "compressed": compress,
            "reader_cpu_pct": round(100 * reader_cpu / soak_wall, 2),
            "read_cpu_pct": round(read_cpu_pct, 2),
            "frames": frames, "source_delivered": delivered,
            "source_dropped": counts["source_dropped"], "accounted": _accounted(frames, delivered),
            "sources_opened": counts["sources_opened"], "camera_losses": counts["camera_losses"],
            "watch_checks": counts["counters"].get("watch_checks"),
            "check_every_s": check_every, "counters": counts["counters"],
            "rss_minutely_mb": [round(r[1], 1) for r in samples[::60]],
            "exit_status": code, "stop_s": round(stop_s, 2),
            "daemon_log_tail": daemon_log[-2000:]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--ready-runs", type=int, default=3)
    parser.add_argument("--cold-runs", type=int, default=2)
    parser.add_argument("--cpu-seconds", type=float, default=20.0)
    parser.add_argument("--soak-seconds", type=float, default=0.0,
                        help="soak duration (0: no soak; the issue's target is 600)")
    parser.add_argument("--only", default="latency,ready,cpu,soak")
    parser.add_argument("--soak-camera", choices=("oni", "realsense", "bag"), default="oni",
                        help="soak-daemon's camera: the looped .oni through OpenNI2, or the same "
                        "frames as a RealSense recording through librealsense or the bag "
                        "backend")
    parser.add_argument("--soak-raw", action="store_true",
                        help="with --soak-camera realsense / bag: the recording's depth raw, "
                        "not PNG")
    parser.add_argument("--soak-check-every", type=float, default=0.0,
                        help="soak-daemon: a CHECK (then WATCH again) every this many seconds")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)  # the service's PAUSE warnings are expected here
    only = set(args.only.split(","))
    result: dict = {"load_avg_1min_start": os.getloadavg()[0]}
    if "latency" in only:
        result["latency"] = bench_latency(args.trials)
    if "ready" in only:
        result["ready"] = bench_ready(args.ready_runs)
    if "ready-cold" in only:
        result["ready_cold"] = bench_ready_cold(args.cold_runs)
    if "cpu" in only:
        result["cpu"] = bench_cpu(args.cpu_seconds)
    if "soak" in only and args.soak_seconds > 0:
        result["soak"] = bench_soak(args.soak_seconds)
    if "soak-daemon" in only and args.soak_seconds > 0:
        result["soak_daemon"] = soak_daemon(args.soak_seconds, camera=args.soak_camera,
                                            compress=not args.soak_raw,
                                            check_every=args.soak_check_every)
    result["load_avg_1min_end"] = os.getloadavg()[0]
    print(json.dumps(result, indent=None if args.json else 2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
